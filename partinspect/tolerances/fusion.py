"""One part seen in several views: each feature's measurements checked against each other and combined.

Each view's chain and registration give its measured features in the part
frame, each with a covariance that includes that view's pose covariance
(:meth:`~partinspect.cad.registration.Registration.features_in_part_frame`).
A CAD feature measured in several views has several such estimates. They
are compared in a minimal parametrisation about the nominal feature
(:func:`reduce`): a circle by its centre, the tilt of its normal and its
radius (6 numbers), a line by its offset and slope where it crosses the
plane through the nominal midpoint normal to it (4 numbers), so that the
arbitrary point along a line and the sign of an axis do not count as
differences.

The test (:func:`consistent_views`): each view's estimate against the
combination of the others, ``chi2 = d^T (C_v + C_others)^-1 d`` with ``d``
their difference; the views' errors are independent (separate images,
separate pose estimates), so the difference's covariance is the sum. A
view beyond the ``significance`` quantile of chi-square (as many degrees
of freedom as parameters) disagrees beyond chance: the worst such is left
out for that feature and named, and the test repeated. Of two views that
disagree neither is more suspect by the test alone: the one the caller
ranks lower (e.g. the worse registration fit) is left out.

Whole views are tested before (:func:`consistent_view_set`): a view's pose
error against the features it shares with the others, in the directions of
its pose those features determine (:func:`view_motion`,
:func:`motion_test`), each feature's error taken given the pose
(:func:`given_pose`) [3]_ [5]_, and their residuals one by one [6]_.

The consistent estimates are combined by generalised least squares,
``C = (sum C_v^-1)^-1``, ``y = C sum C_v^-1 y_v`` (:func:`combine`) [1]_;
a circle's radius is weighted apart from its centre and axis
(``SIZE_APART``), the combination's covariance still the full one of the
weighted sum.

Two combined features are correlated where the same view measured both,
through its pose: ``Cov(y_a, y_b) = sum_v W_av K_v W_bv^T`` with ``W`` the
weights and ``K_v`` the view's cross-covariance of the two
(:meth:`~partinspect.cad.registration.Registration.cross_covariance`); a
distance between features seen in different views carries both views'
pose uncertainty in full (:mod:`.evaluate_fused`).

Views taken with one rig calibration share its error: each feature's
response to it, ``H_v`` (:meth:`~partinspect.cad.registration.Registration.calibration_part`,
part frame), is common to every view, so the combination's covariance gains
``sum_{v != w} W_v J_v H_v H_w^T J_w^T W_w^T`` (the shared part does not
average down) and two combined features the same cross-view terms. The
weights and the consistency tests still take the views as independent
(the test is then a little lenient where the shared part would cancel in
a difference). Views with different calibrations (a rig recalibrated or
corrected for drift between them) are independent. Edge points are not
merged across views.

References
----------
.. [1] Aitken, A. C. (1935). On least squares and linear combination of
       observations. Proc. Royal Society of Edinburgh 55, 42-48.
.. [2] JCGM 100:2008 (GUM), 5.2: correlated input quantities; JCGM
       101:2008, 5.6 and 6: propagation of distributions, the first-order
       (linear) law for a vector measurand.
.. [3] Anderson, T. W. (2003). An Introduction to Multivariate Statistical
       Analysis, 3rd ed., Wiley, theorem 2.5.1: the conditional
       distribution of a multivariate normal vector.
.. [4] Higham, N. J. (1988). Computing a nearest symmetric positive
       semidefinite matrix. Linear Algebra and its Applications 103,
       103-118.
.. [5] Teunissen, P. J. G. (2000). Testing Theory: an Introduction. Delft
       University Press, chapter 3: the generalised likelihood ratio test of
       a hypothesis of q dimensions, chi-square on q degrees of freedom.
.. [6] Baarda, W. (1968). A Testing Procedure for Use in Geodetic Networks.
       Netherlands Geodetic Commission, Publications on Geodesy 2(5): data
       snooping, one observation at a time, worst first.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from partinspect.cad.feature_params import FeatureParams
from partinspect.frames import orthonormal_frame
from partinspect.tolerances.evaluate import pick_feature

__all__ = ["SIGNIFICANCE", "VIEW_P", "SIZE_APART", "FusedFeature", "reduce", "expand", "combine",
           "consistent_views", "DETERMINED", "given_pose", "pose_information",
           "motion_test", "view_motion", "consistent_view_set", "fuse_feature", "fuse", "fused_cross_covariance"]

SIGNIFICANCE = 0.99
"""Probability that a consistent view passes the test (per view and feature)."""

SIZE_APART = ((0, 5), (5, 6))
"""A circle's reduced parameters weighted in two blocks: centre and axis, and
the radius on its own. Within one view the radius is correlated with the
centre's depth and the axis through the ellipse fit and the rim's
systematic displacement, the part of the error model least sure of its
correlations; weighting by them lets views correct each other's radius
through their centres. The weights leave them out; the combined covariance
keeps them (:func:`combine`)."""

_STEP = 1e-7


def _frame(nominal):
    """The nominal axis (circle normal or line direction), two unit vectors across it, and the reference point."""
    if nominal.kind == "line":
        a, b = np.asarray(nominal.start, float), np.asarray(nominal.end, float)
        axis, ref = (b - a) / np.linalg.norm(b - a), 0.5 * (a + b)
    else:
        axis, ref = np.asarray(nominal.normal, float), np.asarray(nominal.center, float)
    e1, e2, n = orthonormal_frame(axis)
    return e1, e2, n, ref


def reduce(kind, params, nominal):
    """A measured feature's parameters in the minimal form the views are compared in.

    Parameters
    ----------
    kind : {"circle", "line"}
    params : ndarray, shape (7,) or (6,)
        ``(center, normal, radius)`` or ``(point, direction)``, part frame.
    nominal : Feature-like
        The CAD feature (``kind``, ``center``/``normal`` or ``start``/``end``).

    Returns
    -------
    ndarray, shape (6,) or (4,)
        Circles: centre (mm), the normal's components across the nominal
        normal, radius (mm). Lines: the offset (mm) across the nominal line
        where the measured one crosses the plane through the nominal
        midpoint normal to it, and its slope (dimensionless) across it.
        The axis's sign is taken from the nominal one.
    """
    e1, e2, n, ref = _frame(nominal)
    x = np.asarray(params, float)
    axis = x[3:6] / np.linalg.norm(x[3:6])
    axis = axis if axis @ n >= 0 else -axis
    if kind == "circle":
        return np.r_[x[:3], axis @ e1, axis @ e2, x[6]]
    q = x[:3] + ((ref - x[:3]) @ n) / (axis @ n) * axis - ref
    return np.array([q @ e1, q @ e2, (axis @ e1) / (axis @ n), (axis @ e2) / (axis @ n)])


def expand(kind, y, nominal):
    """The inverse of :func:`reduce`: full parameters (part frame) from the minimal ones."""
    e1, e2, n, ref = _frame(nominal)
    if kind == "circle":
        tilt = y[3] * e1 + y[4] * e2
        return np.r_[y[:3], tilt + np.sqrt(max(1.0 - tilt @ tilt, 0.0)) * n, y[5]]
    axis = n + y[2] * e1 + y[3] * e2
    return np.r_[ref + y[0] * e1 + y[1] * e2, axis / np.linalg.norm(axis)]


def _jacobian(f, x):
    x = np.asarray(x, float)
    cols = []
    for i in range(x.size):
        e = np.zeros(x.size)
        e[i] = _STEP
        cols.append((f(x + e) - f(x - e)) / (2 * _STEP))
    return np.stack(cols, axis=1)


def _reduced(part, nominal):
    """A measured feature's minimal parameters about its nominal, their Jacobian and covariance."""
    J = _jacobian(lambda x: reduce(part.kind, x, nominal), part.params)
    return reduce(part.kind, part.params, nominal), J, J @ part.param_cov @ J.T


def combine(ys, covs, blocks=None):
    """Generalised least-squares combination of independent estimates of one quantity.

    Parameters
    ----------
    ys : sequence of ndarray, shape (n,)
    covs : sequence of ndarray, shape (n, n)
        Each positive definite.
    blocks : sequence of (int, int), optional
        Index ranges combined each on its own: the weights come from the
        covariances' diagonal blocks, the correlations between blocks left
        out of the weighting (but not of the result's covariance). None:
        one block, the full GLS.

    Returns
    -------
    y : ndarray, shape (n,)
    cov : ndarray, shape (n, n)
        ``sum W_i C_i W_i^T``: with one block ``(sum C_i^-1)^-1``.
    weights : list of ndarray, shape (n, n)
        ``y = sum W_i y_i``; ``W_i = (sum B_j^-1)^-1 B_i^-1`` with ``B_i``
        the block-diagonal part of ``C_i``.
    """
    n = len(ys[0])
    mask = np.zeros((n, n), bool)
    for a, b in blocks or [(0, n)]:
        mask[a:b, a:b] = True
    infos = [np.linalg.inv(np.where(mask, C, 0.0)) for C in covs]
    total = np.linalg.inv(sum(infos))
    weights = [total @ I for I in infos]
    cov = sum(W @ C @ W.T for W, C in zip(weights, covs))
    return sum(W @ y for W, y in zip(weights, ys)), 0.5 * (cov + cov.T), weights


def _chi2_quantile(p, dof):
    # chdtri is what scipy.stats.chi2.ppf calls (isf at 1 - p), without scipy.stats' import time.
    from scipy.special import chdtri

    return float(chdtri(dof, 1.0 - p))


def consistent_views(ys, covs, rank=None, significance=SIGNIFICANCE):
    """Which estimates agree within chance; the others left out, worst first, with their test.

    Parameters
    ----------
    ys, covs : sequences of ndarray
        Independent estimates of one quantity and their covariances.
    rank : sequence of float, optional
        Lower is trusted more; decides which of two disagreeing estimates
        is left out. Default: the order given.
    significance : float
        A consistent estimate passes with this probability.

    Returns
    -------
    kept : list of int
    rejected : list of dict
        ``{"index", "chi2", "dof", "threshold", "pair"}``; ``pair`` True
        when two disagreed and ``rank`` chose.
    """
    kept = list(range(len(ys)))
    rank = list(range(len(ys))) if rank is None else list(rank)
    dof = len(ys[0])
    threshold = _chi2_quantile(significance, dof)
    rejected = []
    while len(kept) >= 2:
        tests = []
        for i in kept:
            others = [j for j in kept if j != i]
            y_o, C_o, _ = combine([ys[j] for j in others], [covs[j] for j in others])
            d = ys[i] - y_o
            tests.append((float(d @ np.linalg.solve(covs[i] + C_o, d)), i))
        worst, i = max(tests)
        if worst <= threshold:
            break
        pair = len(kept) == 2
        if pair:
            i = max(kept, key=lambda j: (rank[j], j))
        rejected.append({"index": i, "chi2": worst, "dof": dof, "threshold": threshold, "pair": pair})
        kept.remove(i)
    return kept, rejected


@dataclass(frozen=True, eq=False)
class FusedFeature(FeatureParams):
    """A CAD feature's measurement combined over the views that agree (part frame).

    Has the attributes of a
    :class:`~partinspect.cad.registration.PartFeature` that
    :mod:`.evaluate` reads, so a characteristic is evaluated on it as on
    one view's feature.

    Attributes
    ----------
    kind : {"circle", "line"}
    cad_id : str
    params : ndarray, shape (7,) or (6,)
    param_cov : ndarray
        Its covariance, each view's pose covariance included.
    views : tuple of int
        The views combined (indices into the caller's list).
    rejected : tuple of dict
        Views left out: ``{"view", "chi2", "dof", "threshold", "reason"}``.
    start, end : ndarray, shape (3,) or None
        Lines: the union of the views' measured extents on the combined line.
    contributions : tuple
        ``(view, PartFeature, J, W)`` per view combined: ``J`` the
        derivative of :func:`reduce` at its parameters, ``W`` its weight.
    shared : tuple
        Per contribution, ``W J H``: its part of the combination's response
        to the shared calibration error (empty when not shared).
    expand_jacobian : ndarray
        Derivative of :func:`expand` at the combined minimal parameters.
    """

    kind: str
    cad_id: str
    params: np.ndarray
    param_cov: np.ndarray
    views: tuple
    rejected: tuple = ()
    start: np.ndarray | None = None
    end: np.ndarray | None = None
    contributions: tuple = field(default=(), repr=False)
    expand_jacobian: np.ndarray | None = field(default=None, repr=False)
    shared: tuple = field(default=(), repr=False)
    index: int = 0
    datum: bool = False
    points = None
    point_covs = None


def _shared_terms(parts):
    """``sum_{i != j} X_i X_j^T`` of the parts ``X_i = W_i J_i H_i``, each (n, q)."""
    total = sum(parts)
    return total @ total.T - sum(X @ X.T for X in parts)


def fuse_feature(cad_id, nominal, measured, rank=None, significance=SIGNIFICANCE, calibration_parts=None):
    """One CAD feature's views tested for consistency and the agreeing ones combined.

    Parameters
    ----------
    cad_id : str
    nominal : Feature-like
        The CAD feature.
    measured : sequence of (int, PartFeature)
        Each view that measured it, and its measurement (part frame,
        ``params`` and ``param_cov`` with the view's pose covariance).
    rank : mapping int -> float, optional
        Per view, lower trusted more (see :func:`consistent_views`).
    significance : float
    calibration_parts : sequence of ndarray, shape (n, q), optional
        Per measurement, its response to the calibration error the views
        share (:meth:`~partinspect.cad.registration.Registration.calibration_part`);
        None: the views' errors are independent.

    Returns
    -------
    FusedFeature
    """
    kind = measured[0][1].kind
    red = [_reduced(p, nominal) for _, p in measured]
    ys = [y for y, _, _ in red]
    covs = [C for _, _, C in red]
    views = [v for v, _ in measured]
    kept, rejected = consistent_views(ys, covs, None if rank is None else [rank[v] for v in views], significance)
    y, C, W = combine([ys[i] for i in kept], [covs[i] for i in kept], SIZE_APART if kind == "circle" else None)
    shared = ()
    if calibration_parts is not None and calibration_parts[0].shape[1]:
        shared = tuple(w @ red[i][1] @ calibration_parts[i] for i, w in zip(kept, W))
        C = C + _shared_terms(shared)
    E = _jacobian(lambda z: expand(kind, z, nominal), y)
    params = expand(kind, y, nominal)
    cov = E @ C @ E.T
    start = end = None
    if kind == "line":
        s = [float((e - params[:3]) @ params[3:6]) for i in kept for e in (measured[i][1].start, measured[i][1].end)
             if e is not None]
        if s:
            start, end = params[:3] + min(s) * params[3:6], params[:3] + max(s) * params[3:6]
    out_rej = []
    for r in rejected:
        v = views[r["index"]]
        why = (f"disagrees with the other views beyond chance (chi-square {r['chi2']:.1f} > {r['threshold']:.1f}, "
               f"{r['dof']} degrees of freedom, {100 * significance:g} %)")
        if r["pair"]:
            why = why.replace("the other views", "the one other view") + "; of the two, this view ranks lower"
        out_rej.append({"view": v, "chi2": r["chi2"], "dof": r["dof"], "threshold": r["threshold"], "reason": why})
    contributions = tuple((views[i], measured[i][1], red[i][1], w) for i, w in zip(kept, W))
    return FusedFeature(kind, cad_id, params, 0.5 * (cov + cov.T), tuple(views[i] for i in kept), tuple(out_rej),
                        start, end, contributions, E, shared)


VIEW_P = 1e-3
"""A whole view is left out when the rigid motion between it and the other
views, or its features' disagreement with theirs, is less likely than this
by chance; a feature within a view is an outlier of that motion below it."""


DETERMINED = 1.0
"""A direction of a view's pose is tested when the features it shares with
the other views carry at least this much information on it, in units of
the pose's own (:func:`pose_information`): the motion they fit in that
direction is then known at least as well as the registration knows the
pose, so a pose error of one standard deviation there adds at least half a
unit to its chi-square. Below it, the fit's own scatter dominates: testing
there adds degrees of freedom that carry noise rather than the pose's error
and dilutes a real error in the directions that are determined."""


def given_pose(cov, cross, pose_cov):
    """A feature's error split into its response to its view's pose error and a part independent of it.

    Parameters
    ----------
    cov : ndarray, shape (n, n)
        Covariance of the feature's parameters (the pose's part included).
    cross : ndarray, shape (n, 6)
        Their covariance with the pose error ``xi``
        (:meth:`~partinspect.cad.registration.Registration.pose_covariance`,
        in the same parameters).
    pose_cov : ndarray, shape (6, 6)
        ``S = Cov(xi)``, rad and mm.

    Returns
    -------
    response : ndarray, shape (n, 6)
        ``G = Cov(p, xi) S^-1``: the error's expectation given ``xi`` is
        ``G xi``.
    rest_cov : ndarray, shape (n, n)
        ``cov - G Cov(p, xi)^T``, the covariance of what is left,
        independent of ``xi``.

    Notes
    -----
    The conditional distribution of jointly normal errors [3]_: with
    ``(p, xi)`` of joint covariance ``[[cov, cross], [cross^T, S]]``, ``p``
    given ``xi`` has mean ``cross S^-1 xi`` and covariance the Schur
    complement, positive semi-definite when the joint covariance is. For a
    datum (the pose was fitted to it) ``G`` is not the motion's effect
    ``B``: its part-frame value is its registration residual, uncorrelated
    with the pose estimate, so ``G`` is near nil; ``cov - B S B^T`` is not
    its covariance given the pose and can be indefinite [2]_.

    The joint covariance is not exactly positive semi-definite: the pose
    fit weights a datum by its point's (centre's) and axis's covariances
    apart (:mod:`partinspect.cad.pose_refine`), so ``Cov(p, xi)`` is that
    of a fit that left out the correlations between the blocks, while
    ``cov`` keeps them. The Schur complement is then projected onto the
    positive semi-definite cone in the feature's parameters scaled by
    ``cov``'s diagonal (so that mm and slopes compare): its negative
    eigenvalues set to zero, the nearest such matrix in the Frobenius norm
    [4]_.
    """
    response = np.linalg.solve(pose_cov, cross.T).T
    rest = cov - response @ cross.T
    scale = np.sqrt(np.diag(cov))
    scale = np.where(scale > 0, scale, 1.0)  # a parameter held exact has no scale to compare by
    w, V = np.linalg.eigh(0.5 * (rest + rest.T) / np.outer(scale, scale))
    rest = (V * np.maximum(w, 0.0)) @ V.T * np.outer(scale, scale)
    return response, rest


def pose_information(responses, covs, pose_cov):
    """What features that respond to a view's pose error tell of it, direction by direction.

    Parameters
    ----------
    responses : sequence of ndarray, shape (n_f, 6)
        Per feature, ``G_f`` (:func:`given_pose`).
    covs : sequence of ndarray, shape (n_f, n_f)
        Per feature, the covariance of its difference's part independent of
        the pose error (its own less the pose's, plus the other views').
    pose_cov : ndarray, shape (6, 6)
        ``S``.

    Returns
    -------
    info : ndarray, shape (6,)
        Eigenvalues, ascending, of the information matrix of the pose error
        whitened by ``S`` (``xi = L z``, ``S = L L^T``):
        ``F = L^T (sum G_f^T E_f^-1 G_f) L``. ``info >= 1``: the features
        know that direction at least as well as ``S`` does.
    directions : ndarray, shape (6, 6)
        Columns ``u_i``, whitened, orthonormal.
    whiten : ndarray, shape (6, 6)
        ``L``.

    Notes
    -----
    The eigenvalues are those of ``A S`` (``A = sum G^T E^-1 G``), whatever
    square root of ``S`` is taken. Weighted least squares in the whitened
    pose error, first order (JCGM 100 5.2, JCGM 101 for the propagation
    [2]_).
    """
    L = np.linalg.cholesky(pose_cov)
    F = sum((G @ L).T @ np.linalg.solve(E, G @ L) for G, E in zip(responses, covs))
    info, U = np.linalg.eigh(0.5 * (F + F.T))
    return info, U, L


def motion_test(diffs, responses, covs, pose_cov, threshold=DETERMINED):
    """A view's pose error tested in the directions its shared features determine; their residuals.

    Parameters
    ----------
    diffs : sequence of ndarray, shape (n_f,)
        Per shared feature, the view's minimal parameters less the other
        views' combination.
    responses, covs, pose_cov
        As :func:`pose_information`.
    threshold : float
        Least information for a direction to be tested (``DETERMINED``).

    Returns
    -------
    dict
        ``chi2``, ``dof`` (directions tested, 0 to 6), ``info`` (the
        information in each of the six directions, ascending), ``motion`` (the fitted pose error in
        those directions, ``xi``, shape (6,)), ``residuals`` (per feature
        ``(r_f, N_f)``: its difference less the motion's effect and that
        residual's covariance).

    Notes
    -----
    The model is ``d_f = G_f xi + e_f``, ``xi = L z`` with ``z`` of unit
    covariance when the view's pose is as stated, ``e_f`` independent of it
    with covariance ``E_f``. With ``F = U diag(info) U^T`` and
    ``g = U^T sum (G_f L)^T E_f^-1 d_f``, ``g_i`` has variance
    ``info_i (1 + info_i)`` and the ``g_i`` are uncorrelated, so
    ``chi2 = sum g_i^2 / (info_i (1 + info_i))`` over the ``dof`` tested
    directions is chi-square on ``dof`` [5]_. Over all six directions it is
    ``delta^T (S + A^-1)^-1 delta`` of the unrestricted fit; a direction of
    small ``info`` adds a degree of freedom whose term is mostly the fit's
    noise. The motion is subtracted in the tested directions only; in the
    others it stays part of each residual's covariance at its prior,
    ``N_f = E_f + G_f L U_o U_o^T L^T G_f^T``. Each residual is judged
    against ``N_f``, its covariance were the motion known (the fit's
    leverage, which makes a residual smaller, is left out: with many
    features it is small, and it makes the test lenient, not strict) [6]_.
    """
    info, U, L = pose_information(responses, covs, pose_cov)
    tested = info >= threshold
    Ws = [G @ L for G in responses]
    g = U.T @ sum(W.T @ np.linalg.solve(E, d) for W, E, d in zip(Ws, covs, diffs))
    chi2 = float(np.sum(g[tested] ** 2 / (info[tested] * (1.0 + info[tested]))))
    Ut, Uo = U[:, tested], U[:, ~tested]
    z = Ut @ (g[tested] / info[tested])
    residuals = [(d - W @ z, E + (W @ Uo) @ (W @ Uo).T) for W, E, d in zip(Ws, covs, diffs)]
    return {"chi2": chi2, "dof": int(tested.sum()), "info": info, "motion": L @ z, "residuals": residuals}


def view_motion(v, others, view_parts, registrations, inventory, p_outlier=VIEW_P, threshold=DETERMINED):
    """One view's pose against the others, from the features they share, and its features' residuals.

    Each shared feature's difference ``d_f`` (view ``v``'s minimal
    parameters less the other views' combination) is modelled as
    ``G_f xi + e_f``: ``xi`` the view's pose error (6 parameters as in
    :mod:`partinspect.cad.pose_refine`), ``G_f`` its feature's error's
    response to it given the registration (:func:`given_pose`) and ``e_f``
    the rest of its error and the others', independent of ``xi``. The pose
    error is tested only in the directions the shared features determine
    (:func:`motion_test`, ``threshold``): a datum's part-frame value is its
    registration residual, uncorrelated with the pose (``G`` near nil), so a
    view whose shared features are all its datums has no direction tested
    and its motion is not fitted at all; its features are then judged as
    residuals. Features whose residual is less likely than ``p_outlier``
    are left out one by one, worst first, and the test repeated (a rim the
    model misjudges must not pass for a moved view).

    Returns
    -------
    dict or None
        ``chi2``, ``dof`` (directions tested), ``p`` (1 when none is),
        ``info`` (the information in each direction, :func:`motion_test`), ``shared`` (features), ``outliers``
        (their ids); None with fewer than 3 shared features.
    """
    from scipy.special import chdtrc

    S = registrations[v].pose_cov
    rows = []
    for f in inventory.features:
        mine = pick_feature(view_parts[v], f.id)
        theirs = [p for u in others if (p := pick_feature(view_parts[u], f.id)) is not None]
        if mine is None or not theirs or any(p.kind != mine.kind for p in theirs):
            continue
        y, J, C = _reduced(mine, f)
        reds = [_reduced(p, f) for p in theirs]
        y_o, C_o, _ = combine([r[0] for r in reds], [r[2] for r in reds])
        G, rest = given_pose(C, J @ registrations[v].pose_covariance(mine), S)
        rows.append((f.id, y - y_o, G, rest + C_o))
    if len(rows) < 3:
        return None
    keep = list(range(len(rows)))
    while True:
        t = motion_test(*([rows[i][k] for i in keep] for k in (1, 2, 3)), S, threshold)
        tests = [(float(chdtrc(len(r), r @ np.linalg.solve(N, r))), i) for (r, N), i in zip(t["residuals"], keep)]
        p, worst = min(tests)
        if p >= p_outlier or len(keep) <= 3:
            break
        keep.remove(worst)
    return {"chi2": t["chi2"], "dof": t["dof"], "p": float(chdtrc(t["dof"], t["chi2"])) if t["dof"] else 1.0,
            "info": t["info"], "shared": len(rows), "outliers": [rows[i][0] for i in range(len(rows)) if i not in keep]}


def consistent_view_set(view_parts, registrations, inventory, rank=None, p_min=VIEW_P):
    """The views that agree with the others as rigid bodies; the others left out, worst first, with the reason.

    A view is left out when :func:`view_motion` finds its pose moved beyond
    chance (``p < p_min``) in the directions the shared features determine,
    or more than half of the features it shares with the others disagree
    with theirs (a bumped camera deforms what it measures, not only moves
    it). The worst view goes first (least ``p``, then the largest share of
    outliers) and the rest are tested again without it: one bad view makes
    the others look bad against it. Of two views that disagree, the one
    ranked lower goes.

    Parameters
    ----------
    view_parts : sequence of list of PartFeature
    registrations : sequence of Registration
    inventory : Inventory
    rank : mapping int -> float, optional
        Lower trusted more (the registrations' weighted RMS).

    Returns
    -------
    kept : list of int
    rejected : list of dict
        ``{"view", "chi2", "dof", "p", "reason"}``.
    """
    kept = list(range(len(view_parts)))
    rank = {v: v for v in kept} if rank is None else rank
    rejected = []
    while len(kept) >= 2:
        tests = []
        for v in kept:
            t = view_motion(v, [u for u in kept if u != v], view_parts, registrations, inventory)
            if t is not None and (t["p"] < p_min or 2 * len(t["outliers"]) > t["shared"]):
                tests.append((-t["p"], len(t["outliers"]) / t["shared"], v, t))
        if not tests:
            break
        _, _, v, t = max(tests)
        if len(kept) == 2:
            v = max(kept, key=lambda j: (rank[j], j))
            t = next((x for *_, u, x in tests if u == v), t)
        p_text = f"p = {t['p']:.1e}" if t["p"] >= 1e-12 else "p < 1e-12"
        moved = f"moved against {'the one other view' if len(kept) == 2 else 'the others'} beyond chance " \
                f"(chi-square {t['chi2']:.1f} on the {t['dof']} directions of its pose the shared features " \
                f"determine, {p_text})"
        split = f"{len(t['outliers'])} of the {t['shared']} features it shares with them disagree"
        why = (f"{moved}; {split}" if t["p"] < p_min else split) + ": a camera moved since calibrating, or a wrong pose"
        if len(kept) == 2:
            why += "; of the two, this view ranks lower"
        rejected.append({"view": v, "chi2": t["chi2"], "dof": t["dof"], "p": t["p"], "reason": why})
        kept.remove(v)
    return kept, rejected


def fuse(view_parts, inventory, rank=None, significance=SIGNIFICANCE, registrations=None):
    """Every CAD feature measured in any view, combined over its consistent views.

    Parameters
    ----------
    view_parts : sequence of list of PartFeature
        Per view, ``registration.features_in_part_frame()``.
    inventory : Inventory
    rank, significance
        See :func:`fuse_feature`.
    registrations : sequence of Registration, optional
        Per view, when all views were measured with one calibration: its
        error is then shared between them (module notes). None: independent.

    Returns
    -------
    dict
        CAD id -> :class:`FusedFeature`, in the inventory's order.
    """
    out = {}
    for f in inventory.features:
        measured = [(v, p) for v, parts in enumerate(view_parts) if (p := pick_feature(parts, f.id)) is not None]
        if measured:
            parts = None if registrations is None else [registrations[v].calibration_part(p) for v, p in measured]
            out[f.id] = fuse_feature(f.id, f, measured, rank, significance, parts)
    return out


def fused_cross_covariance(a, b, registrations):
    """Covariance between two fused features' parameters, through the views that measured both.

    Parameters
    ----------
    a, b : FusedFeature
    registrations : sequence
        Per view, its Registration (``cross_covariance(pa, pb)``).

    Returns
    -------
    ndarray, shape (len(a.params), len(b.params))
    """
    inner = np.zeros((a.expand_jacobian.shape[1], b.expand_jacobian.shape[1]))
    for ia, (va, pa, Ja, Wa) in enumerate(a.contributions):
        for ib, (vb, pb, Jb, Wb) in enumerate(b.contributions):
            if va == vb:
                inner += Wa @ Ja @ registrations[va].cross_covariance(pa, pb) @ Jb.T @ Wb.T
            elif a.shared and b.shared:
                inner += a.shared[ia] @ b.shared[ib].T  # the calibration error both views share
    return a.expand_jacobian @ inner @ b.expand_jacobian.T
