"""Register measured 3D circles and lines to the CAD model: the part's pose and its covariance.

The stereo chain measures edges in the rig (left camera) frame; tolerances
are defined in the part (STEP) frame. :func:`register` finds the rigid
``part_to_camera`` transform and which CAD feature each measured one is,
with no pose given: pose hypotheses from pairs of features, scored by the
number of measured features each explains (:mod:`.pose_search`); the best
distinct ones refined by weighted least squares on the datum features,
each weighted by its covariance, which also gives the pose covariance
(:mod:`.pose_refine`). When other distinct poses explain the data about as
well (:mod:`.ties`) and the CAD model maps onto itself under the turns
between them, they give the same characteristics and the best is taken
(``symmetry``); where it does not, the measured features are symmetric but
the model is not, and each such pose is kept, refined with its own
assignment, as a :class:`~partinspect.cad.ties.CompetingPose`
(``competing``): what depends on which is right cannot be decided, the rest
can (:mod:`partinspect.tolerances.ambiguity`). When the datums give fewer
than six independent constraints, or the refinement does not converge,
:class:`RegistrationError` is raised.

:meth:`Registration.features_in_part_frame` transforms the measured
features to the part frame to first order, their covariance including the
pose's and, for datum features, their cross-covariance with the pose
estimate [1]_; the covariance between two transformed features through the
shared pose is :meth:`Registration.cross_covariance`, and between a
transformed feature and the pose error :meth:`Registration.pose_covariance`.

References
----------
.. [1] JCGM 100:2008 (GUM), section 5.2: correlated input quantities.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from partinspect.cad.feature_params import FeatureParams
from partinspect.cad.pose_refine import calibration_response, pose_matrix, solve_pose
from partinspect.cad.pose_search import (
    RegistrationError,
    axis_cov,
    cad_arrays,
    distinct_best,
    initial_poses,
    line_extent,
    measured_arrays,
    unit,
)
from partinspect.cad.ties import (
    AMBIGUITY_RATIO,
    CompetingPose,
    ambiguity_words,
    competing_pose,
    competing_poses,
    feature_order,
    first_hint_first,
    model_symmetry,
    unmatched_under,
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
    pose_cov_scale : float
        The factor the features' part of ``pose_cov`` carries for a misfit
        beyond chance: ``chi2 / dof`` (``weighted_rms`` squared, the Birge
        ratio squared) when ``chi2`` is beyond chance on ``dof``, else 1
        (:func:`partinspect.cad.pose_refine.misfit_scale`).
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
    pose_cov_scale: float = 1.0
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

    def cad_ids(self, features, kind):
        """CAD id of each matched measured feature, keyed by its index in ``features``.

        Parameters
        ----------
        features : sequence
            The measured features in the chain's order (each with ``kind``),
            lines and circles together, as registered.
        kind : {"line", "circle"}
            Circles and arcs are the measured features whose kind is not "line".

        Returns
        -------
        dict of int to str
        """
        at = [k for k, f in enumerate(features) if (f.kind == "line") == (kind == "line")]
        return {at[i]: cid for i, cid in self.assignment[kind].items()}

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

    def pose_covariance(self, pf):
        """Covariance between a PartFeature's parameters and the pose error ``xi``.

        Parameters
        ----------
        pf : PartFeature
            One of :meth:`features_in_part_frame`.

        Returns
        -------
        ndarray, shape (len(pf.params), 6)
            ``Cov(p, xi) = A K + B S``, part frame (mm and unit-vector
            components against rad and mm): ``p = A m + B xi`` to first
            order (:meth:`features_in_part_frame`), ``S`` the pose
            covariance and ``K = Cov(m, xi)`` the measured rig parameters'
            cross-covariance with the pose estimate, non-zero for a datum
            (the pose was fitted to it) and through the calibration's shared
            error [1]_. Together with ``pf.param_cov`` and ``S`` it is the
            joint covariance of ``(p, xi)``, so the feature's error given
            the pose is ``Cov(p, xi) S^-1 xi`` plus a part independent of
            it (:func:`partinspect.tolerances.fusion.given_pose`).
        """
        out = pf.pose_jacobian @ self.pose_cov
        K = self._pose_cross(pf.kind, pf.index)
        if K is not None:
            out = out + self._rig_to_part(pf.kind) @ K
        return out

    def calibration_part(self, pf):
        """A PartFeature's response to the calibration's principal directions, part frame, shape (n, q).

        ``A G + B dxi/de``: the feature's own (``G``, rig frame, turned into
        the part frame by ``A``) and through the pose, which the same error
        moves (``dxi/de = -JA^T U``, :func:`~partinspect.cad.pose_refine.solve_pose`).
        With ``e`` the calibration's error in those directions (Cov(e) = I)
        this is the part of the feature's error that every measurement made
        with the same calibration shares; q = 0 where the calibration states
        no covariance.
        """
        G = calibration_response(pf.kind, self.measured_feature(pf.kind, pf.index))
        H = self._rig_to_part(pf.kind) @ G
        fit = self._fit
        if fit is not None and G.shape[1] and fit["U"].shape[1] == G.shape[1]:
            H = H - pf.pose_jacobian @ (fit["JA"].T @ fit["U"])
        return H

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
        results = first_hint_first(results, hyps[0])
    symmetry, rivals = competing_poses(results, cad)
    r = results[0]
    if datum_set is None:
        # The tie was judged before: leaving features out of the competing
        # hypotheses could make a wrong one fit as well as the right one.
        r = solve_pose(r["T"], circles, lines, meas, cad, None, exclude_outliers=True)
        rivals = [solve_pose(o["T"], circles, lines, meas, cad, None, exclude_outliers=True) for o in rivals]
    competing = tuple(competing_pose(_registration(o, cad, circles, lines, len(hyps)), r, cad) for o in rivals)
    words = ambiguity_words(r, rivals, competing) if competing else ""
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
        pose_cov_scale=r["cov_scale"],
        outliers=r["outliers"],
        symmetry=symmetry,
        competing=competing,
        ambiguity=ambiguity,
        _circles=circles,
        _lines=lines,
        _fit={"JA": r["JA"], "U": r["U"], "rows": r["rows"]},
    )
