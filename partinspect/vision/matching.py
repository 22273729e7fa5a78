"""Matching of left and right image features by the epipolar constraint.

Each image's segments (straight lines and elliptical arcs) are first merged
where several pieces are one edge (collinear lines, co-elliptic arcs: the
same physical edge interrupted by an occlusion, a specular spot or a corner
of the segmentation) and refitted in *ideal* pixel coordinates. Left and
right features are then paired:

- every feature spans a range of epipolar lines, its *band* (a 1-D
  interval: the signed offset, in ideal left-image pixels at the image
  centre, of the epipolar line through each of its points); two images of
  one edge span the same band up to their ends' trimming, so candidates
  must overlap [2]_;
- their shapes must agree: the same kind; the same polarity (the grey level
  rises in the same sense along the epipolar lines, or for arcs on the same
  side of the ellipse; not compared for an arc merged from pieces of
  opposite polarity); for arcs, the same 3D radius once each ellipse's
  size is scaled by its depth (centres triangulated), to within what the
  two ellipse fits leave uncertain (a short arc's size is known to a few
  per cent only); for lines, similar
  angles to the epipolar lines and a triangulated middle in front of both
  cameras;
- a one-to-one assignment (Hungarian algorithm) minimises the summed cost,
  with a rejection threshold for pairs too poor to keep.

Nothing is dropped silently: every feature left without a partner is
returned with its reason. Two geometries are not measured at all, and are
reported with the figure that rules them out rather than matched:

- a line nearly parallel to the epipolar lines is *degenerate*: its
  position along them, hence its depth, is undetermined;
- an elliptical arc whose minor/major axis ratio is small is a circle seen
  nearly *edge-on* (the ratio is about the cosine of the angle between the
  line of sight and the circle's axis): the radius of curvature at the ends
  of its major axis, b^2 / a, falls to a pixel or two, below what the edge
  detector's first-order smoothing correction models; the two sides of the
  ellipse crowd each other; a hole's rim is seen against its own wall,
  whose shading changes along the thin ellipse, so only pieces of it are
  found. Its points are then displaced by more than their uncertainty says.
  On renders of the sample plate (1224 x 1024 px, noise 2) holes whose
  thinner image had axis ratio 0.095 and 0.13 came out 0.096 and 0.016 mm
  too small in diameter with U = 0.072 and 0.014 mm: false fails; from
  0.13 (that one) to 0.18, 3 of 5 were within U. The threshold, 0.2
  (78.5 degrees off axis), is above all of these. Thin partial arcs above
  it can still be biased where the rim's contrast varies along them: a
  displacement of the edge points, not a geometric degeneracy, and not
  rejected here.

A feature whose only plausible partner in the other image is degenerate or
edge-on gets that partner's reason, so both images tell the same story.

All coordinates are ideal pixels (distortion removed, see
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

from dataclasses import dataclass, replace

import cv2
import numpy as np
from scipy.optimize import linear_sum_assignment

from partinspect.vision.fitting import (
    EllipseJob,
    as_points,
    axis_bound,
    direct_residuals,
    ellipse_geometry,
    ellipse_with_covariance,
    fit_ellipses,
    fit_line,
    line_with_covariance,
)
from partinspect.vision.ideal import IdealPoints, ideal_points
from partinspect.vision.triangulation import fundamental_matrix, triangulate

__all__ = [
    "EpipolarGeometry",
    "ImageFeature",
    "Match",
    "Unmatched",
    "Matching",
    "epipolar_geometry",
    "image_features",
    "match_features",
    "REASONS",
    "MIN_EPIPOLAR_ANGLE",
    "MIN_AXIS_RATIO",
    "chauvenet_z",
]

MIN_EPIPOLAR_ANGLE = np.deg2rad(8.0)
"""Lines closer than this to the epipolar lines (in either image) are "degenerate", rad."""
MIN_AXIS_RATIO = 0.2
"""Arcs whose fitted ellipse has a minor/major axis ratio below this (in
either image) are "edge-on": the circle is seen more than arccos 0.2 = 78.5
degrees off its axis. See the module notes for the evidence."""
RADIUS_COVERAGE = 2.0
"""Coverage factor on the standard uncertainty of ``log(r_left / r_right)``
that two arcs' ellipse fits leave: the ratio's tolerance in the matching
cost is ``radius_tolerance`` widened in quadrature by this many standard
uncertainties (:func:`_radius_scale`). A short arc's semi-major axis is
uncertain by several per cent: the plate's 12 mm hole's bottom rim, a
quarter of it seen through the hole (bench_plan's default pose), 5-8 % in
the left image and 2 % in the right. It went unmatched in 12 of 50 noise
draws (the four looked at: "features in its band disagree in ... size",
the two views' radii 7.5-12 % apart, which with their bands' partial
overlap cost more than ``max_cost``); in 4 of 50 with this widening."""
RADIUS_WIDENING_MAX = 2.0
"""The widened tolerance never exceeds this many times ``radius_tolerance``
(a 20 % disagreement costs 1): the radius is the only shape an arc is
matched by besides its band, and an arc too short to tell its radius
within that would be paired on its band alone, where arcs of neighbouring
holes overlap. Such arcs are left unmatched as before, with the reason.
(The 25-point sliver of a rim at the right image's border in the
degenerate-geometry tests, its ellipse's semi-major axis uncertain by
16 %, 18 % off the left image's radius, is one: matched, its circularity
over that sliver read 2.4 of its u.)"""

REASONS = {
    "too_short": "too few edge points to be measured",
    "degenerate": "line nearly parallel to the epipolar lines: its position along them is undetermined",
    "edge_on": "circle seen nearly edge-on: its ellipse is too thin for a reliable radius",
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


# -------------------------------------------------------------- image features


@dataclass(frozen=True)
class ImageFeature:
    """One edge in one image: one segment or several merged ones.

    Attributes
    ----------
    kind : str
        "line" or "arc" (an elliptical arc, possibly a whole ellipse).
    segments : tuple of int
        Indices of the segments (of ``segment_contours``) it is made of.
    index : ndarray, shape (N,)
        Indices into the image's EdgePoints of its points (the segments'
        ``fit_index``), each segment's points in order along the edge.
    uv : ndarray, shape (N, 2)
        The points in distorted pixels (as detected).
    cov_uv : ndarray, shape (N, 2, 2)
        Their covariances, px^2.
    ideal : IdealPoints
        The points in ideal pixels with their covariances.
    fit : LineFit or EllipseFit
        Fit to the ideal points (``corr_length`` = the edge filter's sigma),
        ideal pixels.
    blur : float
        Median width of the edge profile, px (for information: the fits
        are not corrected for the smoothing bias of curved edges).
    polarity : int
        Lines: +1 if the grey level rises along ``ref`` of the epipolar
        geometry, -1 if it falls (0 before matching). Arcs: +1 if brighter
        outside the ellipse, -1 if brighter inside (of most points, when
        ``mixed_polarity``).
    mixed_polarity : bool
        An arc merged from pieces of opposite polarity: the faces on the two
        sides of the edge exchange brightness along it (a hole's rim against
        its inner wall, lit on one side and in shadow on the other). Its
        polarity is then not compared in matching: where the exchange
        happens depends on the view (each camera sees another part of the
        wall).
    """

    kind: str
    segments: tuple
    index: np.ndarray
    uv: np.ndarray
    cov_uv: np.ndarray
    ideal: IdealPoints
    fit: object
    blur: float
    polarity: int
    mixed_polarity: bool = False

    def __len__(self):
        return len(self.index)


FIT_SIGMA_TOL = 1e-3
"""Ellipse fits of features are converged when the remaining Gauss-Newton
step is below this many standard uncertainties in every direction (or at
fit_ellipse's pixel tolerance, whichever comes first)."""
FIT_ITERATIONS = 30
"""Iterations of an ellipse fit of a feature at most: well-determined ones
converge in a few (from the segment's fit, or after dropping a point from
the previous one)."""

OUTLIER_ALPHA = 0.05
"""Chance that a feature of N clean points loses one to the outlier test:
a point is an outlier when its residual exceeds ``norm.isf(OUTLIER_ALPHA /
(2 N))`` (Chauvenet's criterion at this level: 3.6 for 150 points, 4.0 for
900) times its own standard uncertainty, scaled up by the robust spread of
the normalised residuals when that exceeds 1 (a very clean image whose
sub-pixel ripple is as large as its noise). Outliers are corner-rounded
ends and a neighbouring edge's smoothing; one of them sets a form zone, which
is the maximum residual."""
OUTLIER_Z_MAX = 5.0
"""The threshold never exceeds this (one Gaussian point in 1.7 million)."""
MAX_OUTLIER_FRACTION = 0.1
"""At most this fraction of a feature's points is rejected: more means the
model (line / ellipse) is wrong, which the segmentation's test must see."""
FADE_RATIO = 5.0
"""Points of an arc whose standard uncertainty across the edge exceeds this
many times the arc's median are left out (see :func:`_unfaded` for a
segment of lower contrast): there the edge profile has
flattened (a weak or broad step), and the sub-pixel position follows
whatever else is beside the edge. Where a hole's rim fades against its lit
inner wall, the contour runs on along what remains of the step and then
along the wall's shading, and a short arc's ellipse bends to take such a
tail in and passes every residual test, off by up to 1 mm in 3D."""
FADE_END_RATIO = 2.5
"""The same at the ends of each segment of an arc, from the end inwards
while the points exceed this many times the arc's median: a rim fades
towards the end of its visible stretch. (A segment whose median exceeds
this many times the arc's is judged against its own: the plate's 10 mm
hole has a third of its rim at four times the others' uncertainty, all
of it "faded" against the arc's median, and a union of the rim's pieces
dropped it whole in a third of the draws.) On rendered plates and brackets
under six light directions (36 draws each, 5600 rim points), the rim
points' errors against the true rim, normalised by their random and Type B
uncertainties together, had 0.8 % beyond 3 and a largest of 7.5, up to 3 px
off (the points beyond 2.5 times the median at ends, beyond 5 anywhere,
RMS 1.5-2.4); without those points (6 % of them), 0.24-0.47 % and 4.4, as
for Gaussian errors (0.27 %)."""



def chauvenet_z(n):
    """Chauvenet's threshold for the |normalised residuals| of a feature of ``n`` points (see ``OUTLIER_ALPHA``).

    The threshold before the scaling by the residuals' robust spread (3.9
    for 500 points).

    References
    ----------
    .. [1] Taylor, J. R. (1997). An Introduction to Error Analysis, 2nd
           ed., section 6.2 (Chauvenet's criterion).
    """
    from scipy.special import ndtri

    return min(float(-ndtri(OUTLIER_ALPHA / (2.0 * max(int(n), 1)))), OUTLIER_Z_MAX)


def _outlier_threshold(z):
    """Chauvenet's threshold for |normalised residuals| ``z``, scaled by their robust spread (see ``OUTLIER_ALPHA``)."""
    spread = 1.4826 * float(np.median(z))  # MAD of z about zero
    return chauvenet_z(len(z)) * max(1.0, spread)


_IDEAL_FIELDS = ("xy", "cov", "normal", "normal_std", "jacobian")


def _segment_ideal(segments, edges, K, D, used=None):
    """The fitted points of segments in ideal pixels (IdealPoints per segment, None if not ``used``).

    A point's ideal coordinates do not depend on the other points mapped
    with it, so they are computed once, in one call for all the segments
    used (default all), and a feature made of several segments (a merge
    trial) concatenates them instead of mapping its points again.
    """
    used = range(len(segments)) if used is None else sorted(used)
    index = [np.asarray(segments[i].fit_index) for i in used]
    out = [None] * len(segments)
    if not index:
        return out
    allidx = np.concatenate(index)
    ideal = ideal_points(edges.xy[allidx], edges.cov[allidx], K, D, edges.normal[allidx])
    cuts = np.cumsum([len(i) for i in index])[:-1]
    parts = [np.split(getattr(ideal, f), cuts) for f in _IDEAL_FIELDS]
    for i, p in zip(used, zip(*parts)):
        out[i] = IdealPoints(*p)
    return out


def _unfaded(std, lengths):
    """Indices of the points of an arc kept by ``FADE_RATIO`` and ``FADE_END_RATIO``.

    ``std`` are the points' standard uncertainties across the edge, the
    arc's segments one after the other with ``lengths`` points each. The
    ratios are taken to the arc's median, except for a segment whose own
    median exceeds ``FADE_END_RATIO`` times it: a stretch of the rim of
    lower contrast than the rest (the rim of a hole whose inner wall is lit
    on one side), which the arc's median would drop whole, is judged
    against its own. (Against its own median, any segment kept points at
    a fading end: the bracket's flat wall hole kept an end point 0.95 px
    off the rim at 2.4 times its segment's median, 2.7 times the arc's.)
    """
    arc_med = float(np.median(std))
    keep = np.ones(len(std), bool)
    start = 0
    for n in lengths:
        piece = std[start:start + n]
        med = float(np.median(piece))
        if med <= FADE_END_RATIO * arc_med:
            med = arc_med
        keep[start:start + n] = piece <= FADE_RATIO * med
        faded = piece > FADE_END_RATIO * med
        # Runs of faded points at either end of the segment.
        head = int(np.argmin(faded)) if not faded.all() else n
        tail = int(np.argmin(faded[::-1])) if not faded.all() else n
        keep[start:start + head] = False
        keep[start + n - tail:start + n] = False
        start += n
    kept = np.flatnonzero(keep)
    # A very short arc keeps its points: too few are left to fit.
    return kept if len(kept) >= 6 else np.arange(len(std))


def _make_features(requests, segments, edges, seg_ideal):
    """Image features of several (kind, segment ids) requests at once.

    Points of arcs where the edge has faded are left out (``FADE_RATIO``,
    ``FADE_END_RATIO``); each feature is fitted, its worst outlier dropped
    and the fit redone while one remains (below); the ellipse fits of all requests in one such round run
    together (:func:`partinspect.vision.fitting.fit_ellipses`), each as it
    would alone. The fits come without their covariances (``cov`` None):
    most features made are merge trials that are not kept;
    :func:`_with_covariance` completes the kept ones, as the fits would
    have computed them.
    """
    states = []
    for kind, seg_ids in requests:
        index = np.concatenate([segments[i].fit_index for i in seg_ids])
        piece = np.repeat(np.arange(len(seg_ids)), [len(segments[i].fit_index) for i in seg_ids])
        all_ideal = IdealPoints(*(np.concatenate([getattr(seg_ideal[i], f) for i in seg_ids])
                                  for f in _IDEAL_FIELDS))
        keep = np.arange(len(index)) if kind == "line" else _unfaded(all_ideal.normal_std, [
            len(segments[i].fit_index) for i in seg_ids])
        # A single displaced point (a corner-rounded end that passed the
        # segmentation's trim) would otherwise enter the 3D points and make
        # a straight edge look out of straightness by tenths of a mm: points
        # inconsistent with the fit are rejected, worst first, and the fit
        # redone.
        # One arc segment: its own fit (of the same points, in distorted
        # pixels, corrected for the smoothing) starts the fit next to its
        # minimum; the direct fit can start a short piece far from it.
        start = None
        if kind == "arc" and len(seg_ids) == 1 and segments[seg_ids[0]].kind == "arc":
            start = segments[seg_ids[0]].fit.params
        states.append(dict(kind=kind, seg_ids=seg_ids, index=index, piece=piece, all_ideal=all_ideal,
                           keep=keep, budget=int(MAX_OUTLIER_FRACTION * len(index)),
                           start=start))
    active = list(range(len(states)))
    while active:
        jobs = []
        for k in active:
            st = states[k]
            keep = st["keep"]
            st["ideal"] = ideal = IdealPoints(*(np.ascontiguousarray(getattr(st["all_ideal"], f)[keep])
                                                for f in _IDEAL_FIELDS))
            if st["kind"] == "line":
                st["fit"] = fit_line(ideal.xy, ideal.cov, corr_length=edges.sigma, with_cov=False)
            else:
                # No smoothing-bias correction (fit_ellipse's ``blur``): on
                # rendered parts the rims of holes are not uniform discs, and
                # the edge points lie on the true ellipse to 0.01-0.02 px as
                # found, while the correction pushed them 0.03-0.06 px
                # outwards (measured against the truth). After dropping one
                # point the previous fit is a start next to the new minimum
                # (same minimum, fewer iterations).
                jobs.append((k, EllipseJob(as_points(ideal.xy, 6), ideal.cov, edges.sigma, None, st["start"],
                                           max_axis=axis_bound(ideal.xy))))
        # Converged at fit_ellipse's pixel tolerance or once the remaining
        # step is below a thousandth of the parameters' standard
        # uncertainties: a short piece's ellipse is uncertain by pixels, and
        # its cost so flat that the pixel tolerance takes a hundred
        # iterations to reach, for nothing; such a fit (or a union of two
        # edges) stops after FIT_ITERATIONS, as the segmentation's.
        for (k, _), fit in zip(jobs, fit_ellipses([job for _, job in jobs], FIT_ITERATIONS, with_cov=False,
                                                  sigma_tol=FIT_SIGMA_TOL)):
            states[k]["fit"] = fit
        again = []
        for k in active:
            st = states[k]
            fit = st["fit"]
            z = np.abs(fit.residuals) / np.maximum(fit.point_std, 1e-12)
            worst = int(np.argmax(z))
            if z[worst] <= _outlier_threshold(z) or st["budget"] == 0:
                continue
            st["keep"] = np.delete(st["keep"], worst)
            st["budget"] -= 1
            st["start"] = fit.params if st["kind"] == "arc" else None
            again.append(k)
        active = again
    out = []
    for st in states:
        kind, fit, ideal = st["kind"], st["fit"], st["ideal"]
        index = st["index"][st["keep"]]
        uv, cov = edges.xy[index], edges.cov[index]
        blur = float(np.median(edges.width[index]))
        # Edge normals point dark to bright: their component along the
        # fit's normal (outward for arcs) tells each point's polarity.
        if kind == "arc":
            _, n_out, _ = ellipse_geometry(ideal.xy, fit.params, fit.phases)
        else:
            n_out = fit.normal[None, :]
        along = np.einsum("ni,ni->n", n_out, ideal.normal)
        polarity = (1 if along.mean() > 0 else -1) if kind == "arc" else 0
        # Polarity per piece (the mean over its points), so that a stray
        # point does not make a feature mixed.
        piece = st["piece"][st["keep"]]
        sums = np.bincount(piece, along, minlength=len(st["seg_ids"]))
        signs = np.sign(sums[np.bincount(piece, minlength=len(st["seg_ids"])) > 0])
        mixed = bool(signs.min() != signs.max())
        out.append(ImageFeature(kind, tuple(int(i) for i in st["seg_ids"]), index, uv, cov, ideal, fit, blur,
                                polarity, mixed))
    return out


def _with_covariance(f, corr_length):
    """Feature f (of :func:`_make_features`) with its fit's covariance."""
    if f.fit.cov is not None:
        return f
    complete = line_with_covariance if f.kind == "line" else ellipse_with_covariance
    return replace(f, fit=complete(f.fit, f.ideal.xy, corr_length))


def _rms(f):
    return float(np.sqrt(np.mean(f.fit.residuals ** 2)))


def _kept(part, union):
    """Fraction of the points of feature ``part`` that feature ``union`` keeps
    (the rest are among its rejected outliers)."""
    return np.count_nonzero(np.isin(part.index, union.index)) / max(len(part.index), 1)


def _mergeable(a, b, max_angle, max_offset, max_axis_ratio, limit=np.inf):
    """Cheap geometric pre-test before the union is refitted.

    Lines: nearly parallel, each piece's centroid near the other's line.
    Arcs: the two ellipses agree within the fixed tolerances, or, the
    pieces' own ellipses aside, the direct (algebraic) ellipse fit of the
    union leaves residuals whose RMS is within ``MERGE_SCREEN`` times
    ``limit``, the RMS the refitted union must reach to be accepted.

    The second is needed because a short piece of a rim fixes its own
    ellipse poorly, and worse than its first-order uncertainty says: its
    cost is flat along a curved valley (a rim piece of 60 points had its
    centre 17 px off at a stated 3 px), so comparing the pieces' ellipses
    refuses pieces of one rim; the points themselves tell. The geometric
    fit improves on the direct one by far less than ``MERGE_SCREEN`` in
    RMS for points of one ellipse (the direct fit is biased, not far off)
    and for points of two (both leave the misfit between them), so a union
    failing the screen would fail its test too.

    Arcs of opposite polarity are tried: a hole's rim is brighter outside
    along one stretch and darker along another, against its inner wall lit
    on one side and in shadow on the other (see
    ``ImageFeature.mixed_polarity``); two different rims are told apart by
    the refit of their union, whose residuals then show the two. Lines of
    opposite polarity are not: two pieces of one straight edge along which
    the faces exchange brightness and two different edges that happen to
    be collinear in this image (common in a view at grazing incidence) are
    alike in one image, both one line within the noise (on the grazing
    render of the sample plate in tests/test_degenerate.py two such edges,
    12 px apart, gave a union with chi-square p = 0.52; merged, neither
    matched, and the registration became ambiguous).
    """
    if a.kind != b.kind:
        return False
    if a.kind == "line":
        na, nb = a.fit.normal, b.fit.normal
        if na @ nb < np.cos(max_angle) and -(na @ nb) < np.cos(max_angle):
            return False
        if np.mean(np.einsum("ni,i->n", a.ideal.normal, na)) * np.mean(np.einsum("ni,i->n", b.ideal.normal, na)) < 0:
            return False  # opposite polarity (see above)
        da = abs(b.fit.centroid @ na + a.fit.params[2])
        db = abs(a.fit.centroid @ nb + b.fit.params[2])
        return max(da, db) < max_offset
    pa, pb = a.fit.params, b.fit.params
    if (np.hypot(*(pa[:2] - pb[:2])) <= max(max_offset, 0.05 * max(pa[2], pb[2]))
            and abs(np.log(pa[2] / pb[2])) < max_axis_ratio
            and abs(np.log(pa[3] / pb[3])) < 2 * max_axis_ratio):
        return True
    xy = np.concatenate([a.ideal.xy, b.ideal.xy])
    try:
        direct = direct_residuals(xy)
    except (ValueError, np.linalg.LinAlgError, cv2.error):
        return False
    if direct is None or direct[0][2] > axis_bound(xy):
        return False
    r = direct[2]
    return bool(np.sqrt(np.mean(r * r)) <= MERGE_SCREEN * limit)


MERGE_SCREEN = 3.0
"""Arcs whose ellipses disagree are still tried as one edge when the direct
ellipse fit of their union has an RMS residual within this factor of the
RMS the union must reach (see :func:`_mergeable`); the same factor (9 in
mean square) as the segmentation's screen of its trial fits."""


def image_features(edges, segments, K, D, *, merge=True, min_fit_points=6, max_angle=np.deg2rad(3.0),
                   max_offset=3.0, max_axis_ratio=0.1, merge_ratio=1.3, max_misfit=0.15):
    """Image features of one image: its segments, merged where they are one edge.

    Parameters
    ----------
    edges : EdgePoints
        The image's edge points (distorted pixels).
    segments : list of Segment
        From :func:`partinspect.vision.contours.segment_contours`.
    K, D : the camera's matrix and distortion vector.
    merge : bool
        Merge collinear lines and co-elliptic arcs (many-to-one).
    min_fit_points : int
        Segments with fewer fitted points are skipped.
    max_angle : float
        Lines: largest angle between two pieces of one edge, rad.
    max_offset : float
        Lines: largest distance of one piece's centroid from the other's
        line, px; arcs: of the two centres (or 5 % of the major axis).
    max_axis_ratio : float
        Arcs: largest ``|log(a1 / a2)|`` (twice that for the minor axes).
        Arcs whose ellipses disagree beyond these are still tried when the
        direct fit of their points passes a screen (see :func:`_mergeable`).
    merge_ratio, max_misfit : float
        The union is accepted when the RMS of its residuals is at most
        ``merge_ratio`` times the worse piece's, or, for arcs, at most
        ``max_misfit`` px: two different edges leave a misfit far larger
        than the noise, while the pieces of one small ellipse may show a
        few hundredths of a pixel of systematic misfit that a ratio test
        alone would refuse. Lines get the ratio test only: two straight
        edges meeting at a shallow angle differ by a few hundredths of a
        pixel over a long stretch, which passed ``max_misfit`` and bent
        the merged line out of straightness by 30 um. The union must also
        keep more than half of each part's points (see the notes in the
        code); an arc it mostly rejects is dropped as an outlier stretch.
        Arcs of opposite polarity are merged (``ImageFeature.mixed_polarity``),
        lines not (see :func:`_mergeable`).

    Returns
    -------
    list of ImageFeature
        In the order of their first segment.
    """
    made = {}
    used = [i for i, s in enumerate(segments) if len(s.fit_index) >= min_fit_points]
    seg_ideal = _segment_ideal(segments, edges, K, D, used)

    def make_all(requests):
        # A feature is fixed by its kind and segments: each is made once,
        # those not made yet together (their ellipse fits batched).
        todo = list(dict.fromkeys((kind, tuple(ids)) for kind, ids in requests if (kind, tuple(ids)) not in made))
        for key, f in zip(todo, _make_features([(kind, list(ids)) for kind, ids in todo], segments, edges,
                                               seg_ideal)):
            made[key] = f
        return [made[(kind, tuple(ids))] for kind, ids in requests]

    feats = make_all([(segments[i].kind, [i]) for i in used])
    if not merge:
        return [_with_covariance(f, edges.sigma) for f in feats]
    tried = {}

    rms = {}

    def feature_rms(f):
        key = (f.kind, f.segments)
        if key not in rms:
            rms[key] = _rms(f)
        return rms[key]

    def pair_key(a, b):
        return (a.kind, a.segments, b.segments)

    def try_pairs(pairs):
        # A pair's test and union need computing once, not in every round;
        # the unions of one round are made together.
        new = [(a, b) for a, b in pairs if pair_key(a, b) not in tried]
        union = []
        limits = {}
        for a, b in new:
            if a.kind != b.kind:
                tried[pair_key(a, b)] = None
                continue
            limit = merge_ratio * max(feature_rms(a), feature_rms(b))
            limit = max(limit, max_misfit) if a.kind == "arc" else limit
            if _mergeable(a, b, max_angle, max_offset, max_axis_ratio, limit):
                union.append((a, b))
                limits[pair_key(a, b)] = limit
            else:
                tried[pair_key(a, b)] = None
        for (a, b), u in zip(union, make_all([(a.kind, a.segments + b.segments) for a, b in union])):
            tried[pair_key(a, b)] = (feature_rms(u), limits[pair_key(a, b)], u, _kept(a, u), _kept(b, u))

    # The union's RMS is pooled: a short stretch of another edge, or a
    # displaced stretch of this one (a rim beside a second edge closer than
    # the filter resolves), barely raises it, and the outlier rejection hides
    # it further by dropping its points. A union is taken only if it keeps
    # more than half of the points of each part. An arc most of whose points
    # the union rejects, while the union fits the other part within the
    # limit, is an outlier stretch of that rim: it is dropped, as its points
    # would have been had the two been found as one piece. (On the sample
    # renders, pieces of one edge lose at most a fifth of their points to
    # the union, displaced stretches half or more. Lines are only not
    # merged: a short edge parallel to a long one and within the merge
    # offset may be an edge of its own, a chamfer's.)
    changed = True
    while changed:
        changed = False
        best = None
        outlier = None
        try_pairs([(feats[i], feats[j]) for i in range(len(feats)) for j in range(i + 1, len(feats))])
        for i in range(len(feats)):
            for j in range(i + 1, len(feats)):
                trial = tried[pair_key(feats[i], feats[j])]
                if trial is None:
                    continue
                ratio, limit, u, kept_i, kept_j = trial
                if ratio > limit:
                    continue
                if kept_i > 0.5 and kept_j > 0.5:
                    if best is None or ratio < best[0]:
                        best = (ratio, i, j, u)
                elif outlier is None and u.kind == "arc" and (kept_i > 0.5 or kept_j > 0.5):
                    outlier = j if kept_i > 0.5 else i
        if best is not None:
            _, i, j, u = best
            feats = [f for k, f in enumerate(feats) if k not in (i, j)] + [u]
            feats.sort(key=lambda f: f.segments[0])
            changed = True
        elif outlier is not None:
            feats = [f for k, f in enumerate(feats) if k != outlier]
            changed = True
    return [_with_covariance(f, edges.sigma) for f in feats]


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


def _line_angles(geo, feats, side):
    """Angle (rad, in [0, pi/2]) between each line and the epipolar lines; NaN for arcs."""
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
        From :func:`image_features` of each image.
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
        seen by each view (a 10 % disagreement costs 1), for exactly
        determined ellipses; widened by what the two fits leave uncertain
        (:data:`RADIUS_COVERAGE`, :func:`_radius_scale`).
    angle_tolerance : float
        Lines: scale of the difference of the signed angles to the epipolar
        lines in the cost, rad.
    max_cost : float
        Pairs costing more are rejected.
    ambiguity_margin : float
        A match whose best alternative assignment costs less than this more
        is "ambiguous" and not kept.
    depth_range : (float, float), optional
        Plausible depths of the scene, mm; default only "in front of both
        cameras".

    Returns
    -------
    Matching

    Notes
    -----
    A degenerate or edge-on feature takes part in no pair. A feature left
    unmatched whose band holds such a feature of its kind and polarity (the
    partner it would have had) is given the same reason, naming it.

    A match whose best alternative is within ``ambiguity_margin`` is kept
    only when the alternative breaks the ordering constraint more often
    (matched lines keep their order along the epipolar lines).

    The cost of a candidate pair is ``(1 - IoU of the bands) + shape cost``;
    polarity disagreement (unless either feature is of mixed polarity), a
    kind mismatch or a triangulated point outside
    the depth range exclude the pair. The assignment is solved with dummy
    rows and columns of cost ``max_cost / 2`` so that leaving both features
    unmatched is preferred to any pair costing more than ``max_cost``.
    """
    nl, nr = len(left), len(right)
    zmin, zmax = depth_range if depth_range is not None else (0.0, np.inf)
    band_l, band_r = _bands(geo, left, "left"), _bands(geo, right, "right")
    ang_l, ang_r = _line_angles(geo, left, "left"), _line_angles(geo, right, "right")
    ratio_l, ratio_r = _axis_ratios(left), _axis_ratios(right)
    long_l = np.array([len(f) >= min_points for f in left], bool)
    long_r = np.array([len(f) >= min_points for f in right], bool)
    # Degenerate (None: usable) or ("degenerate" | "edge_on", detail) per feature.
    unfit_l = [_unfit(ang_l[k], ratio_l[k], min_angle, min_axis_ratio) for k in range(nl)]
    unfit_r = [_unfit(ang_r[k], ratio_r[k], min_angle, min_axis_ratio) for k in range(nr)]
    usable_l = long_l & np.array([u is None for u in unfit_l], bool)
    usable_r = long_r & np.array([u is None for u in unfit_r], bool)
    pol_l = [f.polarity if f.kind == "arc" else _line_polarity(geo, f, "left") for f in left]
    pol_r = [f.polarity if f.kind == "arc" else _line_polarity(geo, f, "right") for f in right]
    sang_l = [_signed_line_angle(geo, f, "left") if f.kind == "line" else 0.0 for f in left]
    sang_r = [_signed_line_angle(geo, f, "right") if f.kind == "line" else 0.0 for f in right]

    cost = np.full((nl, nr), np.inf)
    iou = np.zeros((nl, nr))
    shape = np.full((nl, nr), np.inf)
    in_band = np.zeros((nl, nr), bool)
    same_kind_in_band = np.zeros((nl, nr), bool)
    blocked = np.zeros((nl, nr), bool)  # would-be partners, one of them degenerate or edge-on
    for i in np.flatnonzero(long_l):
        lo_i, hi_i = band_l[i, 0] - band_tolerance, band_l[i, 1] + band_tolerance
        for j in np.flatnonzero(long_r):
            lo_j, hi_j = band_r[j, 0] - band_tolerance, band_r[j, 1] + band_tolerance
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
            same_kind_in_band[i, j] = True
            if pol_l[i] != pol_r[j] and not (fl.mixed_polarity or fr.mixed_polarity):
                continue
            if not (usable_l[i] and usable_r[j]):
                blocked[i, j] = True
                continue
            if fl.kind == "arc":
                _, (rl, rr), (zl, zr) = arc_circle(geo, fl, fr)
                if not (zmin < zl < zmax and zmin < zr < zmax) or rl <= 0 or rr <= 0:
                    continue
                s = abs(np.log(rl / rr)) / _radius_scale(fl, fr, radius_tolerance)
            else:
                zl, zr = _line_middle_depth(geo, fl, fr, max(lo_i, lo_j), min(hi_i, hi_j))
                if not (zmin < zl < zmax and zmin < zr < zmax):
                    continue
                # Line angles are defined modulo pi.
                s = abs((sang_l[i] - sang_r[j] + 0.5 * np.pi) % np.pi - 0.5 * np.pi) / angle_tolerance
            shape[i, j] = s
            c = (1.0 - iou[i, j]) + s
            if c <= max_cost:
                cost[i, j] = c

    pairs, total = _assign(cost, max_cost)
    matches, taken_l, taken_r, ambiguous = [], set(), set(), {}
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
        matches.append(Match(int(i), int(j), float(cost[i, j]), float(iou[i, j]), float(shape[i, j]), float(margin)))
        taken_l.add(i)
        taken_r.add(j)

    unmatched = []
    for side, other, feats, unfit, unfit_other, angles, taken, band_mask in (
        ("left", "right", left, unfit_l, unfit_r, ang_l, taken_l, (in_band, same_kind_in_band, cost, blocked)),
        ("right", "left", right, unfit_r, unfit_l, ang_r, taken_r, (in_band.T, same_kind_in_band.T, cost.T, blocked.T)),
    ):
        inb, same, cst, blk = band_mask
        for k, f in enumerate(feats):
            if k in taken:
                continue
            ang = float(angles[k])
            partners = [o for o in np.flatnonzero(blk[k]) if unfit_other[o] is not None]
            if len(f) < min_points:
                unmatched.append(Unmatched(side, k, "too_short", f"{len(f)} points < {min_points}", ang))
            elif unfit[k] is not None:
                unmatched.append(Unmatched(side, k, unfit[k][0], unfit[k][1], ang))
            elif partners and not np.isfinite(cst[k]).any():
                o = partners[0]
                unmatched.append(Unmatched(side, k, unfit_other[o][0],
                                           f"its counterpart in the {other} image (feature {int(o)}): "
                                           + unfit_other[o][1], ang))
            elif (side, k) in ambiguous:
                unmatched.append(Unmatched(side, k, "ambiguous", ambiguous[(side, k)], ang))
            elif not inb[k].any():
                unmatched.append(Unmatched(side, k, "no_candidate", "", ang))
            elif not same[k].any():
                unmatched.append(Unmatched(side, k, "kind_mismatch",
                                           f"{f.kind} with only other kinds in its band", ang))
            elif not np.isfinite(cst[k]).any():
                unmatched.append(Unmatched(side, k, "shape_mismatch", "", ang))
            else:
                others = np.flatnonzero(np.isfinite(cst[k]))
                unmatched.append(Unmatched(side, k, "outcompeted",
                                           "candidates " + ", ".join(str(int(o)) for o in others), ang))
    return Matching(tuple(matches), tuple(unmatched), cost, ang_l, ang_r)


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
