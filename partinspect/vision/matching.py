"""Matching of left and right image features by the epipolar constraint.

The features of each image (:mod:`partinspect.vision.imagefeatures`) are
paired across the two images:

- every feature spans a range of epipolar lines, its *band* (the signed
  offset, in ideal left-image pixels at the image centre, of the epipolar
  line through each of its points); two images of one edge span the same
  band up to their ends' trimming, so candidates must overlap [2]_;
- their shapes must agree: the same kind and polarity (not compared for an
  arc merged from pieces of opposite polarity); for arcs, the same 3D
  radius once each ellipse is scaled by its triangulated depth, within
  what the two ellipse fits leave uncertain; for lines, similar angles to
  the epipolar lines and a triangulated middle in front of both cameras;
- a one-to-one assignment (Hungarian algorithm [3]_) minimises the summed
  cost, with a threshold for pairs too poor to keep.

Every feature left without a partner is returned with its reason. Two
geometries are reported instead of matched: a line nearly parallel to the
epipolar lines is *degenerate* (its depth is undetermined), and a circle
seen nearly *edge-on* (``MIN_AXIS_RATIO``) has an ellipse so thin that its
points are displaced by more than their uncertainty says: the radius of
curvature at the ends of the major axis, b^2 / a, falls to a pixel or two,
below what the detector's smoothing correction models, the two sides crowd
each other, and a rim seen against its own wall's changing shading is
found in pieces. A feature whose only plausible partner is degenerate or
edge-on gets that partner's reason, so both images tell the same story.

All coordinates are ideal pixels (distortion removed,
:mod:`partinspect.vision.ideal`); 3D points are in the rig (left camera)
frame, mm.

References
----------
.. [1] Hartley, R., & Zisserman, A. (2004). Multiple View Geometry in
       Computer Vision, 2nd ed., chapter 9 (epipolar geometry, the
       fundamental matrix) and 12 (triangulation).
.. [2] Paper of this project, reference 2 and section 4: feature matching by
       epipolar constraint matrices.
.. [3] Kuhn, H. W. (1955). The Hungarian method for the assignment problem.
       Naval Research Logistics Quarterly 2, 83-97 (scipy's
       ``linear_sum_assignment``).
"""

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from partinspect.vision.ramps import RAMP_SHARE
from partinspect.vision.triangulation import fundamental_matrix, triangulate

__all__ = [
    "EpipolarGeometry",
    "Match",
    "Unmatched",
    "Matching",
    "epipolar_geometry",
    "match_features",
    "arc_circle",
    "line_angles",
    "REASONS",
    "MIN_EPIPOLAR_ANGLE",
    "MIN_AXIS_RATIO",
]

MIN_EPIPOLAR_ANGLE = np.deg2rad(8.0)
"""Lines closer than this to the epipolar lines (in either image) are "degenerate", rad."""
MIN_AXIS_RATIO = 0.2
"""Arcs whose fitted ellipse has a minor/major axis ratio below this (in
either image) are "edge-on": the circle is seen more than arccos 0.2 = 78.5
degrees off its axis, where holes' diameters come out too small by more
than their U (see the module notes). Thin partial arcs above it can still be
biased where the rim's contrast varies along them: a displacement of the
edge points, not a geometric degeneracy, and not rejected here."""
RADIUS_COVERAGE = 2.0
"""Coverage factor on the standard uncertainty of ``log(r_left / r_right)``
that two arcs' ellipse fits leave: the ratio's tolerance in the matching
cost is ``radius_tolerance`` widened in quadrature by this many standard
uncertainties (:func:`_radius_scale`). A short arc's semi-major axis (a
quarter of a rim seen through its hole) is uncertain by several per cent,
beyond the fixed tolerance, which would leave such true pairs unmatched."""
RADIUS_WIDENING_MAX = 2.0
"""The widened tolerance never exceeds this many times ``radius_tolerance``
(a 20 % disagreement costs 1): the radius is the only shape an arc is
matched by besides its band, and an arc too short to tell its radius
within that would be paired on its band alone, where arcs of neighbouring
holes overlap. Such arcs are left unmatched, with the reason."""

REASONS = {
    "too_short": "too few edge points to be measured",
    "degenerate": "line nearly parallel to the epipolar lines: its position along them is undetermined",
    "edge_on": "circle seen nearly edge-on: its ellipse is too thin for a reliable radius",
    "ramp": "a shading ramp's crest, not a step edge (a curved face's shading or a highlight's flank): "
            "nothing to locate an edge by",
    "no_candidate": "no feature of the other image in its epipolar band",
    "kind_mismatch": "only features of another kind in its epipolar band",
    "shape_mismatch": "features in its band disagree in polarity, size or orientation",
    "ambiguous": "two or more partners fit about equally well",
    "outcompeted": "its candidates were matched better to other features",
}


# ----------------------------------------------------------- epipolar geometry


def _homogeneous(x):
    """Points (N, 2) as homogeneous rows (x, y, 1) (``np.c_`` costs more in overhead here)."""
    x = np.asarray(x, float)
    out = np.ones((len(x), 3))
    out[:, :2] = x
    return out


def _cross_point(e, x):
    """``np.cross(e, (x, y, 1))`` for a 3-vector e and points x (N, 2), written out."""
    x = np.asarray(x, float)
    out = np.empty((len(x), 3))
    out[:, 0] = e[1] - e[2] * x[:, 1]
    out[:, 1] = e[2] * x[:, 0] - e[0]
    out[:, 2] = e[0] * x[:, 1] - e[1] * x[:, 0]
    return out


@dataclass(frozen=True)
class EpipolarGeometry:
    """The epipolar geometry of a rig in ideal pixels.

    Attributes
    ----------
    F : ndarray, shape (3, 3)
        Fundamental matrix, ``y^T F x = 0`` for left x, right y.
    center : ndarray, shape (2,)
        Principal point of the left camera, px: where band offsets are read.
    ref_left, ref_right : ndarray, shape (2,)
        Unit directions along the epipolar lines at the left principal point
        and at its image in the right camera through the plane
        ``Z = depth``: a point moving along the epipolar line in the sense of
        ``ref_left`` in the left image moves in the sense of ``ref_right``
        in the right image (for points near that depth).
    epipole_left, epipole_right : ndarray, shape (3,)
        Homogeneous epipoles (unit vectors): the images of the other
        camera's centre.
    K1, K2, R, T : the calibration's pinhole part.
    """

    F: np.ndarray
    epipole_left: np.ndarray
    epipole_right: np.ndarray
    center: np.ndarray
    ref_left: np.ndarray
    ref_right: np.ndarray
    K1: np.ndarray
    K2: np.ndarray
    R: np.ndarray
    T: np.ndarray

    def left_lines(self, x):
        """Epipolar lines (N, 3) in the left image through left points x (N, 2),
        normalised and oriented (normal = ``ref_left`` turned by +90 deg)."""
        return self._orient(_cross_point(self.epipole_left, x), self.ref_left)

    def left_lines_of_right(self, y):
        """Left epipolar lines (N, 3) of right points y (N, 2), oriented as :meth:`left_lines`."""
        return self._orient(_homogeneous(y) @ self.F, self.ref_left)

    def right_lines(self, x):
        """Right epipolar lines (N, 3) of left points x (N, 2), oriented by ``ref_right``."""
        return self._orient(_homogeneous(x) @ self.F.T, self.ref_right)

    def right_lines_through(self, y):
        """Right epipolar lines (N, 3) through right points y (N, 2)."""
        return self._orient(_cross_point(self.epipole_right, y), self.ref_right)

    @staticmethod
    def _orient(lines, ref):
        lines = lines / np.hypot(lines[:, 0], lines[:, 1])[:, None]
        normal_ref = np.array([-ref[1], ref[0]])
        sign = np.where(lines[:, :2] @ normal_ref < 0, -1.0, 1.0)
        return lines * sign[:, None]

    def band_left(self, x):
        """Band offsets (N,) of left points: signed distance, px, of their
        epipolar line from the left principal point."""
        return self._offset(self.left_lines(x))

    def band_right(self, y):
        """Band offsets (N,) of right points, on the same scale as :meth:`band_left`."""
        return self._offset(self.left_lines_of_right(y))

    def _offset(self, lines):
        return -(lines[:, :2] @ self.center + lines[:, 2])

    def directions_left(self, x):
        """Unit directions (N, 2) along the left epipolar lines at x, in the sense of ``ref_left``."""
        lines = self.left_lines(x)
        return np.c_[lines[:, 1], -lines[:, 0]]

    def directions_right(self, y):
        """Unit directions (N, 2) along the right epipolar lines at y, in the sense of ``ref_right``."""
        lines = self.right_lines_through(y)
        return np.c_[lines[:, 1], -lines[:, 0]]


def epipolar_geometry(calib, depth=None):
    """The :class:`EpipolarGeometry` of a calibration.

    Parameters
    ----------
    calib : StereoCalibration
    depth : float, optional
        Depth (mm, rig frame) of the plane that fixes which sense along the
        right epipolar lines corresponds to ``ref_left``; default where the
        two optical axes pass closest, or three baselines if they diverge.

    Returns
    -------
    EpipolarGeometry

    Notes
    -----
    The sense matters only for polarity and for choosing between the two
    intersections of an epipolar line with an ellipse; it is the same for
    all depths unless the scene straddles a camera centre's plane, so any
    plausible working depth gives it.
    """
    K1, K2 = np.asarray(calib.K1, float), np.asarray(calib.K2, float)
    R, T = np.asarray(calib.R, float), np.asarray(calib.T, float).ravel()
    F = fundamental_matrix(K1, K2, R, T)
    if depth is None:
        depth = _convergence_depth(R, T)
    center = K1[:2, 2].copy()
    # The direction at the centre points away from the left epipole (its
    # sign is only a convention); the right sense follows by transfer.
    u, _, vt = np.linalg.svd(F)
    e, e_right = vt[-1], u[:, -1]
    toward = center * e[2] - e[:2]  # (c - e) scaled by e_w, well defined at infinity
    line = np.cross(e, np.r_[center, 1.0])
    d = np.array([line[1], -line[0]])
    d /= np.linalg.norm(d)
    if d @ toward < 0:
        d = -d
    H = K2 @ (R + np.outer(T, [0.0, 0.0, 1.0 / depth])) @ np.linalg.inv(K1)
    p0 = H @ np.r_[center, 1.0]
    p1 = H @ np.r_[center + 1.0 * d, 1.0]
    dr = p1[:2] / p1[2] - p0[:2] / p0[2]
    dr /= np.linalg.norm(dr)
    return EpipolarGeometry(F, e, e_right, center, d, dr, K1, K2, R, T)


def _convergence_depth(R, T):
    c2 = -R.T @ T
    a2 = R.T @ np.array([0.0, 0.0, 1.0])
    a1 = np.array([0.0, 0.0, 1.0])
    # Closest points of the optical axes s a1 and c2 + t a2.
    A = np.array([[a1 @ a1, -a1 @ a2], [a1 @ a2, -a2 @ a2]])
    b = np.array([a1 @ c2, a2 @ c2])
    try:
        s, _ = np.linalg.solve(A, b)
    except np.linalg.LinAlgError:
        s = -1.0
    return float(s) if s > 0 else 3.0 * float(np.linalg.norm(T))


# -------------------------------------------------------------------- matching


@dataclass(frozen=True)
class Match:
    """A left and a right feature taken as images of one edge.

    Attributes
    ----------
    left, right : int
        Indices into the left and right feature lists.
    cost : float
        Total matching cost (lower is better; 0 is perfect).
    band_overlap : float
        Intersection over union of the two epipolar bands.
    shape_cost : float
        The part of the cost from shape disagreement.
    margin : float
        How much the total assignment cost rises if this pair is forbidden
        (large: unambiguous).
    """

    left: int
    right: int
    cost: float
    band_overlap: float
    shape_cost: float
    margin: float


@dataclass(frozen=True)
class Unmatched:
    """A feature left without a partner.

    Attributes
    ----------
    side : str
        "left" or "right".
    feature : int
        Index into that side's feature list.
    reason : str
        A key of :data:`REASONS`.
    detail : str
        Human-readable specifics (e.g. the angle of a degenerate line, the
        competing candidates).
    epipolar_angle : float
        Lines: angle to the epipolar lines, rad (NaN for arcs).
    """

    side: str
    feature: int
    reason: str
    detail: str
    epipolar_angle: float = float("nan")


@dataclass(frozen=True)
class Matching:
    """Result of :func:`match_features`.

    Attributes
    ----------
    matches : tuple of Match
    unmatched : tuple of Unmatched
    cost : ndarray, shape (n_left, n_right)
        The cost matrix (inf: not a candidate).
    epipolar_angle_left, epipolar_angle_right : ndarray
        Per feature, the angle between a line and the epipolar lines, rad
        (NaN for arcs).
    """

    matches: tuple
    unmatched: tuple
    cost: np.ndarray
    epipolar_angle_left: np.ndarray
    epipolar_angle_right: np.ndarray


def _bands(geo, feats, side):
    out = np.empty((len(feats), 2))
    for k, f in enumerate(feats):
        t = geo.band_left(f.ideal.xy) if side == "left" else geo.band_right(f.ideal.xy)
        out[k] = t.min(), t.max()
    return out


def line_angles(geo, feats, side):
    """Angle between each line and the epipolar lines, rad, in [0, pi/2]; NaN for arcs.

    Parameters
    ----------
    geo : EpipolarGeometry
    feats : sequence of ImageFeature
        Features of one image (their line fits in ideal pixels).
    side : str
        "left" or "right": the image they are in.

    Returns
    -------
    ndarray, shape (len(feats),)
        Taken at each line's centroid: a line at a small angle is nearly
        parallel to the epipolar lines, which then fix its position along
        them, hence its depth, poorly (``MIN_EPIPOLAR_ANGLE``).
    """
    out = np.full(len(feats), np.nan)
    for k, f in enumerate(feats):
        if f.kind != "line":
            continue
        c = f.fit.centroid[None]
        d = geo.directions_left(c)[0] if side == "left" else geo.directions_right(c)[0]
        out[k] = np.arcsin(min(1.0, abs(d @ f.fit.normal)))
    return out


def _axis_ratios(feats):
    """Minor/major axis ratio of each arc's fitted ellipse; NaN for lines."""
    out = np.full(len(feats), np.nan)
    for k, f in enumerate(feats):
        if f.kind == "arc":
            a, b = f.fit.params[2:4]
            out[k] = min(a, b) / max(a, b) if max(a, b) > 0 else 0.0
    return out


def _line_polarity(geo, f, side):
    d = geo.directions_left(f.ideal.xy) if side == "left" else geo.directions_right(f.ideal.xy)
    return 1 if np.mean(np.einsum("ni,ni->n", d, f.ideal.normal)) > 0 else -1


def _signed_line_angle(geo, f, side):
    c = f.fit.centroid[None]
    d = geo.directions_left(c)[0] if side == "left" else geo.directions_right(c)[0]
    t = f.fit.direction
    if t @ d < 0:
        t = -t
    return float(np.arctan2(d[0] * t[1] - d[1] * t[0], d @ t))


def arc_circle(geo, fl, fr):
    """The 3D circle two matched arcs' ellipses suggest, before any 3D fit.

    Returns
    -------
    center : ndarray, shape (3,)
        The ellipse centres triangulated, rig frame, mm (the centre of the
        circle's image is not the image of its centre, but close to it for
        the holes of a part in view).
    radii : tuple of float
        Each view's semi-major axis scaled by the centre's depth over the
        focal length, mm: the 3D radius each image shows.
    depths : tuple of float
        The centre's depth in the left and right camera, mm.
    """
    X = triangulate(fl.fit.center[None], fr.fit.center[None], geo.K1, geo.K2, geo.R, geo.T)[0]
    zl = X[2]
    zr = (geo.R @ X + geo.T)[2]
    rl = fl.fit.params[2] * zl / geo.K1[0, 0]
    rr = fr.fit.params[2] * zr / geo.K2[0, 0]
    return X, (rl, rr), (zl, zr)


def _radius_scale(fl, fr, tolerance):
    """Scale of ``|log(r_left / r_right)|`` in the cost of a pair of arcs.

    ``tolerance`` and ``RADIUS_COVERAGE`` times the standard uncertainty of
    the log-ratio in quadrature, at most ``RADIUS_WIDENING_MAX`` times
    ``tolerance``. The ratio's uncertainty is that of the two
    semi-major axes (independent images; JCGM 100, 5.1.2), read from each
    ellipse fit's covariance; the centre's depth scales both radii alike
    and drops out of their ratio. A fit without a covariance adds nothing.
    """
    var = 0.0
    for f in (fl, fr):
        cov = getattr(f.fit, "cov", None)
        if cov is not None and f.fit.params[2] > 0:
            var += float(cov[2, 2]) / float(f.fit.params[2]) ** 2
    return float(min(np.hypot(tolerance, RADIUS_COVERAGE * np.sqrt(var)), RADIUS_WIDENING_MAX * tolerance))


def _line_middle_depth(geo, fl, fr, lo, hi):
    """Depths (left, right) of the triangulated point of the two lines at band offset (lo + hi) / 2."""
    t = 0.5 * (lo + hi)
    # The left epipolar line at offset t: through the centre shifted by t along its normal.
    n_ref = np.array([-geo.ref_left[1], geo.ref_left[0]])
    p = geo.center + t * n_ref
    l_ep = geo.left_lines(p[None])[0]
    x = np.cross(l_ep, fl.fit.params)
    if abs(x[2]) < 1e-12:
        return -1.0, -1.0
    x = x[:2] / x[2]
    l_r = geo.right_lines(x[None])[0]
    y = np.cross(l_r, fr.fit.params)
    if abs(y[2]) < 1e-12:
        return -1.0, -1.0
    y = y[:2] / y[2]
    X = triangulate(x[None], y[None], geo.K1, geo.K2, geo.R, geo.T)[0]
    return X[2], (geo.R @ X + geo.T)[2]


def match_features(left, right, geo, *, min_points=12, min_angle=MIN_EPIPOLAR_ANGLE, min_axis_ratio=MIN_AXIS_RATIO,
                   band_tolerance=3.0, min_overlap=0.5, radius_tolerance=0.1, angle_tolerance=np.deg2rad(30.0),
                   max_cost=1.0, ambiguity_margin=0.1, depth_range=None):
    """Pair left and right image features one to one.

    Parameters
    ----------
    left, right : list of ImageFeature
        From :func:`partinspect.vision.imagefeatures.image_features` of each
        image.
    geo : EpipolarGeometry
    min_points : int
        Features with fewer points are reported "too_short".
    min_angle : float
        Lines closer than this to the epipolar lines (in either image) are
        "degenerate", rad.
    min_axis_ratio : float
        Arcs whose ellipse's minor/major axis ratio is below this (in
        either image) are "edge_on".
    band_tolerance : float
        Each band is widened by this at both ends, px (the two images trim
        their segments' ends independently).
    min_overlap : float
        Smallest intersection over union of the two (widened) bands for a
        pair to be a candidate.
    radius_tolerance : float
        Arcs: scale of ``|log(r_left / r_right)|`` in the cost, the 3D radii
        seen by each view (a 10 % disagreement costs 1), widened by what
        the two ellipse fits leave uncertain (:data:`RADIUS_COVERAGE`).
    angle_tolerance : float
        Lines: scale of the difference of the signed angles to the epipolar
        lines in the cost, rad.
    max_cost : float
        Pairs costing more are rejected.
    ambiguity_margin : float
        A match whose best alternative assignment costs less than this more,
        and breaks the ordering constraint (matched lines keep their order
        along the epipolar lines) no more often, is "ambiguous" and not kept.
    depth_range : (float, float), optional
        Plausible depths of the scene, mm; default only "in front of both
        cameras".

    Returns
    -------
    Matching

    Notes
    -----
    A degenerate or edge-on feature takes part in no pair, nor does a
    shading ramp's crest (:mod:`partinspect.vision.ramps`); a feature left
    unmatched whose band holds such a feature of its kind and polarity is
    given that feature's reason, naming it. The cost of a candidate pair is ``(1 - IoU of the bands) + shape cost``;
    polarity disagreement (unless either feature is of mixed polarity), a
    kind mismatch or a triangulated point outside the depth range exclude
    the pair. Dummy rows and columns of cost ``max_cost / 2`` make leaving
    both features unmatched cheaper than any pair costing more than
    ``max_cost``.
    """
    depth = depth_range if depth_range is not None else (0.0, np.inf)
    sl = _side(geo, left, "left", min_points, min_angle, min_axis_ratio)
    sr = _side(geo, right, "right", min_points, min_angle, min_axis_ratio)
    c = _candidates(geo, left, right, sl, sr, band_tolerance=band_tolerance, min_overlap=min_overlap,
                    radius_tolerance=radius_tolerance, angle_tolerance=angle_tolerance, max_cost=max_cost,
                    depth=depth)
    matches, ambiguous = _assigned(geo, left, right, c, max_cost, ambiguity_margin)
    unmatched = (_unmatched("left", left, sl, sr, {m.left for m in matches}, c, ambiguous, min_points)
                 + _unmatched("right", right, sr, sl, {m.right for m in matches}, c.transposed(), ambiguous,
                              min_points))
    return Matching(tuple(matches), tuple(unmatched), c.cost, sl.angle, sr.angle)


@dataclass(frozen=True)
class _Side:
    """What the matching reads of the features of one image, per feature."""

    band: np.ndarray
    """(n, 2): lowest and highest band offset, px."""
    angle: np.ndarray
    """Lines: angle to the epipolar lines, rad (:func:`line_angles`); NaN for arcs."""
    long: np.ndarray
    """Whether it has at least ``min_points`` points."""
    ramp: np.ndarray
    """Whether it is a shading ramp's crest (``ramp_share`` above ``RAMP_SHARE``): no candidate of any pair."""
    unfit: list
    """None, or (reason, detail) for a degenerate line or an edge-on arc (:func:`_unfit`)."""
    usable: np.ndarray
    """Long and not unfit: may take part in a pair."""
    polarity: list
    """Arcs: their own; lines: of the grey level along the epipolar lines (:func:`_line_polarity`)."""
    signed_angle: list
    """Lines: signed angle to the epipolar lines, rad (:func:`_signed_line_angle`); 0 for arcs."""


def _side(geo, feats, side, min_points, min_angle, min_axis_ratio):
    """The :class:`_Side` of the features ``feats`` of image ``side`` ("left" or "right")."""
    band = _bands(geo, feats, side)
    angle = line_angles(geo, feats, side)
    ratio = _axis_ratios(feats)
    long = np.array([len(f) >= min_points for f in feats], bool)
    ramp = np.array([_ramp_share(f) > RAMP_SHARE for f in feats], bool)
    unfit = [_unfit(angle[k], ratio[k], min_angle, min_axis_ratio) for k in range(len(feats))]
    usable = long & np.array([u is None for u in unfit], bool)
    polarity = [f.polarity if f.kind == "arc" else _line_polarity(geo, f, side) for f in feats]
    signed_angle = [_signed_line_angle(geo, f, side) if f.kind == "line" else 0.0 for f in feats]
    return _Side(band, angle, long, ramp, unfit, usable, polarity, signed_angle)


def _ramp_share(f):
    """The feature's ``ramp_share``, or -inf where it was not read (features of the 2D chain alone)."""
    share = getattr(f, "ramp_share", None)
    return -np.inf if share is None or not np.isfinite(share) else share


@dataclass(frozen=True)
class _Candidates:
    """The candidate pairs, (n_left, n_right) matrices."""

    cost: np.ndarray
    """Matching cost; inf where not a candidate or above ``max_cost``."""
    iou: np.ndarray
    """Intersection over union of the widened bands (0 where they do not meet)."""
    shape: np.ndarray
    """Shape part of the cost; inf where not evaluated."""
    in_band: np.ndarray
    """Bands overlapping by ``min_overlap`` at least."""
    same_kind: np.ndarray
    """In band and of one kind."""
    blocked: np.ndarray
    """In band, of one kind and polarity, but one of them degenerate or edge-on: would-be partners."""

    def transposed(self):
        """The same with the right image's features as rows."""
        return _Candidates(self.cost.T, self.iou.T, self.shape.T, self.in_band.T, self.same_kind.T, self.blocked.T)


def _candidates(geo, left, right, sl, sr, *, band_tolerance, min_overlap, radius_tolerance, angle_tolerance,
                max_cost, depth):
    """Every pair's band overlap and shape cost (see :func:`match_features`' notes).

    ``sl`` and ``sr`` are the :class:`_Side` of the left and right
    features; ``depth`` is (zmin, zmax), mm.
    """
    nl, nr = len(left), len(right)
    cost = np.full((nl, nr), np.inf)
    iou = np.zeros((nl, nr))
    shape = np.full((nl, nr), np.inf)
    in_band = np.zeros((nl, nr), bool)
    same_kind = np.zeros((nl, nr), bool)
    blocked = np.zeros((nl, nr), bool)
    for i in np.flatnonzero(sl.long & ~sl.ramp):
        lo_i, hi_i = sl.band[i, 0] - band_tolerance, sl.band[i, 1] + band_tolerance
        for j in np.flatnonzero(sr.long & ~sr.ramp):
            lo_j, hi_j = sr.band[j, 0] - band_tolerance, sr.band[j, 1] + band_tolerance
            inter = min(hi_i, hi_j) - max(lo_i, lo_j)
            if inter <= 0:
                continue
            iou[i, j] = inter / (max(hi_i, hi_j) - min(lo_i, lo_j))
            if iou[i, j] < min_overlap:
                continue
            in_band[i, j] = True
            fl, fr = left[i], right[j]
            if fl.kind != fr.kind:
                continue
            same_kind[i, j] = True
            if sl.polarity[i] != sr.polarity[j] and not (fl.mixed_polarity or fr.mixed_polarity):
                continue
            if not (sl.usable[i] and sr.usable[j]):
                blocked[i, j] = True
                continue
            s = _shape_cost(geo, fl, fr, sl.signed_angle[i], sr.signed_angle[j], max(lo_i, lo_j),
                            min(hi_i, hi_j), depth, radius_tolerance, angle_tolerance)
            if s is None:
                continue
            shape[i, j] = s
            c = (1.0 - iou[i, j]) + s
            if c <= max_cost:
                cost[i, j] = c
    return _Candidates(cost, iou, shape, in_band, same_kind, blocked)


def _shape_cost(geo, fl, fr, angle_l, angle_r, lo, hi, depth, radius_tolerance, angle_tolerance):
    """The shape disagreement of two features of one kind, or None if their triangulation is out of ``depth``.

    Arcs: ``|log(r_left / r_right)|`` of the 3D radii each view shows
    (:func:`arc_circle`) over :func:`_radius_scale`; lines: the difference
    of their signed angles to the epipolar lines (``angle_l``,
    ``angle_r``, rad, modulo pi) over ``angle_tolerance``, triangulated at
    the middle of the bands' overlap (``lo``, ``hi``, px). ``depth`` is
    (zmin, zmax), mm, open at both ends.
    """
    zmin, zmax = depth
    if fl.kind == "arc":
        _, (rl, rr), (zl, zr) = arc_circle(geo, fl, fr)
        if not (zmin < zl < zmax and zmin < zr < zmax) or rl <= 0 or rr <= 0:
            return None
        return abs(np.log(rl / rr)) / _radius_scale(fl, fr, radius_tolerance)
    zl, zr = _line_middle_depth(geo, fl, fr, lo, hi)
    if not (zmin < zl < zmax and zmin < zr < zmax):
        return None
    # Line angles are defined modulo pi.
    return abs((angle_l - angle_r + 0.5 * np.pi) % np.pi - 0.5 * np.pi) / angle_tolerance


def _assigned(geo, left, right, c, max_cost, ambiguity_margin):
    """The optimal one-to-one assignment less its ambiguous pairs.

    Returns
    -------
    matches : list of Match
    ambiguous : dict
        ("left" | "right", index) -> the detail of a pair left out as
        ambiguous: its best alternative assignment costs less than
        ``ambiguity_margin`` more and breaks the ordering constraint no
        more often (:func:`_order_violations`).
    """
    cost = c.cost
    pairs, total = _assign(cost, max_cost)
    matches, ambiguous = [], {}
    for i, j in pairs:
        forbidden = cost.copy()
        forbidden[i, j] = np.inf
        alt_pairs, alt_total = _assign(forbidden, max_cost)
        margin = alt_total - total
        rivals = [(a, b) for a, b in alt_pairs if (a == i) != (b == j)]
        if margin < ambiguity_margin and rivals and \
                _order_violations(geo, left, right, alt_pairs) <= _order_violations(geo, left, right, pairs):
            ambiguous[("left", i)] = ambiguous[("right", j)] = (
                f"left {i} / right {j} (cost {cost[i, j]:.2f}) vs "
                + ", ".join(f"left {a} / right {b} (cost {cost[a, b]:.2f})" for a, b in rivals)
            )
            continue
        matches.append(Match(int(i), int(j), float(cost[i, j]), float(c.iou[i, j]), float(c.shape[i, j]),
                             float(margin)))
    return matches, ambiguous


def _unmatched(side, feats, mine, theirs, taken, c, ambiguous, min_points):
    """The features of image ``side`` left without a partner, each with its reason.

    ``mine`` and ``theirs`` are the :class:`_Side` of this image and the
    other; ``c`` the :class:`_Candidates` with this image's features as
    rows; ``taken`` the indices matched.
    """
    other = "right" if side == "left" else "left"
    out = []
    for k, f in enumerate(feats):
        if k in taken:
            continue
        ang = float(mine.angle[k])
        partners = [o for o in np.flatnonzero(c.blocked[k]) if theirs.unfit[o] is not None]
        if len(f) < min_points:
            out.append(Unmatched(side, k, "too_short", f"{len(f)} points < {min_points}", ang))
        elif mine.ramp[k]:
            out.append(Unmatched(side, k, "ramp", f"the grey-level slope on either side keeps "
                                                  f"{100 * f.ramp_share:.0f} % of its peak gradient", ang))
        elif mine.unfit[k] is not None:
            out.append(Unmatched(side, k, mine.unfit[k][0], mine.unfit[k][1], ang))
        elif partners and not np.isfinite(c.cost[k]).any():
            o = partners[0]
            out.append(Unmatched(side, k, theirs.unfit[o][0],
                                 f"its counterpart in the {other} image (feature {int(o)}): " + theirs.unfit[o][1],
                                 ang))
        elif (side, k) in ambiguous:
            out.append(Unmatched(side, k, "ambiguous", ambiguous[(side, k)], ang))
        elif not c.in_band[k].any():
            out.append(Unmatched(side, k, "no_candidate", "", ang))
        elif not c.same_kind[k].any():
            out.append(Unmatched(side, k, "kind_mismatch", f"{f.kind} with only other kinds in its band", ang))
        elif not np.isfinite(c.cost[k]).any():
            out.append(Unmatched(side, k, "shape_mismatch", "", ang))
        else:
            others = np.flatnonzero(np.isfinite(c.cost[k]))
            out.append(Unmatched(side, k, "outcompeted", "candidates " + ", ".join(str(int(o)) for o in others),
                                 ang))
    return out


def _unfit(angle, ratio, min_angle, min_axis_ratio):
    """Why a feature cannot be measured by its geometry alone: None, or (reason, detail)."""
    if angle < min_angle:
        return ("degenerate",
                f"{np.degrees(angle):.1f} deg from the epipolar lines (< {np.degrees(min_angle):.1f} deg)")
    if ratio < min_axis_ratio:
        return ("edge_on", f"ellipse axis ratio {ratio:.2f} (< {min_axis_ratio:.2f}): seen about "
                           f"{np.degrees(np.arccos(min(1.0, ratio))):.0f} deg off its axis")
    return None


def _order_violations(geo, left, right, pairs):
    """Pairs of matched lines whose order along the epipolar lines differs between the images.

    Opaque surfaces seen from both cameras keep their order along the
    epipolar lines (the ordering constraint); it separates parallel edges
    whose bands and shapes are alike.
    """
    lines = [(i, j) for i, j in pairs if left[i].kind == "line"]
    n_ref = np.array([-geo.ref_left[1], geo.ref_left[0]])
    bad = 0
    for a in range(len(lines)):
        for b in range(a + 1, len(lines)):
            (i, j), (k, l) = lines[a], lines[b]
            lo = max(geo.band_left(left[i].ideal.xy).min(), geo.band_left(left[k].ideal.xy).min(),
                     geo.band_right(right[j].ideal.xy).min(), geo.band_right(right[l].ideal.xy).min())
            hi = min(geo.band_left(left[i].ideal.xy).max(), geo.band_left(left[k].ideal.xy).max(),
                     geo.band_right(right[j].ideal.xy).max(), geo.band_right(right[l].ideal.xy).max())
            if hi <= lo:
                continue
            ep = geo.left_lines((geo.center + 0.5 * (lo + hi) * n_ref)[None])
            xi = np.cross(ep[0], left[i].fit.params)
            xk = np.cross(ep[0], left[k].fit.params)
            xi, xk = xi[:2] / xi[2], xk[:2] / xk[2]
            er = geo.right_lines(xi[None])[0]
            yj = np.cross(er, right[j].fit.params)
            yl = np.cross(er, right[l].fit.params)
            yj, yl = yj[:2] / yj[2], yl[:2] / yl[2]
            if np.sign((xk - xi) @ geo.ref_left) != np.sign((yl - yj) @ geo.ref_right):
                bad += 1
    return bad


def _assign(cost, max_cost):
    """Optimal one-to-one pairs under ``cost`` with the option of leaving features unmatched."""
    nl, nr = cost.shape
    if nl == 0 or nr == 0:
        return [], 0.0
    big = 1e6
    half = 0.5 * max_cost
    A = np.full((nl + nr, nr + nl), big)
    A[:nl, :nr] = np.where(np.isfinite(cost), cost, big)
    # Left i unmatched -> its dummy column nr + i; right j unmatched -> dummy row nl + j.
    A[np.arange(nl), nr + np.arange(nl)] = half
    A[nl + np.arange(nr), np.arange(nr)] = half
    A[nl:, nr:] = 0.0
    rows, cols = linear_sum_assignment(A)
    total = float(A[rows, cols].sum())
    pairs = [(int(r), int(c)) for r, c in zip(rows, cols) if r < nl and c < nr and A[r, c] < big]
    return pairs, total
