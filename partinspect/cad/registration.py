"""Register measured 3D circles and lines to the CAD model: the part's pose and its covariance.

The stereo chain measures edges in the rig (left camera) frame; tolerances
are defined in the part (STEP) frame. :func:`register` finds the rigid
``part_to_camera`` transform and which CAD feature each measured one is,
with no pose given: pose hypotheses from pairs of features, scored by the
number of measured features each explains (:mod:`.pose_search`); the best
distinct ones refined by weighted least squares on the datum features,
each weighted by its covariance, which also gives the pose covariance
(:mod:`.pose_refine`). When other distinct poses explain the data about as
well (same score, chi-square within ``AMBIGUITY_RATIO``) and the CAD model
maps onto itself under the turns between them, they give the same
characteristics and the best is taken (``symmetry``); where it does not,
the measured features are symmetric but the model is not, and each such
pose is kept, refined with its own assignment, as a :class:`CompetingPose`
(``competing``): what depends on which is right cannot be decided, the rest
can (:mod:`partinspect.tolerances.ambiguity`). When the datums give fewer
than six independent constraints, or the refinement does not converge,
:class:`RegistrationError` is raised.

:meth:`Registration.features_in_part_frame` transforms the measured
features to the part frame to first order, their covariance including the
pose's and, for datum features, their cross-covariance with the pose
estimate [1]_; the covariance between two transformed features through the
shared pose is :meth:`Registration.cross_covariance`.

References
----------
.. [1] JCGM 100:2008 (GUM), section 5.2: correlated input quantities.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from partinspect.cad.feature_params import FeatureParams
from partinspect.cad.pose_refine import calibration_response, pose_error, pose_matrix, solve_pose
from partinspect.cad.pose_search import (
    MATCH_GATE,
    RegistrationError,
    axis_cov,
    cad_arrays,
    distinct_best,
    initial_poses,
    line_extent,
    measured_arrays,
    same_pose,
    unit,
)

__all__ = [
    "RegistrationError",
    "Registration",
    "CompetingPose",
    "PartFeature",
    "register",
    "rig_params",
    "AMBIGUITY_RATIO",
    "model_symmetry",
    "unmatched_under",
    "feature_order",
]

AMBIGUITY_RATIO = 2.0
"""Two distinct poses whose chi-squares are within this factor (plus a few
units) explain the data equally well."""


@dataclass(frozen=True, eq=False)
class PartFeature(FeatureParams):
    """A measured feature in the part frame, its covariance including the pose's.

    Attributes
    ----------
    kind : {"circle", "line"}
    index : int
        Position in the measured circles or lines given to :func:`register`.
    cad_id : str or None
        The CAD feature it was matched to; None if unmatched.
    datum : bool
        True when it drove the pose refinement.
    params : ndarray, shape (7,) or (6,)
        Circles: ``(center, normal, radius)``; lines: ``(point, direction)``.
        Part frame, mm.
    param_cov : ndarray, shape (7, 7) or (6, 6)
        First-order covariance of ``params``: the measurement's own,
        rotated, plus the pose's, plus their cross-covariance with the pose
        estimate (datum features, and every feature through the
        calibration's shared error).
    pose_jacobian : ndarray, shape (7, 6) or (6, 6)
        d params / d xi (``xi`` as in :mod:`partinspect.cad.pose_refine`).
    start, end : ndarray, shape (3,) or None
        Lines: the measured extent's end points, part frame.
    points : ndarray, shape (M, 3) or None
        The measured edge points, part frame, if the record had them.
    point_covs : ndarray, shape (M, 3, 3) or None
        Their covariances, each including the pose's (the correlation
        between points through the shared pose is not represented).
    """

    kind: str
    index: int
    cad_id: str | None
    datum: bool
    params: np.ndarray
    param_cov: np.ndarray
    pose_jacobian: np.ndarray
    start: np.ndarray | None = None
    end: np.ndarray | None = None
    points: np.ndarray | None = None
    point_covs: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class Registration:
    """The pose of the part in the rig and the feature correspondences.

    Attributes
    ----------
    part_to_camera : ndarray, shape (4, 4)
        ``x_rig = R @ X_part + t``.
    pose_cov : ndarray, shape (6, 6)
        Covariance of the pose error ``xi = (w [rad], v [mm])`` in the part
        frame, ``T_hat = T_true @ D(xi)`` (:mod:`partinspect.cad.pose_refine`).
    assignment : dict
        ``{"circle": {i: cad_id}, "line": {j: cad_id}}``, measured index to
        CAD id.
    unmatched : dict
        ``{"circle": (i, ...), "line": (j, ...)}``: measured features no CAD
        feature explains.
    datums : tuple of str
        CAD ids of the features that drove the refinement.
    rms : float
        Root mean square of the unweighted datum residual distances, mm
        (centre offsets and line offsets at the reference points).
    weighted_rms : float
        ``sqrt(chi2 / dof)``: about 1 when the covariances are honest and the
        part is as modelled.
    chi2 : float
    dof : int
        Number of scalar residuals minus 6.
    n_hypotheses : int
        Pose hypotheses scored.
    outliers : dict
        CAD id -> (chi-square, residuals) of the matched features left out of
        the pose fit as inconsistent with the others (``OUTLIER_P``); empty
        when datums are named.
    symmetry : str
        Where other poses explain the features as well and the CAD model maps
        onto itself under the turns between them (a bolt circle, a square
        plate), which those turns are: any of the poses gives the same
        characteristics, and the best is taken. Empty otherwise.
    competing : tuple of CompetingPose
        Other poses that explain the measured features as well, under turns
        the CAD model does not map onto itself by (the feature that would
        tell them apart not measured); one per class of poses the model's
        own symmetry relates. Empty when the pose is unambiguous.
    ambiguity : str
        Those poses in words, with the features that would tell; empty
        when there are none.
    """

    part_to_camera: np.ndarray
    pose_cov: np.ndarray
    assignment: dict
    unmatched: dict
    datums: tuple
    rms: float
    weighted_rms: float
    chi2: float
    dof: int
    n_hypotheses: int = 0
    outliers: dict = field(default_factory=dict)
    symmetry: str = ""
    competing: tuple = ()
    ambiguity: str = ""
    _circles: tuple = field(default=(), repr=False)
    _lines: tuple = field(default=(), repr=False)
    _fit: object = field(default=None, repr=False)

    @property
    def rotation(self):
        return self.part_to_camera[:3, :3]

    @property
    def translation(self):
        return self.part_to_camera[:3, 3]

    @property
    def poses(self):
        """``part_to_camera`` of this pose and of each competing one: ndarray, shape (1 + n, 4, 4)."""
        return np.stack([self.part_to_camera] + [c.registration.part_to_camera for c in self.competing])

    @property
    def pose_std(self):
        """Standard uncertainties of ``xi``: rad (3) and mm (3)."""
        return np.sqrt(np.diag(self.pose_cov))

    def measured_feature(self, kind, index):
        """The measured record (rig frame) as given to :func:`register`."""
        return (self._circles if kind == "circle" else self._lines)[index]

    def measured_params(self, kind, index):
        """The measured record's stacked rig-frame parameters and covariance (:func:`rig_params`)."""
        return rig_params(kind, self.measured_feature(kind, index))

    def features_in_part_frame(self):
        """Every measured feature in the part frame with its full covariance.

        Returns
        -------
        list of PartFeature
            Circles first (measured order), then lines.

        Notes
        -----
        First order in the pose error ``xi`` and the measurement errors.
        For a measured parameter vector ``m`` (rig) with covariance ``C`` the
        part-frame ``p = A m + B xi`` (``A`` the inverse rotation, ``B`` from
        ``X_hat = X - w x X - v``), so
        ``Cov p = A C A^T + B S B^T + A K B^T + B K^T A^T`` where ``S`` is
        ``pose_cov`` and ``K = Cov(m, xi)``: non-zero for datum features
        (the pose was estimated from them, JCGM 100 5.2) and, through the
        calibration's error that all features share, for every feature
        measured with a calibration that states its uncertainty.
        """
        return [self._part_feature("circle", i) for i in range(len(self._circles))] + [
            self._part_feature("line", j) for j in range(len(self._lines))
        ]

    def cross_covariance(self, a, b):
        """Covariance between the parameters of two PartFeatures via the shared pose.

        Parameters
        ----------
        a, b : PartFeature

        Returns
        -------
        ndarray, shape (len(a.params), len(b.params))
            ``B_a S B_b^T`` plus the feature-pose cross terms and, for two
            different features, ``A_a G_a G_b^T A_b^T``: their image noise is
            independent, the calibration's error they share.
        """
        S = self.pose_cov
        out = a.pose_jacobian @ S @ b.pose_jacobian.T
        if (a.kind, a.index) != (b.kind, b.index):
            Ga = calibration_response(a.kind, self.measured_feature(a.kind, a.index))
            Gb = calibration_response(b.kind, self.measured_feature(b.kind, b.index))
            if Ga.shape[1] and Ga.shape[1] == Gb.shape[1]:
                out = out + self._rig_to_part(a.kind) @ Ga @ Gb.T @ self._rig_to_part(b.kind).T
        Ka, Kb = self._pose_cross(a.kind, a.index), self._pose_cross(b.kind, b.index)
        Aa, Ab = self._rig_to_part(a.kind), self._rig_to_part(b.kind)
        if Ka is not None:
            out = out + Aa @ Ka @ b.pose_jacobian.T
        if Kb is not None:
            out = out + a.pose_jacobian @ Kb.T @ Ab.T
        return out

    # -- internals -------------------------------------------------------

    def _rig_to_part(self, kind):
        Rt = self.rotation.T
        n = 7 if kind == "circle" else 6
        A = np.zeros((n, n))
        A[:3, :3] = Rt
        A[3:6, 3:6] = Rt
        if kind == "circle":
            A[6, 6] = 1.0
        return A

    def _pose_cross(self, kind, index):
        """Cov(measured rig params, xi): from the feature's own rows for a datum, and through the calibration's error.

        ``xi = -JA^T r`` (:func:`~partinspect.cad.pose_refine.solve_pose`) and
        ``Cov(m, r)`` is ``-M L`` on the feature's own rows plus ``G U^T``,
        so ``K = M L JA[rows] - G U^T JA``. None when both are absent.
        """
        fit = self._fit
        if fit is None:
            return None
        G = calibration_response(kind, self.measured_feature(kind, index))
        JA, U = fit["JA"], fit["U"]
        K = None
        if (kind, index) in fit["rows"]:
            rows, M, L = fit["rows"][(kind, index)]
            K = M @ L @ JA[rows]
        if G.shape[1] and U.shape[1] == G.shape[1]:
            shared = -G @ (U.T @ JA)
            K = shared if K is None else K + shared
        return K

    def _part_feature(self, kind, index):
        rec = (self._circles if kind == "circle" else self._lines)[index]
        R, t = self.rotation, self.translation
        m, C = rig_params(kind, rec)
        A = self._rig_to_part(kind)
        p = A @ m
        p[:3] = R.T @ (m[:3] - t)
        B = np.zeros((len(m), 6))
        B[:3, :3] = _skew(p[:3])
        B[:3, 3:] = -np.eye(3)
        B[3:6, :3] = _skew(p[3:6])
        cov = A @ C @ A.T + B @ self.pose_cov @ B.T
        K = self._pose_cross(kind, index)
        if K is not None:
            cross = A @ K @ B.T
            cov = cov + cross + cross.T
        cov = 0.5 * (cov + cov.T)
        start = end = points = point_covs = None
        if kind == "line":
            s0, s1 = line_extent(rec)
            if s0 is not None:
                start, end = p[:3] + s0 * p[3:6], p[:3] + s1 * p[3:6]
        pts = getattr(rec, "points", None)
        if pts is not None:
            pts = np.asarray(pts, float).reshape(-1, 3)
            points = (pts - t) @ R
            pc = getattr(rec, "point_covs", None)
            if pc is not None:
                pc = np.asarray(pc, float).reshape(-1, 3, 3)
                Bp = np.concatenate([_skew_many(points), np.broadcast_to(-np.eye(3), (len(points), 3, 3))], axis=2)
                point_covs = R.T @ pc @ R + Bp @ self.pose_cov @ np.swapaxes(Bp, 1, 2)
        cad = self.assignment.get(kind, {}).get(index)
        datum = self._fit is not None and (kind, index) in self._fit["rows"]
        return PartFeature(kind, index, cad, datum, p, cov, B, start, end, points, point_covs)


@dataclass(frozen=True, eq=False)
class CompetingPose:
    """A pose that explains the measured features as well as the chosen one, the CAD model not being symmetric under the turn.

    Attributes
    ----------
    registration : Registration
        The pose refined on its own assignment of the measured features,
        its covariance and fit statistics.
    angle : float
        Degrees: the rotation between it and the chosen pose.
    shift : float
        mm: how far the CAD features move between the two poses (the
        largest), not the part's arbitrary origin.
    deciding : tuple of str
        CAD ids of the features the turn between the poses puts where the
        model has no feature of their kind and size (or brings one there
        from such a place): measured, any of them would tell the two poses
        apart.
    """

    registration: Registration
    angle: float
    shift: float
    deciding: tuple


def _skew(v):
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def _skew_many(v):
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def rig_params(kind, rec):
    """Stacked rig-frame parameters and their covariance.

    Circles ``(center, normal, radius)`` (7,), lines ``(point, direction)``
    (6,). A record's own ``param_cov`` of that shape (stereo Feature3D) is
    used whole, with the correlations inside the fit; otherwise the blocks
    are assembled and those correlations are neglected, but for the
    calibration's part, which its responses give whole.
    """
    n = 7 if kind == "circle" else 6
    if kind == "circle":
        m = np.r_[np.asarray(rec.center, float), unit(rec.normal), float(rec.radius)]
    else:
        m = np.r_[np.asarray(rec.point, float), unit(rec.direction)]
    full = getattr(rec, "param_cov", None)
    if full is not None and np.shape(full) == (n, n):
        return m, np.asarray(full, float)
    C = np.zeros((n, n))
    C[:3, :3] = rec.covariance
    C[3:6, 3:6] = axis_cov(rec)
    if kind == "circle":
        C[6, 6] = float(rec.radius_std) ** 2
    # The calibration's shared error correlates the blocks too: its part is known whole.
    G = calibration_response(kind, rec)
    block = np.zeros((n, n), bool)
    for sl in (slice(0, 3), slice(3, 6), slice(6, n)):
        block[sl, sl] = True
    return m, C + np.where(block, 0.0, G @ G.T)


def register(measured_circles, measured_lines, inventory, *, datums=None, pose_hint=None):
    """Find the part's pose from measured 3D circles and lines, with its covariance.

    Parameters
    ----------
    measured_circles : sequence
        Records with ``center`` (3,), ``normal`` (3,), ``radius``,
        ``covariance`` (3, 3, centre, mm^2), ``normal_cov`` (3, 3) (or
        ``axis_cov``), ``radius_std``; optional ``points`` (M, 3), ``point_covs`` (M, 3, 3).
        Rig frame (e.g. :class:`partinspect.vision.fit3d.Circle3D`).
    measured_lines : sequence
        Records with ``point``, ``direction``, ``covariance`` (3, 3, of the
        point, zero along the line), ``direction_cov`` (3, 3) (or
        ``axis_cov``); optional
        ``start``, ``end`` (the measured extent), ``points``, ``point_covs``.
        Rig frame.
    inventory : partinspect.cad.features.Inventory
        The CAD features (part frame). Smooth edges are ignored.
    datums : sequence of str, optional
        CAD ids of the features the alignment uses; the others are matched
        and measured relative to it. Default: all matched features.
    pose_hint : ndarray, shape (4, 4) or (n, 4, 4), optional
        A ``part_to_camera`` close enough (within ``MATCH_GATE`` at the
        features) to skip the hypothesis search; several (a registration's
        ``poses``): each is a hypothesis, and ties between them are judged
        as in the search.

    Returns
    -------
    Registration

    Raises
    ------
    RegistrationError
        "alignment is ambiguous: ..." when the datums give fewer than 6
        independent constraints or nothing matches; or the refinement does
        not converge. Distinct poses that explain the data equally well are
        the Registration's ``competing`` ones, not an error.
    """
    circles, lines = tuple(measured_circles), tuple(measured_lines)
    cad = cad_arrays(inventory)
    meas = measured_arrays(circles, lines)
    datum_set = _datum_set(datums, inventory)
    if pose_hint is None:
        hyps = initial_poses(meas, cad, circles, lines)
    else:
        hyps = [h for T in np.asarray(pose_hint, float).reshape(-1, 4, 4)
                for h in initial_poses(meas, cad, circles, lines, T)]
    results = _refined(distinct_best(meas, cad, hyps), circles, lines, meas, cad, datum_set)
    if len(hyps) > 1 and pose_hint is not None:
        results = _first_hint_first(results, hyps[0])
    symmetry, rivals = _competing(results, cad)
    r = results[0]
    if datum_set is None:
        # The tie was judged before: leaving features out of the competing
        # hypotheses could make a wrong one fit as well as the right one.
        r = solve_pose(r["T"], circles, lines, meas, cad, None, exclude_outliers=True)
        rivals = [solve_pose(o["T"], circles, lines, meas, cad, None, exclude_outliers=True) for o in rivals]
    competing = tuple(_competing_pose(_registration(o, cad, circles, lines, len(hyps)), r, cad) for o in rivals)
    words = _ambiguity_words(r, rivals, competing) if competing else ""
    return _registration(r, cad, circles, lines, len(hyps), symmetry, competing, words)


def _datum_set(datums, inventory):
    """The named datums as a set (None: every matched feature); unknown ids refused."""
    datum_set = None if datums is None else set(datums)
    if datum_set is not None:
        unknown = sorted(d for d in datum_set if d not in inventory)
        if unknown:
            raise RegistrationError(f"unknown datum feature(s) {', '.join(unknown)}")
    return datum_set


def _refined(poses, circles, lines, meas, cad, datum_set):
    """Each distinct pose refined (:func:`~partinspect.cad.pose_refine.solve_pose`), best first.

    Best: most features explained, then the least chi-square. A pose whose
    refinement fails is dropped; when all fail, the last failure is raised.
    """
    results = []
    last_error = None
    for R, t in poses:
        try:
            results.append(solve_pose(pose_matrix(R, t), circles, lines, meas, cad, datum_set))
        except RegistrationError as e:
            last_error = e
    if not results:
        raise last_error
    results.sort(key=lambda r: (-r["score"], r["chi2"]))
    return results


def _ties(first, other):
    """Whether refined pose ``other`` explains as many features about as well as ``first`` (``AMBIGUITY_RATIO``)."""
    return (other["score"] == first["score"]
            and other["chi2"] <= AMBIGUITY_RATIO * first["chi2"] + 10.0 * max(1, first["dof"]) ** 0.5)


def _first_hint_first(results, hint):
    """``results`` with the pose refined from the first hint in front when it ties with the best.

    Measured again (another round, features added), tied poses swap places
    on chi-squares that differ by chance; the first hint, the pose chosen
    before, stays the chosen one, so that a CAD id names the same measured
    edge from round to round.
    """
    R, t = hint
    for j, r in enumerate(results):
        if same_pose(R, t, r["T"][:3, :3], r["T"][:3, 3]):
            if j and _ties(results[0], r):
                return [r] + results[:j] + results[j + 1:]
            break
    return results


def _competing(results, cad):
    """The poses that explain as many features about as well as the best, split by the model's symmetry.

    A second distinct pose with the best's score and a chi-square within
    ``AMBIGUITY_RATIO`` (plus a few standard deviations of the chi-square)
    ties with it. Under a turn the CAD model maps onto itself
    (:func:`model_symmetry`), both give the same characteristics: the turn
    is named and the best kept. Otherwise the tie is real and the pose
    competes, unless it is one already kept moved by a symmetry of the model.

    Returns
    -------
    symmetry : str
        What was said of the model's own turns ("" if none).
    rivals : list of dict
        The competing refined poses (:func:`~partinspect.cad.pose_refine.solve_pose`'s results).
    """
    first = results[0]
    turns, rivals = [], []
    for other in results[1:]:
        if other["score"] < first["score"]:
            break
        if same_pose(first["T"][:3, :3], first["T"][:3, 3], other["T"][:3, :3], other["T"][:3, 3]):
            continue
        if not _ties(first, other):
            continue
        turn = model_symmetry(cad, np.linalg.inv(first["T"]) @ other["T"])
        if turn is not None:
            if turn not in turns:
                turns.append(turn)
            continue
        if any(same_pose(o["T"][:3, :3], o["T"][:3, 3], other["T"][:3, :3], other["T"][:3, 3])
               or model_symmetry(cad, np.linalg.inv(o["T"]) @ other["T"]) is not None for o in rivals):
            continue
        rivals.append(other)
    if not turns:
        return "", rivals
    return ("the CAD model maps onto itself under " + ", ".join(turns) + ": the poses those turns relate explain "
            "the features equally well and give the same characteristics; the best fitting one was taken"), rivals


def _competing_pose(reg, best, cad):
    """A :class:`CompetingPose`: ``reg`` and how it differs from the refined pose ``best``.

    Its deciding features are those the turn between them moves where the
    model has nothing like them, either way, and which neither pose matched
    to a measured feature.
    """
    T, T_best = reg.part_to_camera, best["T"]
    e = pose_error(T, T_best)
    # how far the part's features move between the two poses, not its (arbitrary) origin
    pts = np.r_[cad.centers, cad.starts]
    shift = np.linalg.norm(pts @ (T[:3, :3] - T_best[:3, :3]).T + T[:3, 3] - T_best[:3, 3], axis=1).max()
    S = np.linalg.inv(T_best) @ T
    ids = set()
    for M in (S, np.linalg.inv(S)):
        lone_circles, lone_lines = unmatched_under(cad, M)
        ids.update(cad.round_ids[k] for k in lone_circles)
        ids.update(cad.line_ids[k] for k in lone_lines)
    ids -= {cad.round_ids[k] for k in best["circ"].values()} | {cad.line_ids[k] for k in best["lin"].values()}
    ids -= set(reg.assignment["circle"].values()) | set(reg.assignment["line"].values())
    return CompetingPose(reg, float(np.rad2deg(np.linalg.norm(e[:3]))), float(shift), tuple(sorted(ids, key=feature_order)))


def feature_order(fid):
    """Sort key of a CAD id in its number's order: circle-2 before circle-10."""
    kind, _, n = fid.rpartition("-")
    return (kind, int(n)) if n.isdigit() else (fid, 0)


def _ambiguity_words(best, rivals, competing):
    """The tie in words: the poses, the fits, and what would tell them apart."""
    angles = ", ".join(f"{c.angle:.1f}" for c in competing)
    n = len(competing) + 1
    poses = (f"two poses {angles} degrees apart" if n == 2 else f"{n} poses ({angles} degrees from the best fitting)")
    shift = max(c.shift for c in competing)
    chi2 = " vs ".join(f"{r['chi2']:.3g}" for r in [best, *rivals])
    deciding = sorted({fid for c in competing for fid in c.deciding}, key=feature_order)
    tell = (f": {', '.join(deciding)}, which would tell, {'was' if len(deciding) == 1 else 'were'} not measured"
            if deciding else "")
    return (f"{poses} (features moved by up to {shift:.1f} mm) explain the {best['score']} matched features equally "
            f"well (chi-square {chi2}); the measured features are symmetric, the CAD model is not{tell}. "
            "Characteristics that depend on which pose is right are inconclusive; the others are judged")


def unmatched_under(cad, S, tol=MATCH_GATE):
    """The CAD edges that the turn ``S`` puts where the model has no edge like them.

    Parameters
    ----------
    cad : CadArrays
    S : ndarray, shape (4, 4)
        A rigid motion of the part frame onto itself.
    tol : float
        mm: how far a moved edge may lie from its counterpart.

    Returns
    -------
    circles, lines : list of int
        Indices into ``cad.round_ids`` and ``cad.line_ids``: a moved circle
        with no circle of its radius and axis direction within ``tol`` of
        its centre, a moved line with no line whose ends (either way round)
        lie within ``tol`` of its ends. Both empty when the model maps onto
        itself under ``S``.
    """
    R, t = S[:3, :3], S[:3, 3]
    c = cad.centers @ R.T + t
    n = cad.normals @ R.T
    circles = []
    for k in range(len(c)):
        d = np.linalg.norm(cad.centers - c[k], axis=1)
        same = (d < tol) & (np.abs(cad.radii - cad.radii[k]) < tol) & (np.abs(np.einsum("ij,j->i", cad.normals, n[k])) > 0.999)
        if not same.any():
            circles.append(k)
    ends = cad.starts + cad.dirs * cad.lengths[:, None]
    a, b = cad.starts @ R.T + t, ends @ R.T + t
    lines = []
    for k in range(len(a)):
        fwd = np.maximum(np.linalg.norm(cad.starts - a[k], axis=1), np.linalg.norm(ends - b[k], axis=1))
        back = np.maximum(np.linalg.norm(cad.starts - b[k], axis=1), np.linalg.norm(ends - a[k], axis=1))
        if not (np.minimum(fwd, back) < tol).any():
            lines.append(k)
    return circles, lines


def model_symmetry(cad, S, tol=MATCH_GATE):
    """The turn ``S`` (part frame to part frame) as words if it maps every CAD edge onto one, else None.

    Parameters
    ----------
    cad : CadArrays
    S : ndarray, shape (4, 4)
        ``inv(T_best) @ T_other`` of two registered poses: the part moved by
        it is seen by the second pose as the part by the first.
    tol : float
        mm: how far a moved edge may lie from its counterpart (the two poses
        are estimates; ``MATCH_GATE`` is what registration itself accepts).

    Returns
    -------
    str or None
        E.g. "a turn of 60.0 deg about (0.000, 0.000, 1.000) through (45.0, 45.0, 6.0)".
    """
    lone_circles, lone_lines = unmatched_under(cad, S, tol)
    if lone_circles or lone_lines:
        return None
    R, t = S[:3, :3], S[:3, 3]
    from scipy.spatial.transform import Rotation

    from partinspect.cad.features import canonical_direction

    rv = Rotation.from_matrix(R).as_rotvec()
    angle = float(np.linalg.norm(rv))
    # A turn by a about -n is one by -a about n: the axis is named by its sign-free direction.
    axis = canonical_direction(rv) if angle > 0 else np.array([0.0, 0.0, 1.0])
    # A point on the axis: the least-squares solution of (I - R) p = t within the plane normal to the axis.
    p = np.linalg.lstsq(np.eye(3) - R, t, rcond=None)[0]
    p -= (p @ axis) * axis
    p = np.where(np.abs(p) < 0.05, 0.0, p)  # no "-0.0" in the words
    axis = np.where(np.abs(axis) < 5e-4, 0.0, axis)
    return (f"a turn of {np.degrees(angle):.1f} deg about ({axis[0]:.3f}, {axis[1]:.3f}, {axis[2]:.3f}) "
            f"through ({p[0]:.1f}, {p[1]:.1f}, {p[2]:.1f})")


def _registration(r, cad, circles, lines, n_hypotheses, symmetry="", competing=(), ambiguity=""):
    """The :class:`Registration` of a refined pose (:func:`~partinspect.cad.pose_refine.solve_pose`'s result)."""
    return Registration(
        part_to_camera=r["T"],
        pose_cov=r["cov"],
        assignment={"circle": {i: cad.round_ids[k] for i, k in r["circ"].items()}, "line": {j: cad.line_ids[l] for j, l in r["lin"].items()}},
        unmatched={"circle": tuple(i for i in range(len(circles)) if i not in r["circ"]), "line": tuple(j for j in range(len(lines)) if j not in r["lin"])},
        datums=r["datums"],
        rms=r["rms"],
        weighted_rms=float(np.sqrt(r["chi2"] / max(r["dof"], 1))),
        chi2=r["chi2"],
        dof=r["dof"],
        n_hypotheses=n_hypotheses,
        outliers=r["outliers"],
        symmetry=symmetry,
        competing=competing,
        ambiguity=ambiguity,
        _circles=circles,
        _lines=lines,
        _fit={"JA": r["JA"], "U": r["U"], "rows": r["rows"]},
    )
