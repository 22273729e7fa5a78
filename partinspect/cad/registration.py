"""Register measured 3D circles and lines to the CAD model, with the pose's covariance.

The stereo chain measures edges in the rig (left camera) frame; tolerances
are defined in the part (STEP) frame. :func:`register` finds the rigid
``part_to_camera`` transform and which CAD feature each measured feature is,
with no pose given:

1. *Hypotheses.* Every pair of measured circles is compared with every
   ordered pair of CAD circles/arcs whose radii agree (within
   ``RADIUS_GATE``), whose centre distance agrees (``DISTANCE_GATE``) and
   whose normals make the same angle (``ANGLE_GATE``; a measured normal's
   sign is unobservable, so both signs are tried). Each consistent pairing
   gives a rotation by aligning the centre-to-centre vector and the two
   normals (Kabsch / Wahba, ``Rotation.align_vectors``) and a translation
   from the centroids. With fewer than two circles (or when circle pairs
   give nothing) pairs of non-parallel measured lines are matched to CAD
   line pairs with the same angle and common-perpendicular length.
2. *Scoring.* Under each hypothesis pose, a measured circle counts when a
   CAD circle or arc of similar radius lies within ``MATCH_GATE`` of its
   centre with a parallel normal, a measured line when a CAD line runs
   parallel within ``MATCH_GATE`` of both its measured end points and the
   measured stretch lies on the CAD segment (a measured line may cover part
   of an edge). CAD features all of whose faces are planes turned away
   from the camera cannot be seen and never count. The score is the number of
   measured features explained.
3. *Refinement.* Generalised least squares over the six pose parameters, in
   which each measured feature's covariance is its weight: the circle centre
   residual is whitened by its 3x3 covariance, the normal by its 2x2
   covariance in the tangent plane, a line by the 4x4 covariance of its
   offset and slope ``(a, b, alpha, beta)`` in the plane normal to it at its
   reference point (the perpendicular offset of the CAD line from the
   measured line, i.e. the offset of the CAD line's points, in first order).
   Poorly known depth thus pulls the fit little. Radii carry no pose
   information. Only datum features (when ``datums`` are given) enter.
   Without named datums, a feature whose residuals at the refined pose are
   beyond any chance (``OUTLIER_P``) is left out and the pose refined
   again, worst first, at most a quarter of them (a robust best fit): one
   edge paired with a different edge in the other image, or a hole moved
   on the part, would otherwise pull the pose and with it every other
   feature. Such a feature is still assigned and measured against the pose
   the others give, and is listed in ``Registration.outliers``.
4. *Ambiguity.* The best-scoring hypotheses are grouped into distinct poses
   and each is refined; when a second distinct pose explains the data about
   as well (same score, chi-square within a factor ``AMBIGUITY_RATIO``), or
   the datum features give fewer than six independent constraints, or the
   refinement does not converge, :class:`RegistrationError` is raised.

Pose parametrisation and covariance
-----------------------------------
The estimated pose is ``T_hat = T_true @ D(xi)`` with ``D(xi) = [[Rot(w), v],
[0, 1]]``, ``xi = (w, v)``: ``w`` a rotation vector (rad) and ``v`` a
translation (mm), both in the *part* frame, i.e. about the part-frame origin.
``pose_cov`` is the 6x6 covariance of ``xi``, ``(J^T J)^-1`` with ``J`` the
whitened Jacobian of the residuals (first order; it is not scaled by the
chi-square, which is reported as ``weighted_rms`` so that a model mismatch is
seen rather than hidden in an inflated covariance).

Neglected correlations (first-order model): the centre-normal-radius
correlations inside one circle fit and the point-direction correlation of a
line (the fitter reports the line point at the data centroid, where it
vanishes); correlations between different features through the stereo
calibration (a shared scale error; the calibration budget is carried by the
vision side). :meth:`Registration.features_in_part_frame` includes the pose
covariance and, for datum features, their exact first-order
cross-covariance with the pose estimate; the covariance *between* two
transformed features through the shared pose is available from
:meth:`Registration.cross_covariance`.

References
----------
.. [1] Arun, K. S., Huang, T. S., & Blostein, S. D. (1987). Least-squares
       fitting of two 3-D point sets. IEEE PAMI 9(5), 698-700.
.. [2] Umeyama, S. (1991). Least-squares estimation of transformation
       parameters between two point patterns. IEEE PAMI 13(4), 376-380.
.. [3] Kabsch, W. (1976). A solution for the best rotation to relate two
       sets of vectors. Acta Cryst. A32, 922-923.
.. [4] Hartley, R., & Zisserman, A. (2004). Multiple View Geometry in
       Computer Vision, 2nd ed., section 5.2 (covariance by
       back-propagation, ``(J^T Sigma^-1 J)^-1``).
.. [5] JCGM 100:2008 (GUM), section 5.2: correlated input quantities.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from partinspect.errors import InputError
from partinspect.frames import plane_basis

__all__ = [
    "RegistrationError",
    "Registration",
    "PartFeature",
    "register",
    "refine_pose",
    "pose_error",
    "RADIUS_GATE",
    "DISTANCE_GATE",
    "ANGLE_GATE",
    "MATCH_GATE",
    "AMBIGUITY_RATIO",
]

RADIUS_GATE = 0.3
"""mm: a measured and a CAD radius this close may be the same edge (machining
tolerance plus a poorly measured radius)."""
DISTANCE_GATE = 0.3
"""mm: centre distances of two pairs agreeing this well may be the same pair."""
ANGLE_GATE = np.deg2rad(3.0)
"""rad: angles between normals (or lines) agreeing this well are the same."""
MATCH_GATE = 0.5
"""mm: a measured feature this close to a posed CAD feature is taken as it.
Large against the noise (microns), small against feature spacing (mm), and
loose enough to accept a feature machined a few tenths off."""
DIRECTION_GATE = np.deg2rad(2.0)
"""rad: a measured line or normal within this of a posed CAD one is parallel
(or within ``DIRECTION_GATE_SIGMAS`` of its own standard uncertainty, when
that is wider)."""
DIRECTION_GATE_SIGMAS = 4.0
"""A short or faint edge's direction can be uncertain by a degree or more;
gating it at a fixed angle refused such an edge (a 2 mm stretch at half
contrast, 2.3 deg off with a standard uncertainty of 1.0 deg) that its own
covariance explains. Its weight in the fit follows that covariance."""
DIRECTION_GATE_MAX = np.deg2rad(10.0)
"""rad: however uncertain, a direction further off than this is not parallel."""
AMBIGUITY_RATIO = 2.0
"""Two distinct poses whose chi-squares are within this factor (plus a few
units) explain the data equally well."""
_SAME_POSE_ANGLE = np.deg2rad(2.0)
_SAME_POSE_SHIFT = 2.0  # mm
_MAX_LINE_SEEDS = 8  # longest measured lines used to seed line hypotheses
_MAX_ITER = 30
OUTLIER_P = 1e-9
"""Without named datums, a matched feature whose own chi-square at the
refined pose has a chance below this (for its 4 or 5 whitened residuals:
beyond 46 or 51) is left out of the pose fit, worst first, at most a
quarter of the features, and reported (``Registration.outliers``). It is
still assigned and measured against the pose the others give. On the
stress renders such features were edges matched to a different edge in
the other image (the CAD edge itself hidden there, or lost in a face seen
edge-on) at 40-300 standard uncertainties, and a line 10-17 off; renders
of the sample parts otherwise reach 20 at most."""
COST_TOL = 1e-10
"""The pose refinement has converged when a Gauss-Newton step would lower
the chi-square by less than this fraction of it (``|J step|^2``; the
residuals are whitened, so the step then moves the fit by a negligible
part of a standard deviation), or the step itself is below 1e-11 rad and
1e-9 mm. The relative test is what ends a fit whose chi-square is large:
on a render at noise 5.5 (a NIST test part, chi-square 12816 on 120
residuals) the steps after the second stayed at 1e-10 rad and 1e-8 mm,
the rounding of the residuals, and the refinement ran out of iterations."""


class RegistrationError(InputError):
    """The measured features do not determine the part's pose uniquely.

    An :class:`~partinspect.errors.InputError` (exit code 2, one line).
    """

    def __init__(self, problem):
        super().__init__(None, problem)


@dataclass(frozen=True, eq=False)
class PartFeature:
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
        rotated, plus the pose's, plus (datum features) their
        cross-covariance with the pose estimate.
    pose_jacobian : ndarray, shape (7, 6) or (6, 6)
        d params / d xi (see the module notes for ``xi``).
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

    @property
    def center(self):
        return self.params[:3] if self.kind == "circle" else None

    @property
    def normal(self):
        return self.params[3:6] if self.kind == "circle" else None

    @property
    def radius(self):
        return float(self.params[6]) if self.kind == "circle" else None

    @property
    def point(self):
        return self.params[:3] if self.kind == "line" else None

    @property
    def direction(self):
        return self.params[3:6] if self.kind == "line" else None

    @property
    def covariance(self):
        """3x3 covariance of the centre (circles) or point (lines), mm^2."""
        return self.param_cov[:3, :3]

    @property
    def normal_cov(self):
        return self.param_cov[3:6, 3:6] if self.kind == "circle" else None

    @property
    def direction_cov(self):
        return self.param_cov[3:6, 3:6] if self.kind == "line" else None

    @property
    def radius_std(self):
        return float(np.sqrt(self.param_cov[6, 6])) if self.kind == "circle" else None


@dataclass(frozen=True, eq=False)
class Registration:
    """The pose of the part in the rig and the feature correspondences.

    Attributes
    ----------
    part_to_camera : ndarray, shape (4, 4)
        ``x_rig = R @ X_part + t``.
    pose_cov : ndarray, shape (6, 6)
        Covariance of the pose error ``xi = (w [rad], v [mm])`` in the part
        frame, ``T_hat = T_true @ D(xi)`` (module notes).
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
    def pose_std(self):
        """Standard uncertainties of ``xi``: rad (3) and mm (3)."""
        return np.sqrt(np.diag(self.pose_cov))

    def measured_feature(self, kind, index):
        """The measured record (rig frame) as given to :func:`register`."""
        return (self._circles if kind == "circle" else self._lines)[index]

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
        ``pose_cov`` and ``K = Cov(m, xi)``, non-zero only for datum
        features (the pose was estimated from them, JCGM 100 5.2).
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
            ``B_a S B_b^T`` plus the datum-pose cross terms; the
            measurement errors of two different features are independent.
        """
        S = self.pose_cov
        out = a.pose_jacobian @ S @ b.pose_jacobian.T
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
        """Cov(measured rig params, xi) for a datum feature, else None."""
        fit = self._fit
        if fit is None or (kind, index) not in fit["rows"]:
            return None
        rows, M, L = fit["rows"][(kind, index)]
        return M @ L @ fit["J"][rows] @ self.pose_cov

    def _part_feature(self, kind, index):
        rec = (self._circles if kind == "circle" else self._lines)[index]
        R, t = self.rotation, self.translation
        m, C = _rig_params(kind, rec)
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
            s0, s1 = _line_extent(rec)
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
        return PartFeature(kind, index, cad, K is not None, p, cov, B, start, end, points, point_covs)


# ---------------------------------------------------------------------------
# small geometry helpers


def _skew(v):
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def _skew_many(v):
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def _unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def _whitener(C):
    """S with S C S^T = I (inverse Cholesky), robust to a near-singular C."""
    C = 0.5 * (np.asarray(C, float) + np.asarray(C, float).T)
    w, V = np.linalg.eigh(C)
    floor = max(w.max(), 1e-30) * 1e-12
    w = np.maximum(w, floor)
    return (V / np.sqrt(w)).T, V * np.sqrt(w)  # S, L with L L^T = C, S = L^-1


def _pose_matrix(R, t):
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def _delta(xi):
    return _pose_matrix(Rotation.from_rotvec(xi[:3]).as_matrix(), xi[3:])


def pose_error(T_est, T_true):
    """The error ``xi`` with ``T_est = T_true @ D(xi)``: rotation vector (rad), translation (mm), part frame.

    Parameters
    ----------
    T_est, T_true : ndarray, shape (4, 4)

    Returns
    -------
    ndarray, shape (6,)
    """
    D = np.linalg.inv(T_true) @ T_est
    return np.r_[Rotation.from_matrix(D[:3, :3]).as_rotvec(), D[:3, 3]]


def _line_extent(rec):
    """Arc-length parameters of the measured end points along the record's line, or (None, None)."""
    s, e = getattr(rec, "start", None), getattr(rec, "end", None)
    if s is None or e is None:
        return None, None
    p, d = np.asarray(rec.point, float), _unit(rec.direction)
    s0, s1 = float((np.asarray(s, float) - p) @ d), float((np.asarray(e, float) - p) @ d)
    return min(s0, s1), max(s0, s1)


def axis_cov(rec):
    """Covariance (3, 3) of a record's unit normal or direction.

    ``normal_cov`` / ``direction_cov`` (fit3d records) or ``axis_cov``
    (:class:`partinspect.vision.stereo.Feature3D`).
    """
    for name in ("normal_cov", "direction_cov", "axis_cov"):
        v = getattr(rec, name, None)
        if v is not None:
            return np.asarray(v, float)
    raise AttributeError(f"{type(rec).__name__} has no normal/direction covariance")


def rig_params(kind, rec):
    """Stacked rig-frame parameters and their covariance.

    Circles ``(center, normal, radius)`` (7,), lines ``(point, direction)``
    (6,). A record's own ``param_cov`` of that shape (stereo Feature3D) is
    used whole, with the correlations inside the fit; otherwise the blocks
    are assembled and those correlations are neglected.
    """
    n = 7 if kind == "circle" else 6
    if kind == "circle":
        m = np.r_[np.asarray(rec.center, float), _unit(rec.normal), float(rec.radius)]
    else:
        m = np.r_[np.asarray(rec.point, float), _unit(rec.direction)]
    full = getattr(rec, "param_cov", None)
    if full is not None and np.shape(full) == (n, n):
        return m, np.asarray(full, float)
    C = np.zeros((n, n))
    C[:3, :3] = rec.covariance
    C[3:6, 3:6] = axis_cov(rec)
    if kind == "circle":
        C[6, 6] = float(rec.radius_std) ** 2
    return m, C


_rig_params = rig_params


# ---------------------------------------------------------------------------
# CAD side


@dataclass(frozen=True)
class _Cad:
    round_ids: tuple
    centers: np.ndarray  # (K, 3)
    normals: np.ndarray
    radii: np.ndarray
    round_faces: np.ndarray  # (K, F, 3) outward normals of plane faces, zeros for curved ones, NaN-padded
    line_ids: tuple
    starts: np.ndarray  # (L, 3)
    dirs: np.ndarray
    lengths: np.ndarray
    line_faces: np.ndarray


def _face_normals(inventory, feature, width=2):
    """Outward normals of a feature's adjacent faces: a plane's normal, zeros for a curved face, NaN padding."""
    out = np.full((width, 3), np.nan)
    k = 0
    for fid in feature.faces:
        try:
            face = inventory[fid]
        except KeyError:
            continue
        if k < width:
            normal = getattr(face, "normal", None)
            out[k] = 0.0 if normal is None else normal
            k += 1
    return out


def _cad_arrays(inventory):
    feats = [f for f in inventory.features if not f.smooth]
    rnd = [f for f in feats if f.kind in ("circle", "arc")]
    lines = [f for f in feats if f.kind == "line"]
    z3 = np.zeros((0, 3))
    return _Cad(
        tuple(f.id for f in rnd),
        np.array([f.center for f in rnd], float).reshape(-1, 3) if rnd else z3,
        np.array([f.normal for f in rnd], float).reshape(-1, 3) if rnd else z3,
        np.array([f.radius for f in rnd], float),
        np.array([_face_normals(inventory, f) for f in rnd]).reshape(-1, 2, 3),
        tuple(f.id for f in lines),
        np.array([f.start for f in lines], float).reshape(-1, 3) if lines else z3,
        np.array([f.direction for f in lines], float).reshape(-1, 3) if lines else z3,
        np.array([np.linalg.norm(f.end - f.start) for f in lines], float),
        np.array([_face_normals(inventory, f) for f in lines]).reshape(-1, 2, 3),
    )


def _facing(face_normals, R, points_cam):
    """(B, K) True where a feature may be seen: some adjacent plane faces the camera, or a face is curved.

    ``R`` (B, 3, 3) and ``points_cam`` (B, K, 3) are B poses' rotations
    and the features' points in each camera frame; ``face_normals`` (K, F, 3)
    the adjacent faces' normals in the part frame (zero: curved; NaN: none).

    An edge between a plane turned away and a curved face shows where the
    curved face turns to the camera: the bottom end of the bracket's
    through slot, seen through the slot against the background, is such an
    arc; taken as hidden, it was measured (to 0.001 mm) and then matched to
    nothing.
    """
    # Which faces are known and which plane does not change with the pose.
    known = ~np.isnan(face_normals[..., 0])
    plane = known & (np.abs(np.nan_to_num(face_normals)).sum(axis=2) > 0)
    n = np.einsum("kfi,bji->bkfj", np.nan_to_num(face_normals), R)
    toward = np.einsum("bkfi,bki->bkf", n, -points_cam) > 0
    return (~plane.any(1) | (known & ~plane).any(1))[None] | (toward & plane[None]).any(2)


# ---------------------------------------------------------------------------
# measured side


@dataclass(frozen=True)
class _Meas:
    centers: np.ndarray
    normals: np.ndarray
    radii: np.ndarray
    points: np.ndarray  # lines
    dirs: np.ndarray
    ends: np.ndarray  # (N, 2, 3) measured extent end points (or +-5 mm)
    lengths: np.ndarray
    normal_cos: np.ndarray  # (M,) cosine of each circle's direction gate
    dir_cos: np.ndarray  # (N,) the same for lines


def _direction_gate_cos(rec):
    """Cosine of the angle within which a measured axis counts as parallel to a CAD one."""
    try:
        C = axis_cov(rec)
        u = float(np.sqrt(max(np.linalg.eigvalsh(0.5 * (C + C.T))[-1], 0.0)))
    except (AttributeError, np.linalg.LinAlgError, ValueError):
        u = 0.0
    if not np.isfinite(u):
        u = 0.0
    return float(np.cos(np.clip(DIRECTION_GATE_SIGMAS * u, DIRECTION_GATE, DIRECTION_GATE_MAX)))


def _meas_arrays(circles, lines):
    z3 = np.zeros((0, 3))
    ends, lens = [], []
    for rec in lines:
        p, d = np.asarray(rec.point, float), _unit(rec.direction)
        s0, s1 = _line_extent(rec)
        if s0 is None:
            s0, s1 = -5.0, 5.0  # no extent: judge the line by a short stretch
        ends.append([p + s0 * d, p + s1 * d])
        lens.append(s1 - s0)
    return _Meas(
        np.array([c.center for c in circles], float).reshape(-1, 3) if circles else z3,
        np.array([_unit(c.normal) for c in circles], float).reshape(-1, 3) if circles else z3,
        np.array([c.radius for c in circles], float),
        np.array([l.point for l in lines], float).reshape(-1, 3) if lines else z3,
        np.array([_unit(l.direction) for l in lines], float).reshape(-1, 3) if lines else z3,
        np.array(ends, float).reshape(-1, 2, 3),
        np.array(lens, float),
        np.array([_direction_gate_cos(c) for c in circles], float),
        np.array([_direction_gate_cos(l) for l in lines], float),
    )


# ---------------------------------------------------------------------------
# hypotheses


def _circle_hypotheses(meas, cad):
    """Poses from pairs of measured circles matched to pairs of CAD round features."""
    out = []
    m, k = len(meas.radii), len(cad.radii)
    if m < 2 or k < 2:
        return out
    rad_ok = np.abs(meas.radii[:, None] - cad.radii[None, :]) <= RADIUS_GATE  # (m, k)
    cad_d = np.linalg.norm(cad.centers[:, None] - cad.centers[None, :], axis=2)
    cad_cos = np.abs(cad.normals @ cad.normals.T)
    for i in range(m):
        for j in range(i + 1, m):
            dm = np.linalg.norm(meas.centers[j] - meas.centers[i])
            if dm < 1e-6:
                continue  # concentric circles: no baseline
            am = np.arccos(min(1.0, abs(meas.normals[i] @ meas.normals[j])))
            ok = rad_ok[i][:, None] & rad_ok[j][None, :]
            ok &= np.abs(cad_d - dm) <= DISTANCE_GATE
            ok &= np.abs(np.arccos(np.clip(cad_cos, -1, 1)) - am) <= ANGLE_GATE
            np.fill_diagonal(ok, False)
            for a, b in zip(*np.nonzero(ok)):
                base_m = meas.centers[j] - meas.centers[i]
                base_c = cad.centers[b] - cad.centers[a]
                for si in (1.0, -1.0):
                    for sj in (1.0, -1.0):
                        target = np.stack([base_m / dm, meas.normals[i], meas.normals[j]])
                        source = np.stack([base_c / dm, si * cad.normals[a], sj * cad.normals[b]])
                        R = _align(target, source, np.array([2.0, 1.0, 1.0]))
                        if R is None:
                            continue
                        t = 0.5 * (meas.centers[i] + meas.centers[j]) - R @ (0.5 * (cad.centers[a] + cad.centers[b]))
                        out.append((R, t))
    return out


def _align(target, source, weights):
    """Rotation R minimising sum w |target - R source|^2 (Kabsch), or None if degenerate."""
    H = (source * weights[:, None]).T @ target
    U, s, Vt = np.linalg.svd(H)
    if s[1] < 1e-6 * max(s[0], 1e-30):
        return None  # all vectors parallel: rotation about them undetermined
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    return Vt.T @ np.diag([1.0, 1.0, d]) @ U.T


def _common_perpendicular(p1, d1, p2, d2):
    """Midpoint and length of the common perpendicular of two non-parallel lines."""
    w = p1 - p2
    b = d1 @ d2
    den = 1.0 - b * b
    s = (b * (d2 @ w) - (d1 @ w)) / den
    u = ((d2 @ w) - b * (d1 @ w)) / den
    q1, q2 = p1 + s * d1, p2 + u * d2
    return 0.5 * (q1 + q2), float(np.linalg.norm(q1 - q2))


def _line_hypotheses(meas, cad):
    """Poses from pairs of non-parallel measured lines matched to CAD line pairs."""
    out = []
    order = np.argsort(-meas.lengths)[:_MAX_LINE_SEEDS]
    L = len(cad.lengths)
    if len(order) < 2 or L < 2:
        return out
    cad_cos = np.abs(cad.dirs @ cad.dirs.T)
    for ii, i in enumerate(order):
        for j in order[ii + 1 :]:
            c = abs(meas.dirs[i] @ meas.dirs[j])
            if c > np.cos(np.deg2rad(10.0)):
                continue  # near-parallel pairs fix the pose poorly
            vm, hm = _common_perpendicular(meas.points[i], meas.dirs[i], meas.points[j], meas.dirs[j])
            ang = np.arccos(min(1.0, c))
            ok = np.abs(np.arccos(np.clip(cad_cos, -1, 1)) - ang) <= ANGLE_GATE
            ok &= (cad.lengths[:, None] >= meas.lengths[i] - 2 * MATCH_GATE) & (cad.lengths[None, :] >= meas.lengths[j] - 2 * MATCH_GATE)
            np.fill_diagonal(ok, False)
            for a, b in zip(*np.nonzero(ok)):
                vc, hc = _common_perpendicular(cad.starts[a], cad.dirs[a], cad.starts[b], cad.dirs[b])
                if abs(hc - hm) > DISTANCE_GATE:
                    continue
                for si in (1.0, -1.0):
                    for sj in (1.0, -1.0):
                        da, db = si * cad.dirs[a], sj * cad.dirs[b]
                        target = np.stack([meas.dirs[i], meas.dirs[j], np.cross(meas.dirs[i], meas.dirs[j])])
                        source = np.stack([da, db, np.cross(da, db)])
                        R = _align(target, source, np.ones(3))
                        if R is None:
                            continue
                        out.append((R, vm - R @ vc))
    return out


# ---------------------------------------------------------------------------
# scoring and matching


def _candidates(meas, cad, R, t, gate=MATCH_GATE):
    """Distances of the candidate pairs under B poses: circles (B, m, K), lines (B, n, L), inf where not a candidate.

    ``R`` (B, 3, 3), ``t`` (B, 3). A circle pairs with a CAD round feature
    within ``gate`` of its centre, of its radius within ``RADIUS_GATE`` and
    its axis within the measured axis' gate, and that may be seen; a line
    with a CAD line parallel within its gate whose extent covers the
    measured ends (plus ``gate``) at most ``gate`` off it, and that may be
    seen.
    """
    B = len(R)
    dc = np.full((B, len(meas.radii), len(cad.radii)), np.inf)
    if len(meas.radii) and len(cad.radii):
        cc = cad.centers @ R.transpose(0, 2, 1) + t[:, None]  # (B, K, 3)
        nn = cad.normals @ R.transpose(0, 2, 1)
        d = np.linalg.norm(meas.centers[None, :, None] - cc[:, None], axis=3)
        ok = d <= gate
        ok &= (np.abs(meas.radii[:, None] - cad.radii[None]) <= RADIUS_GATE)[None]
        ok &= np.abs(np.einsum("mi,bki->bmk", meas.normals, nn)) >= meas.normal_cos[None, :, None]
        ok &= _facing(cad.round_faces, R, cc)[:, None]
        dc = np.where(ok, d, np.inf)
    dl = np.full((B, len(meas.lengths), len(cad.lengths)), np.inf)
    if len(meas.lengths) and len(cad.lengths):
        s = cad.starts @ R.transpose(0, 2, 1) + t[:, None]  # (B, L, 3)
        u = cad.dirs @ R.transpose(0, 2, 1)
        mid_cad = s + 0.5 * cad.lengths[None, :, None] * u
        # The distances only of the parallel pairs (a third or less of them).
        b, j, l = np.nonzero(np.abs(np.einsum("ni,bli->bnl", meas.dirs, u)) >= meas.dir_cos[None, :, None])
        sp, up = s[b, l], u[b, l]
        dist = np.zeros(len(b))
        inside = np.ones(len(b), bool)
        for e in range(2):
            v = meas.ends[j, e] - sp
            along = np.einsum("pi,pi->p", v, up)
            dist = np.maximum(dist, np.linalg.norm(v - along[:, None] * up, axis=1))
            inside &= (along >= -gate) & (along <= cad.lengths[l] + gate)
        ok = inside & (dist <= gate) & _facing(cad.line_faces, R, mid_cad)[b, l]
        dl[b[ok], j[ok], l[ok]] = dist[ok]
    return dc, dl


def _assigned(dc, dl, gate=MATCH_GATE):
    """Correspondences of one pose's candidates (:func:`_candidates`): ({i: k}, {j: l}, cost).

    Circles one to one, nearest pair first; each line to its nearest CAD
    line. The cost sums the squared distances over ``gate``.
    """
    circ, lin, cost = {}, {}, 0.0
    pairs = np.flatnonzero(np.isfinite(dc))
    taken = set()
    for flat in pairs[np.argsort(dc.flat[pairs], kind="stable")]:
        i, k = divmod(int(flat), dc.shape[1])
        if i in circ or k in taken:
            continue
        circ[i] = k
        taken.add(k)
        cost += (dc[i, k] / gate) ** 2
    if dl.size:
        best = np.argmin(dl, axis=1)
        for j, l in enumerate(best):
            if np.isfinite(dl[j, l]):
                lin[j] = int(l)
                cost += (dl[j, l] / gate) ** 2
    return circ, lin, cost


def _match(meas, cad, R, t, gate=MATCH_GATE):
    """Correspondences under a pose: ({i: k}, {j: l}, cost)."""
    dc, dl = _candidates(meas, cad, np.asarray(R, float)[None], np.asarray(t, float)[None], gate)
    return _assigned(dc[0], dl[0], gate)


_SCORE_BATCH = 150_000
"""Poses :func:`_scores` takes at once: as many as make about this many
elements in its largest arrays (B x m x K x 3 for the circles, B x n x L
for the lines' directions). Small
batches stay in the CPU's cache: on NIST ftc_09 (23 measured circles and
15 lines against 126 and 162 CAD ones) 3000 poses took 0.60 s in batches
of 16, 0.70 s of 32 and 0.77 s of 256, and 0.91-0.98 s one at a time."""


def _scores(meas, cad, hyps, gate=MATCH_GATE, batch=None):
    """Matched features and cost of each hypothesis (R, t): what :func:`_match` gives, many poses at once.

    The candidates of a batch of poses are one array operation: the
    search scores tens of thousands of poses on a part with hundreds of
    edges (51720 in one inspection of a NIST ftc_09 render, 27 s of its
    42 s one pose at a time). ``batch``: poses per batch (default: by
    ``_SCORE_BATCH``).
    """
    per_pose = max(1, len(meas.lengths) * len(cad.lengths), 3 * len(meas.radii) * len(cad.radii))
    step = batch or max(1, _SCORE_BATCH // per_pose)
    out = []
    for a in range(0, len(hyps), step):
        R = np.array([h[0] for h in hyps[a:a + step]], float)
        t = np.array([h[1] for h in hyps[a:a + step]], float)
        dc, dl = _candidates(meas, cad, R, t, gate)
        for b in range(len(R)):
            circ, lin, cost = _assigned(dc[b], dl[b], gate)
            out.append((len(circ) + len(lin), cost))
    return out


# ---------------------------------------------------------------------------
# refinement


class _Problem:
    """Whitened residuals of matched features as a function of a pose."""

    def __init__(self, circles, lines, circ_match, line_match, cad):
        self.items = []  # (kind, index, n_rows, M, L)
        cc, cn, cS, cE, cSn, cm, nm = [], [], [], [], [], [], []
        for i, k in sorted(circ_match.items()):
            rec = circles[i]
            S, L = _whitener(rec.covariance)
            n = _unit(rec.normal)
            E = plane_basis(n)
            Sn, Ln = _whitener(E.T @ axis_cov(rec) @ E)
            cc.append(cad.centers[k])
            cn.append(cad.normals[k])
            cS.append(S)
            cE.append(E)
            cSn.append(Sn)
            cm.append(np.asarray(rec.center, float))
            nm.append(n)
            M = np.zeros((7, 5))
            M[:3, :3] = np.eye(3)
            M[3:6, 3:5] = E
            Lb = np.zeros((5, 5))
            Lb[:3, :3], Lb[3:, 3:] = L, Ln
            self.items.append(("circle", i, 5, M, Lb))
        lp, ld, lS, lE, pm, dm = [], [], [], [], [], []
        for j, l in sorted(line_match.items()):
            rec = lines[j]
            d = _unit(rec.direction)
            E = plane_basis(d)
            C4 = np.zeros((4, 4))
            C4[:2, :2] = E.T @ np.asarray(rec.covariance, float) @ E
            C4[2:, 2:] = E.T @ axis_cov(rec) @ E
            S, L = _whitener(C4)
            lp.append(cad.starts[l])
            ld.append(cad.dirs[l])
            lS.append(S)
            lE.append(E)
            pm.append(np.asarray(rec.point, float))
            dm.append(d)
            M = np.zeros((6, 4))
            M[:3, :2] = E
            M[3:6, 2:] = E
            self.items.append(("line", j, 4, M, L))
        arr = lambda x, s: np.array(x, float).reshape(s)  # noqa: E731
        self.cc, self.cn, self.cS = arr(cc, (-1, 3)), arr(cn, (-1, 3)), arr(cS, (-1, 3, 3))
        self.cE, self.cSn, self.cm, self.nm = arr(cE, (-1, 3, 2)), arr(cSn, (-1, 2, 2)), arr(cm, (-1, 3)), arr(nm, (-1, 3))
        self.lp, self.ld, self.lS, self.lE = arr(lp, (-1, 3)), arr(ld, (-1, 3)), arr(lS, (-1, 4, 4)), arr(lE, (-1, 3, 2))
        self.pm, self.dm = arr(pm, (-1, 3)), arr(dm, (-1, 3))
        self.n_res = 5 * len(self.cc) + 4 * len(self.lp)
        self.csign = np.ones(len(self.cc))
        self.lsign = np.ones(len(self.lp))

    def fix_signs(self, T):
        R = T[:3, :3]
        self.csign = np.where(np.einsum("ni,ni->n", self.cn @ R.T, self.nm) < 0, -1.0, 1.0)
        self.lsign = np.where(np.einsum("ni,ni->n", self.ld @ R.T, self.dm) < 0, -1.0, 1.0)

    def residuals(self, T, raw=False):
        R, t = T[:3, :3], T[:3, 3]
        out = []
        if len(self.cc):
            dc = self.cc @ R.T + t - self.cm
            nt = np.einsum("nij,ni->nj", self.cE, self.csign[:, None] * (self.cn @ R.T))
            if raw:
                out.append(np.linalg.norm(dc, axis=1))
            else:
                out.append(np.concatenate([np.einsum("nij,nj->ni", self.cS, dc), np.einsum("nij,nj->ni", self.cSn, nt)], 1))
        if len(self.lp):
            P = self.lp @ R.T + t
            D = self.lsign[:, None] * (self.ld @ R.T)
            den = np.einsum("ni,ni->n", D, self.dm)
            s = np.einsum("ni,ni->n", self.pm - P, self.dm) / den
            X = P + s[:, None] * D - self.pm
            ab = np.einsum("nij,ni->nj", self.lE, X)
            al = np.einsum("nij,ni->nj", self.lE, D) / den[:, None]
            if raw:
                out.append(np.linalg.norm(ab, axis=1))
            else:
                out.append(np.einsum("nij,nj->ni", self.lS, np.concatenate([ab, al], 1)))
        if raw:
            return np.concatenate(out) if out else np.zeros(0)
        # rows ordered circles then lines, each feature's block contiguous
        return np.concatenate([o.ravel() for o in out]) if out else np.zeros(0)

    def jacobian(self, T, h=1e-7):
        cols = []
        for k in range(6):
            e = np.zeros(6)
            e[k] = h
            cols.append((self.residuals(T @ _delta(e)) - self.residuals(T @ _delta(-e))) / (2 * h))
        return np.stack(cols, 1)


def refine_pose(T0, problem):
    """Gauss-Newton on the right-perturbation ``T @ D(xi)``; returns (T, J, r, converged)."""
    T = np.array(T0, float)
    problem.fix_signs(T)
    r = problem.residuals(T)
    cost = r @ r
    converged = False
    for _ in range(_MAX_ITER):
        J = problem.jacobian(T)
        try:
            step = np.linalg.lstsq(J, -r, rcond=None)[0]
        except np.linalg.LinAlgError:
            break
        # Predicted decrease of the cost, before any halving of the step.
        negligible = float(np.sum((J @ step) ** 2)) <= COST_TOL * max(cost, 1.0)
        Tn = T @ _delta(step)
        rn = problem.residuals(Tn)
        cn = rn @ rn
        if cn > cost * (1 + 1e-12) + 1e-18:
            # a Gauss-Newton step that increases the cost: halve it
            for _ in range(20):
                step *= 0.5
                Tn = T @ _delta(step)
                rn = problem.residuals(Tn)
                cn = rn @ rn
                if cn <= cost:
                    break
            else:
                converged = negligible or np.linalg.norm(step) < 1e-9
                break
        T, r = Tn, rn
        small = negligible or (np.linalg.norm(step[:3]) < 1e-11 and np.linalg.norm(step[3:]) < 1e-9)
        cost = cn
        if small:
            converged = True
            break
    J = problem.jacobian(T)
    return T, J, problem.residuals(T), converged


def _constraint_check(J):
    """Raise when the datum features leave some pose direction free."""
    if J.shape[0] < 6:
        raise RegistrationError(
            f"alignment is ambiguous: the datum features give {J.shape[0]} constraints, the pose needs 6"
        )
    # Scale rotations by a part-sized lever (100 mm) so the test compares like with like.
    Js = J * np.r_[np.full(3, 1e-2), np.ones(3)]
    s = np.linalg.svd(Js, compute_uv=False)
    if s[-1] < 1e-8 * s[0]:
        raise RegistrationError(
            "alignment is ambiguous: the datum features leave the pose undetermined in some direction "
            "(e.g. all lines parallel, or one circle alone)"
        )


# ---------------------------------------------------------------------------


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
    pose_hint : ndarray, shape (4, 4), optional
        A ``part_to_camera`` close enough (within ``MATCH_GATE`` at the
        features) to skip the hypothesis search.

    Returns
    -------
    Registration

    Raises
    ------
    RegistrationError
        "alignment is ambiguous: ..." when two distinct poses explain the
        data equally well, the datums give fewer than 6 independent
        constraints, nothing matches, or the refinement does not converge.
    """
    circles, lines = tuple(measured_circles), tuple(measured_lines)
    cad = _cad_arrays(inventory)
    meas = _meas_arrays(circles, lines)
    datum_set = None if datums is None else set(datums)
    if datum_set is not None:
        unknown = sorted(d for d in datum_set if d not in inventory)
        if unknown:
            raise RegistrationError(f"unknown datum feature(s) {', '.join(unknown)}")

    if pose_hint is not None:
        hyps = [(np.asarray(pose_hint, float)[:3, :3], np.asarray(pose_hint, float)[:3, 3])]
    elif _symmetric_model(cad):
        # A property of the model, whatever was measured (its short arcs
        # may even be measured as circles off the axis).
        raise RegistrationError(
            f"alignment is ambiguous: the CAD model's {len(cad.round_ids)} circles share one axis and it has no "
            "straight edge, so the rotation about that axis is undetermined (a rotationally symmetric part)"
        )
    else:
        hyps = _circle_hypotheses(meas, cad)
        if not hyps:
            hyps = _line_hypotheses(meas, cad)
        if not hyps and not lines and _coaxial(circles):
            raise RegistrationError(
                f"alignment is ambiguous: the {len(circles)} measured circles share one axis and no line was "
                "measured, so the rotation about that axis is undetermined (a rotationally symmetric view)"
            )
        if not hyps:
            raise RegistrationError(
                "alignment is ambiguous: no pair of measured circles or lines matches the CAD model "
                f"({len(circles)} circles, {len(lines)} lines measured)"
            )

    scored = [(n, -cost, R, t) for (n, cost), (R, t) in zip(_scores(meas, cad, hyps), hyps)]
    best = max(s[0] for s in scored)
    if best < 2:
        raise RegistrationError("alignment is ambiguous: no pose explains more than one measured feature")
    top = sorted((s for s in scored if s[0] == best), key=lambda s: -s[1])
    clusters = []
    for s in top:
        if not any(_same_pose(s[2], s[3], c[2], c[3]) for c in clusters):
            clusters.append(s)
        if len(clusters) >= 12:
            break

    results = []
    last_error = None
    for _, _, R, t in clusters:
        try:
            results.append(_solve(_pose_matrix(R, t), circles, lines, meas, cad, datum_set))
        except RegistrationError as e:
            last_error = e
    if not results:
        raise last_error
    results.sort(key=lambda r: (-r["score"], r["chi2"]))
    first = results[0]
    for other in results[1:]:
        if other["score"] < first["score"]:
            break
        if _same_pose(first["T"][:3, :3], first["T"][:3, 3], other["T"][:3, :3], other["T"][:3, 3]):
            continue
        if other["chi2"] <= AMBIGUITY_RATIO * first["chi2"] + 10.0 * max(1, first["dof"]) ** 0.5:
            e = pose_error(other["T"], first["T"])
            # how far the part's features move between the two poses, not its (arbitrary) origin
            pts = np.r_[cad.centers, cad.starts]
            shift = np.linalg.norm((pts @ (other["T"][:3, :3] - first["T"][:3, :3]).T) + other["T"][:3, 3] - first["T"][:3, 3], axis=1).max()
            raise RegistrationError(
                f"alignment is ambiguous: two poses {np.rad2deg(np.linalg.norm(e[:3])):.1f} degrees apart "
                f"(features moved by up to {shift:.1f} mm) explain the "
                f"{first['score']} matched features equally well (chi-square {first['chi2']:.3g} vs "
                f"{other['chi2']:.3g}); the part looks symmetric to the measured features"
            )
    r = first
    if datum_set is None:
        # Only the chosen pose: leaving features out of the competing
        # hypotheses could make a wrong one fit as well as the right one.
        r = _solve(first["T"], circles, lines, meas, cad, None, exclude_outliers=True)
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
        n_hypotheses=len(hyps),
        outliers=r["outliers"],
        _circles=circles,
        _lines=lines,
        _fit={"J": r["J"], "rows": r["rows"]},
    )


def _symmetric_model(cad):
    """True when the model's edges are circles on one axis and nothing else (exactly, as CAD is)."""
    if len(cad.line_ids) or len(cad.round_ids) == 0:
        return False
    n0 = _unit(cad.normals[0])
    d = cad.centers - cad.centers[0]
    off_axis = d - np.outer(d @ n0, n0)
    scale = max(1.0, float(np.max(cad.radii)))
    return bool(np.all(np.abs(cad.normals @ n0) > 1.0 - 1e-9)
                and np.all(np.linalg.norm(off_axis, axis=1) < 1e-6 * scale))


def _coaxial(circles, rel=0.1, angle=np.deg2rad(10.0)):
    """True when the circles look coaxial: centres within ``rel`` of the largest
    radius (at least ``MATCH_GATE``) of the first one's axis, normals within ``angle``.

    Loose on purpose: it only chooses the wording of an error, and short arcs
    of a symmetric part are measured poorly."""
    if not circles:
        return False
    tol = max(MATCH_GATE, rel * max(float(c.radius) for c in circles))
    c0, n0 = np.asarray(circles[0].center, float), _unit(np.asarray(circles[0].normal, float))
    for c in circles[1:]:
        d = np.asarray(c.center, float) - c0
        if np.linalg.norm(d - (d @ n0) * n0) > tol or abs(_unit(np.asarray(c.normal, float)) @ n0) < np.cos(angle):
            return False
    return True


def _same_pose(R1, t1, R2, t2):
    ang = Rotation.from_matrix(R1.T @ R2).magnitude()
    return ang < _SAME_POSE_ANGLE and np.linalg.norm(t1 - t2) < _SAME_POSE_SHIFT


def _refine(T, circles, lines, meas, cad, datum_set, left_out):
    """Match, refine on the datums (less those keyed (kind, measured index) in ``left_out``), re-match, refine again."""
    for _ in range(3):
        circ, lin, _ = _match(meas, cad, T[:3, :3], T[:3, 3])
        fc = {i: k for i, k in circ.items()
              if (datum_set is None or cad.round_ids[k] in datum_set) and ("circle", i) not in left_out}
        fl = {j: l for j, l in lin.items()
              if (datum_set is None or cad.line_ids[l] in datum_set) and ("line", j) not in left_out}
        problem = _Problem(circles, lines, fc, fl, cad)
        if problem.n_res < 6:
            raise RegistrationError(
                f"alignment is ambiguous: the matched datum features give {problem.n_res} constraints, the pose needs 6"
            )
        T_new, J, r, converged = refine_pose(T, problem)
        if not converged:
            raise RegistrationError("alignment is ambiguous: the pose refinement did not converge")
        moved = np.linalg.norm(T_new[:3, 3] - T[:3, 3]) + 100 * Rotation.from_matrix(T_new[:3, :3].T @ T[:3, :3]).magnitude()
        T = T_new
        if moved < 1e-6:
            break
    _constraint_check(J)
    return T, circ, lin, fc, fl, problem, J, r


def _worst(problem, r):
    """(chance, kind, measured index, chi-square, residuals) of the feature with the least likely residuals."""
    from scipy import stats

    worst, start = None, 0
    for kind, index, n, _, _ in problem.items:
        c2 = float(r[start:start + n] @ r[start:start + n])
        start += n
        p = stats.chi2.sf(c2, n)
        if worst is None or p < worst[0]:
            worst = (p, kind, index, c2, n)
    return worst


def _solve(T, circles, lines, meas, cad, datum_set, exclude_outliers=False):
    """Match, refine on the datums, re-match with the refined pose, refine again.

    With ``exclude_outliers`` (no named datums), a feature inconsistent with
    the others (``OUTLIER_P``) is then left out and the pose refined again,
    worst first, while the rest still fix the pose.
    """
    left_out = {}
    T, circ, lin, fc, fl, problem, J, r = _refine(T, circles, lines, meas, cad, datum_set, left_out)
    limit = (len(fc) + len(fl)) // 4
    while exclude_outliers and len(left_out) < limit:
        p, kind, index, c2, n = _worst(problem, r)  # the refinement needs 6 residuals: there is one
        if p >= OUTLIER_P:
            break
        trial = {**left_out, (kind, index): (c2, n)}
        try:
            refined = _refine(T, circles, lines, meas, cad, datum_set, trial)
        except RegistrationError:
            break  # the others alone leave the pose undetermined: keep the feature
        left_out = trial
        T, circ, lin, fc, fl, problem, J, r = refined
    circ2, lin2, _ = _match(meas, cad, T[:3, :3], T[:3, 3])
    if (circ2, lin2) != (circ, lin):
        circ, lin = circ2, lin2  # final assignment under the final pose
    cov = np.linalg.inv(J.T @ J)
    cov = 0.5 * (cov + cov.T)
    rows, start = {}, 0
    for kind, index, n, M, L in problem.items:
        rows[(kind, index)] = (slice(start, start + n), M, L)
        start += n
    raw = problem.residuals(T, raw=True)
    ids = tuple(sorted({cad.round_ids[k] for k in fc.values()} | {cad.line_ids[l] for l in fl.values()}))
    return {
        "T": T,
        "cov": cov,
        "J": J,
        "rows": rows,
        "chi2": float(r @ r),
        "dof": int(r.size - 6),
        "rms": float(np.sqrt(np.mean(raw**2))) if raw.size else 0.0,
        "circ": circ,
        "lin": lin,
        "score": len(circ) + len(lin),
        "datums": ids,
        "outliers": {(cad.round_ids[circ[i]] if kind == "circle" else cad.line_ids[lin[i]]): (round(c2, 6), n)
                     for (kind, i), (c2, n) in left_out.items()
                     if i in (circ if kind == "circle" else lin)},
    }
