"""Predicted uncertainty of every characteristic for the part in a given pose.

Nothing is rendered and nothing is measured: the CAD edges are projected
into both cameras at the pose and turned into the edge points the detector
would give (one per pixel of the dominant axis, where the edge is in the
image, unoccluded and shows contrast, with the uncertainty the detector
states and its scatter, :func:`~partinspect.planning.edge_model.stated_std_pattern`).
Those points, lying exactly on the true edges, go through the measurement
chain's own code from the 2D fits on: ideal points and 2D fits, stereo
correspondences, the two-view 3D fits (rims with the chain's Type B
uncertainty for the shading beside them, :func:`background_terms`; the
calibration's uncertainty when it states one), the registration with the
true pose as hint, and :func:`partinspect.tolerances.evaluate.evaluate`.

Every step is first-order propagation at the true geometry, so the result
is the u ``inspect`` would report for an exactly nominal part in that pose,
*if the chain keeps every visible edge point* (where its segmentation drops
part of a rim, it reports more). What cannot be measured is said with the
reason: not visible in both images, a line within ``EPIPOLAR_MIN_ANGLE`` of
the epipolar lines (depth undetermined), a circle within ``90 -
EDGE_ON_ANGLE`` degrees of edge-on, arcs too short for the matcher to tell
their radius (:func:`radius_untold`).

Frames: part frame (STEP) for CAD geometry, rig frame (left camera) for
measured features; mm, radians inside.

References
----------
.. [1] JCGM 100:2008 (GUM), 5.1 (law of propagation of uncertainty), 6.2
       (expanded uncertainty, k = 2).
.. [2] Hartley, R., & Zisserman, A. (2004). Multiple View Geometry in
       Computer Vision, 2nd ed., 5.2 (covariance by back-propagation).
.. [3] ISO 14253-1:2017: with the conformance zone shrunk by U at both
       limits, a characteristic can only be decided when U is small against
       its tolerance; U <= T / 4 is the customary 4:1 rule of thumb
       (the ``--ratio`` sets another).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np

from partinspect.planning.edge_model import (
    DetectorModel, detector_parameters, near_image, profile_width, stated_std_pattern)
from partinspect.vision.matching import (
    MIN_EPIPOLAR_ANGLE, RADIUS_COVERAGE, RADIUS_WIDENING_MAX, match_features)

__all__ = [
    "EPIPOLAR_MIN_ANGLE",
    "EDGE_ON_ANGLE",
    "DEFAULT_RATIO",
    "ViewSamples",
    "FeaturePrediction",
    "CharacteristicPrediction",
    "PosePrediction",
    "tolerance_width",
    "sample_view",
    "background_terms",
    "predict_feature",
    "radius_untold",
    "crowded",
    "predict_pose",
    "tied_registration",
]

EPIPOLAR_MIN_ANGLE = MIN_EPIPOLAR_ANGLE
"""A line closer than this to the epipolar lines is not matched
(:func:`partinspect.vision.matching.match_features`' ``min_angle``, the
same object, so that plan and chain cannot drift apart)."""
EDGE_ON_ANGLE = np.deg2rad(80.0)
"""A circle seen more than this off its axis is taken as edge-on: its image
is an ellipse of axis ratio below cos 80 = 0.17, which the segmentation
does not keep as one ellipse."""
OBLIQUE_ANGLE = np.deg2rad(60.0)
"""Beyond this a circle's view is named as a cause of a large uncertainty."""
NARROW_EPIPOLAR_ANGLE = np.deg2rad(20.0)
"""Below this a line's angle to the epipolar lines is named as a cause."""
LOW_CONTRAST = 40.0
"""Grey levels; a median contrast below this is named as a cause."""
FLAT_ELLIPSE = 0.5
"""A circle whose image is an ellipse flatter than this (minor / major axis)
is measurable in principle, but the chain's segmentation often breaks such
an ellipse into pieces too short to match, which the first-order
prediction cannot show: such characteristics carry a warning."""
DEFAULT_RATIO = 0.25
"""A characteristic is decidable when U <= ratio x its tolerance."""
_RADIUS_TOLERANCE = match_features.__kwdefaults__["radius_tolerance"]  # the matcher's, so the two cannot drift
_CONTRAST_OFFSET = 1.5  # px either side of the edge where the faces' greys are read (as truth.py)
_DENSE_PER_PX = 4  # dense samples per pixel of image length before placing the detector's points


# ---------------------------------------------------------------------------
# records


@dataclass(frozen=True, eq=False)
class ViewSamples:
    """The predicted edge points of one feature in one image.

    Attributes
    ----------
    uv : ndarray, shape (N, 2)
        Distorted pixel positions (on the true edge's image), in order along it.
    normal : ndarray, shape (N, 2)
        Unit normals of the projected edge.
    contrast : ndarray, shape (N,)
        Grey-level step across the edge.
    std : ndarray, shape (N,)
        Standard uncertainty of each point across the edge, px.
    n_sampled : int
        Detector points the whole edge would give if fully visible.
    fractions : dict
        ``in_image``, ``unoccluded``, ``contrast`` and ``visible`` fractions
        of those points (as :func:`partinspect.cad.sightlines.edge_visibility`),
        and ``step``: the median noiseless grey step across the edge where
        it is in the image and unoccluded, grey levels.
    background_bound, background_std : ndarray, shape (N,) or None
        Curved edges: what :func:`partinspect.vision.edges.background_gradients`
        would report for the shading beside each point (``W^2 |g_b - g_d| / h``,
        px) and the noise of the first-order background shift, px (see
        :func:`background_terms`),
        both averaged along the edge as the chain averages them
        (:func:`partinspect.vision.rim_errors.smoothed_background`); None for lines.
    """

    uv: np.ndarray
    normal: np.ndarray
    contrast: np.ndarray
    std: np.ndarray
    n_sampled: int
    fractions: dict
    background_bound: np.ndarray | None = None
    background_std: np.ndarray | None = None

    def __len__(self):
        return len(self.uv)


@dataclass(frozen=True, eq=False)
class FeaturePrediction:
    """What the chain would make of one CAD feature in this pose.

    Attributes
    ----------
    id, kind : str
    status : str
        "measured", or why not: "hidden", "degenerate" (a line along the
        epipolar lines), "edge-on" (a circle), "unmatched" (arcs too short
        to tell their radius, :func:`radius_untold`), "faint" (a median step
        under the run's threshold, :func:`_least_step`), "failed".
    reason : str or None
        In words, naming the feature.
    record : partinspect.vision.feature3d.Feature3D or None
        The predicted measured feature (rig frame) with its covariances.
    left, right : ViewSamples or None
    epipolar_angle : float or None
        Lines: smallest angle between the line's image and the epipolar
        lines over both images, rad.
    view_angle : float or None
        Circles and arcs: largest angle between the circle's axis and the
        line of sight to its centre over both cameras, rad.
    axis_ratio : float or None
        Circles and arcs: smallest minor / major axis ratio of the
        predicted image ellipses.
    """

    id: str
    kind: str
    status: str
    reason: str | None = None
    record: object = None
    left: ViewSamples | None = None
    right: ViewSamples | None = None
    epipolar_angle: float | None = None
    view_angle: float | None = None
    axis_ratio: float | None = None

    @property
    def measured(self):
        return self.status == "measured"

    @property
    def visible_fraction(self):
        if self.left is None or self.right is None:
            return 0.0
        return min(self.left.fractions["visible"], self.right.fractions["visible"])

    @property
    def median_contrast(self):
        vals = [np.median(v.contrast) for v in (self.left, self.right) if v is not None and len(v)]
        return float(min(vals)) if vals else float("nan")


@dataclass(frozen=True, eq=False)
class CharacteristicPrediction:
    """Predicted uncertainty of one characteristic.

    Attributes
    ----------
    characteristic : Characteristic
    u, U : float
        Standard and expanded (k = 2) uncertainty, the characteristic's
        unit; ``inf`` when it cannot be measured in this pose.
    tolerance : float or None
        Width of the specification zone (upper - lower limit, or the
        zone of a geometrical tolerance); None without limits.
    ratio : float
        ``U / tolerance`` (inf when not measurable, nan without a tolerance).
    decidable : bool
        ``U <= max_ratio * tolerance``.
    reason : str or None
        Why not decidable, naming the feature and the cause.
    method : str
        How ``u`` was evaluated (evaluate()'s wording).
    warning : str or None
        A risk the first-order prediction does not carry (a flat ellipse
        the segmentation may break up).
    inspected : bool
        False for a general-tolerance characteristic whose edges are all out
        of view in this pose: ``inspect`` lists those as not inspected
        rather than judging them, so they do not count against a pose.
    """

    characteristic: object
    u: float
    U: float
    tolerance: float | None
    ratio: float
    decidable: bool
    reason: str | None = None
    method: str = ""
    inspected: bool = True
    warning: str | None = None

    @property
    def id(self):
        return self.characteristic.id

    def to_dict(self):
        c = self.characteristic
        conv = math.degrees if c.unit == "rad" else float

        def num(x):
            return None if x is None or not math.isfinite(x) else round(conv(x), 9)

        return {
            "id": c.id,
            "type": c.type,
            "features": list(c.features),
            "unit": "deg" if c.unit == "rad" else c.unit,
            "tolerance": num(self.tolerance),
            "standard_uncertainty": num(self.u),
            "expanded_uncertainty": num(self.U),
            "ratio": None if not math.isfinite(self.ratio) else round(self.ratio, 6),
            "decidable": bool(self.decidable),
            "inspected": bool(self.inspected),
            "reason": self.reason,
            "warning": self.warning,
        }


@dataclass(frozen=True, eq=False)
class PosePrediction:
    """Everything predicted for one pose.

    Attributes
    ----------
    part_to_camera : ndarray, shape (4, 4)
    features : dict of str to FeaturePrediction
    characteristics : list of CharacteristicPrediction
        In the order given.
    registration : Registration or None
    registration_error : str or None
    max_ratio : float
    label : str
    angles : tuple
    ambiguity : str
        Where poses tie (:func:`tied_registration`): the tie in words, as
        ``inspect`` would state it; "" when the pose is not ambiguous.
    """

    part_to_camera: np.ndarray
    features: dict
    characteristics: list
    registration: object = None
    registration_error: str | None = None
    max_ratio: float = DEFAULT_RATIO
    label: str = ""
    angles: tuple = field(default=())
    ambiguity: str = ""

    @property
    def n_decidable(self):
        return sum(c.decidable for c in self.characteristics)

    @property
    def all_decidable(self):
        """Every inspected characteristic decidable (see ``CharacteristicPrediction.inspected``)."""
        return all(c.decidable or not c.inspected for c in self.characteristics)

    def undecidable(self):
        """The inspected characteristics that are not decidable."""
        return [c for c in self.characteristics if c.inspected and not c.decidable]

    def not_inspected(self):
        return [c for c in self.characteristics if not c.inspected]

    @property
    def n_measurable(self):
        return sum(math.isfinite(c.U) for c in self.characteristics)

    def score(self):
        """Sort key, larger is better.

        The count of decidable characteristics, then of measurable ones (a
        characteristic measured too coarsely is closer to decidable than one
        not measured at all), then the worst ratio ``U / tolerance`` when all
        are decidable, then the summed log ratio of the measurable ones.
        """
        r = np.array([c.ratio for c in self.characteristics if math.isfinite(c.ratio)] or [1.0])
        worst = max((c.ratio for c in self.characteristics if math.isfinite(c.ratio)), default=0.0)
        return (self.n_decidable, self.n_measurable, -worst if self.all_decidable else 0.0,
                -float(np.log(np.maximum(r, 1e-9)).sum()))


# ---------------------------------------------------------------------------
# sampling one camera


def _edge_function(kind, geometry):
    """(t0, t1, X(t), T(t)) of an edge: points and unit tangents, part frame."""
    from partinspect.frames import reference_direction

    if kind == "line":
        a, b = np.asarray(geometry["start"], float), np.asarray(geometry["end"], float)
        L = float(np.linalg.norm(b - a))
        d = (b - a) / L
        return 0.0, L, (lambda t: a + t[:, None] * d), (lambda t: np.repeat(d[None], len(t), 0))
    c, n, r = np.asarray(geometry["center"], float), np.asarray(geometry["normal"], float), float(geometry["radius"])
    x = reference_direction(n)
    y = np.cross(n, x)
    t0, t1 = (0.0, 2 * np.pi) if kind == "circle" else (float(geometry["angle_start"]), float(geometry["angle_end"]))

    def X(t):
        return c + r * (np.cos(t)[:, None] * x + np.sin(t)[:, None] * y)

    def T(t):
        return -np.sin(t)[:, None] * x + np.cos(t)[:, None] * y

    return t0, t1, X, T


def _trim_runs(mask, uv, trim, closed, breaks=None):
    """Drop points within ``trim`` px (along the image curve) of the ends of each visible run.

    ``breaks`` (bool (N,), optional): ``breaks[i]`` ends a run between
    points i and i + 1 (for a closed edge, ``breaks[N - 1]`` between the
    last point and the first).
    """
    n = len(mask)
    if trim <= 0 or n == 0 or not mask.any():
        return mask
    b = np.zeros(n, bool) if breaks is None else np.asarray(breaks, bool)
    if closed and mask.all() and not b.any():
        return mask
    order = np.arange(n)
    if closed:
        # Start the sequence after a gap or a break so no run wraps around.
        order = np.roll(order, -(int(np.flatnonzero(~mask | b)[0]) + 1))
    m, b = mask[order], b[order]
    step = np.linalg.norm(np.diff(uv[order], axis=0), axis=1)
    s = np.r_[0.0, np.cumsum(np.where(np.isfinite(step), step, 0.0))]  # points off the image have no uv
    starts = np.flatnonzero(m & np.r_[True, ~m[:-1] | b[:-1]])
    ends = np.flatnonzero(m & np.r_[~m[1:] | b[:-1], True])
    keep = m.copy()
    for i0, i1 in zip(starts, ends):
        run = slice(i0, i1 + 1)
        keep[run] &= (s[run] - s[i0] >= trim) & (s[i1] - s[run] >= trim)
    out = np.zeros(n, bool)
    out[order] = keep
    return out


JUNCTION_STEP_FRACTION = 1.0 / 3.0
"""A third edge meeting an edge parts the 2D chain's contour there when its
grey step is at least this fraction of the edge's contrast (the larger of
the two either side of the junction). The chain's edges show a clear
divide: junctions stepping by well over a third of the contrast leave a
gap, those well under it none."""


def _junctions(vis, every, closed):
    """Where a third edge meets the edge between two visible samples.

    The face seen on one side (:func:`partinspect.cad.sightlines.edge_visibility`'s
    ``side_label``) changes from one sample to the next, with a grey step of at
    least ``JUNCTION_STEP_FRACTION`` of the edge's contrast: as where a hole's
    bottom rim, seen through the hole, ends at its top rim. The truth's
    visibility rule misses such a junction where the third edge leaves steeply
    (it crosses the span read beside the edge between two samples), yet the
    chain's contour parts there and the segmentation trims both new ends, so
    the prediction must too.

    Parameters
    ----------
    vis : dict
        :func:`~partinspect.cad.sightlines.edge_visibility` of the samples, in
        order along the edge.
    every : ndarray of bool, shape (N,)
        Visible samples.
    closed : bool
        A whole circle: the last sample neighbours the first.

    Returns
    -------
    ndarray of bool, shape (N,)
        ``[i]``: a junction between samples i and i + 1.
    """
    lab, g = vis["side_label"], vis["side_grey"]
    nxt = np.roll(np.arange(len(every)), -1)
    contrast = np.abs(g[:, 1] - g[:, 0])
    step = np.abs(g - g[nxt])
    changed = (lab != lab[nxt]) & (step >= JUNCTION_STEP_FRACTION * np.maximum(contrast, contrast[nxt])[:, None])
    out = every & every[nxt] & changed.any(axis=1)
    if not closed and len(out):
        out[-1] = False
    return out


def crowded(scene, camera, part_to_camera, uv, normal, side_label, side_grey, reach, shading):
    """Edge samples with another edge's image within ``reach`` px of them.

    The chain's Gaussian smoothing mixes two edges closer than a few edge
    widths and displaces both, so it leaves such points out
    (:func:`partinspect.vision.contours._make_segments` at a line's ends,
    :func:`partinspect.vision.guided.clear_arcs` anywhere on a rim), by
    their distance in the image to another edge's points. Here the other
    edge is found by casting rays on rings around each sample, from the
    span the visibility rule reads (``CONTRAST_OFFSET`` px) out to
    ``reach``, at most ``_RING_STEP`` px apart: a face other than the
    edge's two, whose grey differs from that of the edge's face on the
    same side by at least ``NEIGHBOUR_STEP_FRACTION`` of the edge's own
    step, is another edge's side (a face boundary shaded alike shows no
    edge: a silhouette turning a corner is one grey step; a thin wall
    between a counterbore's floor and the top face, both lit alike, is
    two). A corner is found so as well as a parallel neighbour: the third
    face's wedge begins within ``reach``.

    Parameters
    ----------
    scene : RaycastScene
    camera : tuple
        ``(K, D, R, t)`` of :func:`partinspect.cad.raycast.camera_in_part`.
    part_to_camera : ndarray, shape (4, 4)
    uv, normal : ndarray, shape (N, 2)
        Distorted px and unit normals of the projected edge.
    side_label : ndarray of int, shape (N, 2)
    side_grey : ndarray, shape (N, 2)
        The face seen and its grey against and along the normal
        (:func:`partinspect.cad.sightlines.edge_visibility`).
    reach : float
        px.
    shading : Shading

    Returns
    -------
    ndarray of bool, shape (N,)

    References
    ----------
    .. [1] Canny, J. (1986). A computational approach to edge detection.
       IEEE TPAMI 8(6), 679-698 (the interaction of nearby edges under the
       smoothing filter).
    """
    from partinspect.cad.raycast import cast, pixel_rays, shade
    from partinspect.cad.sightlines import CONTRAST_OFFSET, NEIGHBOUR_STEP_FRACTION

    n = len(uv)
    if n == 0 or reach <= CONTRAST_OFFSET:
        return np.zeros(n, bool)
    radii = np.linspace(CONTRAST_OFFSET, reach, int(np.ceil((reach - CONTRAST_OFFSET) / _RING_STEP)) + 1)
    a = np.arange(_RING_RAYS) * 2 * np.pi / _RING_RAYS
    ring = (radii[:, None, None] * np.stack([np.cos(a), np.sin(a)], axis=-1)[None]).reshape(-1, 2)
    o, d = pixel_rays((uv[:, None, :] + ring[None]).reshape(-1, 2), *camera)
    light = np.asarray(part_to_camera, float)[:3, :3].T @ shading.direction()
    hits = cast(scene, o, d)
    g = shade(scene, hits, d, light, shading).astype(float).reshape(n, len(ring))
    lab = hits.label.reshape(n, len(ring))
    quiet = NEIGHBOUR_STEP_FRACTION * np.abs(side_grey[:, 1] - side_grey[:, 0])
    own = (lab == side_label[:, :1]) | (lab == side_label[:, 1:])
    # The side of the edge each ray lies on (along its normal or against it) and that side's grey.
    along = np.einsum("nd,rd->nr", normal, ring) > 0
    expected = np.where(along, side_grey[:, 1:], side_grey[:, :1])
    alike = np.abs(g - expected) < quiet[:, None]
    return (~own & ~alike).any(axis=1)


_RING_STEP = 1.5  # px between the rings crowded() casts (a neighbouring face narrower than this may slip through)
_RING_RAYS = 16  # rays per ring: 2.9 px apart on a 7.5 px ring


def _clear_of_others(scene, camera, part_to_camera, vis, keep, kind, model, shading):
    """``keep`` less the points the chain leaves out beside another edge (:func:`crowded`).

    A line loses the crowded points that run up to an end of each of its
    stretches (``CLEARANCE`` edge widths: at a corner or a junction), as
    the segmentation cuts it; a whole circle loses every crowded point
    within ``CLEARANCE`` edge widths beyond the span its shading is read
    over (``max(BACKGROUND_DISTANCES)`` px), as the chain clears a
    registered rim (:func:`partinspect.vision.guided.clear_arcs`), and a
    partial arc those within ``CLEARANCE`` edge widths (the chain does not
    count the edges meeting an arc at its ends, which the ray caster cannot
    tell from others: with the wider reach a slot's end, whose sides run
    tangentially into it, would lose points the chain keeps); a rim keeps its
    points where fewer than ``min_points`` would be left (the chain then
    keeps the arc as it was).
    """
    from partinspect.vision.contours import CLEARANCE, end_runs
    from partinspect.vision.edges import BACKGROUND_DISTANCES

    idx = np.flatnonzero(keep)
    if len(idx) == 0:
        return keep
    width = profile_width(model.blur, model.sigma)
    # A whole rim meets no edge at its ends: the chain clears it out to the span its shading is read
    # over and CLEARANCE widths beyond; a partial arc's neighbours at its ends are mostly the edges that
    # meet it there, which the chain does not count (a slot's sides running tangentially into its end).
    reach = CLEARANCE * width + (max(BACKGROUND_DISTANCES) if kind == "circle" else 0.0)
    bad = crowded(scene, camera, part_to_camera, vis["uv"][idx], vis["normal_uv"][idx], vis["side_label"][idx],
                  vis["side_grey"][idx], reach, shading)
    if kind == "line":
        runs = np.split(np.arange(len(idx)), np.flatnonzero(np.diff(idx) > 1) + 1)
        bad = np.concatenate([end_runs(bad[r]) for r in runs])
    elif (~bad).sum() < model.min_points:
        return keep
    out = keep.copy()
    out[idx[bad]] = False
    return out


def _segmentable(keep, closed):
    """``keep`` less its stretches too short for the segmentation to make a piece of.

    The chain's segmentation fits no piece to fewer than its
    ``min_points`` points left once a contour's ends are trimmed
    (:func:`partinspect.vision.contours.segment_contour`; the prediction's
    stretches are trimmed already): a few pixels of a rim seen between two
    occluding edges are found as edge points but belong to no image
    feature, and counted in, they would fix the arc's ellipse over an
    angle the chain does not see (docs/validation.md, ftc_10's view-3).

    Parameters
    ----------
    keep : ndarray of bool, shape (N,)
        Predicted points, in order along the edge.
    closed : bool
        A whole circle: a stretch may run on from the last sample to the first.
    """
    from partinspect.vision.contours import segment_contour

    least = segment_contour.__kwdefaults__["min_points"]
    idx = np.flatnonzero(keep)
    if len(idx) == 0:
        return keep
    runs = np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1)
    if closed and len(runs) > 1 and keep[0] and keep[-1]:
        runs = [np.concatenate([runs[-1], runs[0]])] + runs[1:-1]
    out = keep.copy()
    for r in runs:
        if len(r) < least:
            out[r] = False
    return out


def sample_view(scene, calib, index, part_to_camera, kind, geometry, model, shading=None):
    """The edge points the detector would give for one edge in one image.

    Parameters
    ----------
    scene : partinspect.cad.raycast.RaycastScene
        The part (for occlusion and shading).
    calib : StereoCalibration
    index : int
        0 left, 1 right.
    part_to_camera : ndarray, shape (4, 4)
    kind : {"line", "circle", "arc"}
    geometry : dict
        :func:`partinspect.cad.edge_sampling.feature_geometry` of the edge.
    model : DetectorModel
    shading : Shading, optional
        Default the renderer's.

    Returns
    -------
    ViewSamples
        Only the points that would be detected: in the image, unoccluded, with
        contrast (the truth's visibility rules), minus ``model.run_trim``
        (lines) or ``model.arc_trim`` (circles, arcs) px at the ends of each
        visible stretch; a junction with a third edge (:func:`_junctions`) ends
        a stretch. Points beside another edge's image are then left out as
        the chain leaves them out (:func:`_clear_of_others`), and stretches
        too short to be a piece of the segmentation (:func:`_segmentable`).

    Notes
    -----
    Where a rim's contrast fades out, the detector follows it a little further,
    down to its upper hysteresis threshold (about 10 grey levels), than the
    truth's 20 grey levels used here. Ending the stretches at the threshold
    moves one prediction closer to the chain and another further from it, so
    the truth's rule stays.
    """
    from partinspect.cad.raycast import DEFAULT_SHADING, camera_in_part, cast, pixel_rays, shade
    from partinspect.cad.sightlines import edge_visibility
    from partinspect.vision.calibration import project_points

    shading = shading or DEFAULT_SHADING
    K, D, R, t = camera_in_part(calib, index, part_to_camera)
    t0, t1, X, T = _edge_function(kind, geometry)
    coarse = np.linspace(t0, t1, 65)
    uvc = project_points(X(coarse), K, D, R, t)
    if not np.isfinite(uvc).all():
        return ViewSamples(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), np.zeros(0), 0,
                           {"in_image": 0.0, "unoccluded": 0.0, "contrast": 0.0, "visible": 0.0})
    size = calib.image_size
    # A piece of the edge thrown far off by the distortion polynomial
    # (near_image) counts at most the image's diagonal in the sampling
    # and gets no detector points: it would otherwise ask for millions.
    cap = float(np.hypot(*size)) if size is not None else np.inf
    length = float(np.minimum(np.abs(np.diff(uvc, axis=0)).max(axis=1), cap).sum())
    dense = np.linspace(t0, t1, max(int(_DENSE_PER_PX * length) + 2, 16))
    uvd = project_points(X(dense), K, D, R, t)
    tp = detector_parameters(dense, uvd, valid=near_image(uvd, size) if size is not None else None)
    if len(tp) == 0:
        return ViewSamples(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), np.zeros(0), 0,
                           {"in_image": 0.0, "unoccluded": 0.0, "contrast": 0.0, "visible": 0.0})
    P, Tg = X(tp), T(tp)
    vis = edge_visibility(scene, calib, index, part_to_camera, P, Tg, shading)
    every = vis["in_image"] & vis["unoccluded"] & vis["contrast"]
    fractions = {k: float(np.mean(vis[k])) for k in ("in_image", "unoccluded", "contrast")}
    fractions["visible"] = float(np.mean(every))
    seen = vis["in_image"] & vis["unoccluded"]
    # The run's reading of whether an edge shows: the median step over all of it in view (cad.visibility).
    fractions["step"] = float(np.median(np.abs(np.diff(vis["side_grey"][seen], axis=1)))) if seen.any() else 0.0
    keep = _trim_runs(every, vis["uv"], model.run_trim if kind == "line" else model.arc_trim, kind == "circle",
                      _junctions(vis, every, kind == "circle"))
    keep = _clear_of_others(scene, (K, D, R, t), part_to_camera, vis, keep, kind, model, shading)
    keep = _segmentable(keep, kind == "circle")
    uv, normal = vis["uv"][keep], vis["normal_uv"][keep]
    if model.contrast is not None:
        contrast = np.full(len(uv), float(model.contrast))
    elif len(uv):
        light = np.asarray(part_to_camera, float)[:3, :3].T @ shading.direction()
        q = np.concatenate([uv - _CONTRAST_OFFSET * normal, uv + _CONTRAST_OFFSET * normal])
        o, d = pixel_rays(q, K, D, R, t)
        g = shade(scene, cast(scene, o, d), d, light, shading).astype(float)
        contrast = np.abs(g[len(uv):] - g[: len(uv)])
    else:
        contrast = np.zeros(0)
    std0, pattern = stated_std_pattern(uv, normal, contrast, model)
    std = std0 * pattern
    bound = bstd = None
    if kind != "line" and len(uv):
        from partinspect.vision.rim_errors import smoothed_background

        raw_bound, raw_std = background_terms(scene, K, D, R, t, part_to_camera, uv, normal, contrast, model, shading)
        # Averaged along the edge as the chain averages its readings.
        mean, bstd = smoothed_background(uv, raw_bound[:, None], raw_std, model.sigma)
        bound = mean[:, 0]
    return ViewSamples(uv, normal, contrast, np.atleast_1d(std), len(tp), fractions, bound, bstd)


def background_terms(scene, K, D, R, t, part_to_camera, uv, normal, contrast, model, shading):
    """The shading beside an edge, as the detector's background test would read it.

    The grey-level gradient of each side's surface is taken by central
    differences (1 px apart) of the noiseless shading at 3, 3.5 and 4 px
    from the edge along its normal, and averaged, as
    :func:`partinspect.vision.edges.background_gradients` reads the filtered
    image there. Then ``bound = W^2 |g_b - g_d| / h`` and the noise of the
    first-order background shift ``W^2 sqrt(BACKGROUND_NOISE) s_g / h`` with
    ``s_g`` the gradient noise of the filter (W the profile width, h the
    contrast): the chain's Type B uncertainty of a rim point is a multiple
    of ``bound`` (:func:`partinspect.vision.stereo.feature_views`).

    Returns
    -------
    bound, std : ndarray, shape (N,)
        px.
    """
    from partinspect.cad.raycast import cast, pixel_rays, shade
    from partinspect.vision import edges as edges_mod

    light = np.asarray(part_to_camera, float)[:3, :3].T @ shading.direction()
    n = len(uv)
    steps = np.array([[0.5, 0.0], [-0.5, 0.0], [0.0, 0.5], [0.0, -0.5]])
    dist = np.asarray(edges_mod.BACKGROUND_DISTANCES)
    grads = []
    for sign in (1.0, -1.0):
        q = (uv[:, None, None, :] + sign * dist[None, :, None, None] * normal[:, None, None, :]
             + steps[None, None, :, :]).reshape(-1, 2)
        o, d = pixel_rays(q, K, D, R, t)
        g = shade(scene, cast(scene, o, d), d, light, shading).astype(float).reshape(n, len(dist), 4)
        grads.append(np.stack([g[..., 0] - g[..., 1], g[..., 2] - g[..., 3]], axis=-1).mean(axis=1))
    W = profile_width(model.blur, model.sigma)
    h = np.maximum(np.abs(contrast), 1e-9)
    bound = W * W * np.linalg.norm(grads[0] - grads[1], axis=1) / h
    s_g = edges_mod.gradient_noise_std(model.pixel_noise, model.sigma)
    std = W * W * np.sqrt(edges_mod.BACKGROUND_NOISE) * s_g / h
    return bound, std


# ---------------------------------------------------------------------------
# one feature through the chain


def _image_feature(kind, view, K, D, model):
    """An ImageFeature (as :mod:`partinspect.vision.matching` makes them) of predicted points."""
    from partinspect.vision.edges import ALONG_EDGE_VARIANCE
    from partinspect.vision.fitting import fit_ellipse, fit_line
    from partinspect.vision.ideal import ideal_points
    from partinspect.vision.imagefeatures import ImageFeature

    n, s = view.normal, view.std
    tg = np.c_[-n[:, 1], n[:, 0]]
    cov = (s * s)[:, None, None] * n[:, :, None] * n[:, None, :] + ALONG_EDGE_VARIANCE * tg[:, :, None] * tg[:, None, :]
    ideal = ideal_points(view.uv, cov, K, D, n)
    fit = (fit_line if kind == "line" else fit_ellipse)(ideal.xy, ideal.cov, corr_length=model.sigma)
    base = dict(kind=kind, segments=(0,), index=np.arange(len(view.uv)), uv=view.uv, cov_uv=cov, ideal=ideal, fit=fit,
                blur=profile_width(model.blur, model.sigma), polarity=0)
    extra = {}
    if kind == "arc" and view.background_bound is not None:
        # The points lie on the true edge: nothing to correct (offset 0), but the
        # chain's Type B uncertainty of rim points applies as it would.
        extra = dict(background_offset=np.zeros((len(view.uv), 2)), background_bound=view.background_bound,
                     background_std=view.background_std)
    from partinspect.vision import stereo

    cls = getattr(stereo, "EdgeFeature", None)
    if cls is not None and extra:
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**base, **{k: v for k, v in extra.items() if k in names})
    return ImageFeature(**base)


def _least_step(model):
    """Grey levels: the run counts an edge shown when the median step across it is at least this.

    :data:`partinspect.cad.visibility.MIN_CONTRAST_SNR` times the noise, the
    rule by which ``inspect`` says an edge in view shows too little step
    (:func:`partinspect.diagnosis.unmeasured_reason`) and re-runs for it
    (:mod:`partinspect.adaptive`). An edge between two faces lit alike that
    shows a step only where it passes in front of the background keeps a
    short stretch between two corners, of which the chain's corners take
    more than the trim the prediction allows (docs/validation.md, ftc_10's
    view-3).
    """
    from partinspect.cad.visibility import MIN_CONTRAST_SNR

    return MIN_CONTRAST_SNR * model.noise


def radius_untold(fl, fr):
    """The standard uncertainty of two arcs' radius ratio where the matcher cannot pair them on it, else None.

    The matcher pairs two arcs only when their 3D radii agree: ``|log(r_l / r_r)|``
    within ``radius_tolerance`` widened in quadrature by ``RADIUS_COVERAGE``
    standard uncertainties of the log-ratio, but never beyond
    ``RADIUS_WIDENING_MAX x radius_tolerance``
    (:func:`partinspect.vision.matching.match_features`). Where the
    expanded uncertainty ``RADIUS_COVERAGE u`` of the ratio exceeds that
    cap, a true pair is refused unless the noise happens to fall its way:
    the arc of one image is too short to fix its ellipse (a partly hidden
    rim seen over some 40 degrees; docs/validation.md, ftc_10's view-3).
    The plan then predicts no measurement. ``u`` is read as the matcher reads it, from the two
    ellipse fits' covariances of the semi-major axis (independent images,
    JCGM 100 5.1.2); a short arc's real scatter is larger still (its
    least-squares cost is flat along a curved valley), so the rule errs
    on the side of the run.

    Parameters
    ----------
    fl, fr : ImageFeature
        The predicted arcs of the left and right image (ideal pixels).

    Returns
    -------
    float or None
        ``u(log(r_l / r_r))`` (relative) where it exceeds
        ``RADIUS_WIDENING_MAX x radius_tolerance / RADIUS_COVERAGE``; None
        where the matcher can pair the arcs.
    """
    var = sum(float(f.fit.cov[2, 2]) / float(f.fit.params[2]) ** 2 for f in (fl, fr)
              if getattr(f.fit, "cov", None) is not None and f.fit.params[2] > 0)
    u = math.sqrt(var)
    return u if RADIUS_COVERAGE * u > RADIUS_WIDENING_MAX * _RADIUS_TOLERANCE else None


def _hidden_reason(fid, feature, views):
    if getattr(feature, "smooth", False):
        return f"{fid} shows no edge: its faces meet tangentially"
    worst = min(views, key=lambda nv: len(nv[1]))
    name, v = worst
    fr = v.fractions
    if v.n_sampled == 0:
        return f"{fid} is not in the {name} image"
    causes = []
    if fr["in_image"] < 0.999:
        causes.append(f"{100 * (1 - fr['in_image']):.0f} % outside the image")
    if fr["unoccluded"] < 0.999:
        causes.append(f"{100 * (1 - fr['unoccluded']):.0f} % hidden behind the part")
    if fr["contrast"] < 0.999:
        causes.append(f"{100 * (1 - fr['contrast']):.0f} % without contrast")
    detail = ", ".join(causes) or "too short"
    return f"{fid} is not visible in the {name} image ({detail}; {len(v)} edge points)"


def _epipolar_angle(geo, fl, fr):
    """Smallest angle between the images of a line and the epipolar lines, rad, and the image it occurs in."""
    out = []
    for name, f, dirs in (("left", fl, geo.directions_left), ("right", fr, geo.directions_right)):
        c = f.fit.centroid[None]
        e = dirs(c)[0]
        d = f.fit.direction
        out.append((float(np.arccos(min(1.0, abs(float(d @ e))))), name))
    return min(out)


def _view_angle(calib, part_to_camera, geometry):
    """Largest angle between a circle's axis and the line of sight to its centre, rad, and the camera."""
    P = np.asarray(part_to_camera, float)
    c = P[:3, :3] @ np.asarray(geometry["center"], float) + P[:3, 3]
    n = P[:3, :3] @ np.asarray(geometry["normal"], float)
    out = []
    for index, name in ((0, "left"), (1, "right")):
        R, T = calib.camera(index)[2:]
        origin = -np.asarray(R, float).T @ np.asarray(T, float).ravel()
        ray = c - origin
        out.append((float(np.arccos(min(1.0, abs(float(n @ ray)) / np.linalg.norm(ray)))), name))
    return max(out)


def predict_feature(feature, scene, calib, part_to_camera, model, geo=None, shading=None, form=True):
    """Run one CAD feature through the measurement chain's covariance code.

    Parameters
    ----------
    feature : partinspect.cad.features.Feature
    scene : RaycastScene
    calib : StereoCalibration
    part_to_camera : ndarray, shape (4, 4)
    model : DetectorModel
    geo : EpipolarGeometry, optional
        Of ``calib`` (computed when not given).
    shading : Shading, optional
    form : bool
        Whether a form is judged on the feature's points: then the points'
        responses to the calibration's uncertainty are computed for the
        form's Monte Carlo, as the run does (24 re-triangulations of every
        point where the calibration states its uncertainty).

    Returns
    -------
    FeaturePrediction
    """
    from partinspect.cad.edge_sampling import feature_geometry
    from partinspect.vision.calibration_points import point_responses
    from partinspect.vision.calibration_uncertainty import calibration_responses
    from partinspect.vision.correspondences import correspond
    from partinspect.vision.matching import epipolar_geometry
    from partinspect.vision.arc_partner import corrected_correspondences

    from partinspect.vision.feature3d import make_feature3d
    from partinspect.vision.rim_errors import radius_type_b_scale
    from partinspect.vision.stereo import fit_feature, views_of
    geo = geo if geo is not None else epipolar_geometry(calib)
    fid, kind = feature.id, feature.kind
    g = feature_geometry(feature)
    views = [(name, sample_view(scene, calib, i, part_to_camera, kind, g, model, shading))
             for i, name in enumerate(("left", "right"))]
    vl, vr = views[0][1], views[1][1]
    base = dict(id=fid, kind=kind, left=vl, right=vr)
    view_angle = None
    if kind != "line":
        view_angle, cam = _view_angle(calib, part_to_camera, g)
        base["view_angle"] = view_angle
        if view_angle > EDGE_ON_ANGLE:
            return FeaturePrediction(status="edge-on", reason=(
                f"{fid} is seen nearly edge-on ({np.rad2deg(view_angle):.0f} deg from its axis in the {cam} camera)"), **base)
    if min(len(vl), len(vr)) < model.min_points:
        return FeaturePrediction(status="hidden", reason=_hidden_reason(fid, feature, views), **base)
    faint = [(name, v.fractions["step"]) for name, v in views
             if model.contrast is None and v.fractions.get("step", np.inf) < _least_step(model)]
    if faint and not getattr(feature, "smooth", False):
        name, step = faint[0]
        return FeaturePrediction(status="faint", reason=(
            f"{fid} shows a median grey step of {step:.0f} over the part of it in view in the {name} image, under the "
            f"{_least_step(model):.0f} the run needs to count it shown (its faces look alike under this lighting; "
            f"{100 * dict(views)[name].fractions['contrast']:.0f} % of it shows a step)"), **base)
    kind2 = "line" if kind == "line" else "arc"
    try:
        fl = _image_feature(kind2, vl, calib.K1, calib.D1, model)
        fr = _image_feature(kind2, vr, calib.K2, calib.D2, model)
    except (np.linalg.LinAlgError, ValueError) as exc:
        return FeaturePrediction(status="failed", reason=f"{fid}: 2D fit failed ({exc})", **base)
    if kind != "line":
        base["axis_ratio"] = float(min(f.fit.params[3] / f.fit.params[2] for f in (fl, fr)))
        short = radius_untold(fl, fr)
        if short is not None:
            return FeaturePrediction(status="unmatched", reason=(
                f"{fid}'s arcs are too short to tell its radius: the matcher could not pair them "
                f"(u of the two images' radius ratio {100 * short:.0f} %, beyond the "
                f"{100 * RADIUS_WIDENING_MAX * _RADIUS_TOLERANCE / RADIUS_COVERAGE:.0f} % it accepts)"), **base)
    if kind == "line":
        ang, img = _epipolar_angle(geo, fl, fr)
        base["epipolar_angle"] = ang
        if ang < EPIPOLAR_MIN_ANGLE:
            return FeaturePrediction(status="degenerate", reason=(
                f"{fid} runs {np.rad2deg(ang):.1f} deg from the epipolar lines in the {img} image "
                f"(under {np.rad2deg(EPIPOLAR_MIN_ANGLE):.0f} deg its depth is undetermined)"), **base)
    corr = correspond(fl, fr, geo)
    if len(corr) < 6:
        return FeaturePrediction(status="failed", reason=(
            f"{fid}: only {len(corr)} corresponding points (epipolar lines cross it too obliquely)"), **base)
    try:
        views_under = views_of(fl, fr, model.sigma)
        fviews = views_under(calib)
        fit = fit_feature(fl, fr, fviews, corr.points, geo)
        corr = corrected_correspondences(fl, fr, fviews, corr, geo, model.sigma)
    except (np.linalg.LinAlgError, ValueError) as exc:
        return FeaturePrediction(status="failed", reason=f"{fid}: 3D fit failed ({exc})", **base)
    cal = calibration_responses(fit, kind2, views_under, calib)
    if not model.systematic and fit.param_cov_systematic is not None:
        # The chain weights a rim's points by their Type B part too (the
        # points beside a steep shading count less), which widens its
        # random part: the noise-only figure keeps those weights and leaves
        # out only the Type B part (with the bound set to zero instead, the
        # fit would weight the points by their noise alone and describe a
        # more efficient estimator than the chain's).
        # The points' error model keeps its Type B part: the form's noise-only
        # figure holds it per scene (evaluate_characteristic's one_scene).
        fit = dataclasses.replace(fit, param_cov=fit.param_cov - fit.param_cov_systematic,
                                  param_cov_systematic=np.zeros_like(fit.param_cov_systematic))
    # The calibration bends a rim, not only moves it: the form's Monte Carlo
    # draws the points' responses, as the run's does.
    P = point_responses(corr, calib) if form and cal.shape[1] else None
    # The radius without the detector's per-point floor, as the run states it (no residuals to size the centre by).
    radius_scale = radius_type_b_scale(fviews, fit) if fl.kind == "arc" and model.systematic else 1.0
    f3 = make_feature3d(SimpleNamespace(left=0, right=0), fl, fr, fit, corr, cal, geo, fviews[0], point_response=P,
                        radius_scale=radius_scale)
    return FeaturePrediction(status="measured", record=f3, **base)


# ---------------------------------------------------------------------------
# characteristics


def tolerance_width(c):
    """Width of a characteristic's specification zone (None without limits)."""
    lo, hi = c.lower_limit, c.upper_limit
    if lo is not None and hi is not None:
        return float(hi - lo)
    if hi is not None and lo is None and c.nominal == 0.0:
        return float(hi)  # a geometrical tolerance: zone from 0 to its width
    return None


def _causes(c, features):
    """Why a measured characteristic's U is large: the weak points of its features."""
    out = []
    for fid in c.features:
        fp = features.get(fid)
        if fp is None or not fp.measured:
            continue
        if fp.epipolar_angle is not None and fp.epipolar_angle < NARROW_EPIPOLAR_ANGLE:
            out.append(f"{fid} runs only {np.rad2deg(fp.epipolar_angle):.0f} deg from the epipolar lines")
        if fp.view_angle is not None and fp.view_angle > OBLIQUE_ANGLE:
            out.append(f"{fid} is seen {np.rad2deg(fp.view_angle):.0f} deg off its axis (nearly edge-on)")
        if fp.visible_fraction < 0.7:
            out.append(f"only {100 * fp.visible_fraction:.0f} % of {fid} is visible in both images")
        if fp.median_contrast < LOW_CONTRAST:
            out.append(f"{fid} has only {fp.median_contrast:.0f} grey levels of contrast")
    return out


def _fmt(x, unit):
    return f"{math.degrees(x):.4f} deg" if unit == "rad" else f"{x:.4f} mm"


def _unregistered_reason(fid):
    """Why a measured feature is left out: the registration does not match it."""
    return (f"{fid} would be measured but the registration does not match it to the CAD model "
            "(e.g. a rim seen only through its hole, whose plane face is turned away from the cameras)")


def _general(c):
    return c.source != "spec"


def _characteristic_prediction(c, ev, features, max_ratio, registration_error):
    T = tolerance_width(c)
    if ev is None or ev.standard_uncertainty is None:
        why = [features[f].reason for f in c.features if f in features and not features[f].measured]
        if not why and registration_error:
            why = [registration_error]
        if not why:
            why = [_unregistered_reason(f) for f in c.features if f in features and features[f].measured]
        if not why and ev is not None:
            why = [ev.reason]
        hidden = any(f in features and features[f].status == "hidden" for f in c.features)
        measured_any = any(f in features and features[f].measured for f in c.features)
        inspected = not (_general(c) and hidden and not measured_any)
        return CharacteristicPrediction(c, math.inf, math.inf, T, math.inf, False,
                                        "; ".join(why) or "not measurable", inspected=inspected)
    warn = [f"{fid} is seen {np.rad2deg(features[fid].view_angle):.0f} deg off its axis: its image is an ellipse "
            f"of axis ratio {features[fid].axis_ratio:.2f}, which the segmentation may break into pieces"
            for fid in c.features if fid in features and features[fid].measured
            and features[fid].axis_ratio is not None and features[fid].axis_ratio < FLAT_ELLIPSE]
    u, U = float(ev.standard_uncertainty), float(ev.expanded_uncertainty)
    ratio = U / T if T else float("nan")
    ok = T is not None and U <= max_ratio * T
    reason = None
    if not ok:
        if T is None:
            reason = "no tolerance to compare with"
        else:
            causes = _causes(c, features) or ["the edge-point noise alone (noise-limited)"]
            reason = (f"U = {_fmt(U, c.unit)} is {ratio:.2f} of the tolerance {_fmt(T, c.unit)} "
                      f"(needs <= {max_ratio:g}): " + "; ".join(causes))
    return CharacteristicPrediction(c, u, U, T, ratio, ok, reason, ev.method, warning="; ".join(warn) or None)


def predict_pose(inventory, scene, calib, part_to_camera, characteristics, *, model=None, datums=None,
                 datums_fallback=False, max_ratio=DEFAULT_RATIO, shading=None, n_mc=None, seed=0, label="", angles=()):
    """Predicted U of every characteristic with the part in one pose.

    Parameters
    ----------
    inventory : Inventory
    scene : RaycastScene
        The part's mesh in the ray caster (:func:`partinspect.cad.raycast.build_scene`).
    calib : StereoCalibration
        With ``image_size``.
    part_to_camera : ndarray, shape (4, 4)
    characteristics : sequence of Characteristic
    model : DetectorModel, optional
    datums : sequence of str, optional
        CAD ids the registration aligns on (default all matched features).
    datums_fallback : bool
        Align on every matched feature when the datums leave the pose free,
        as `inspect` does with the PMI's datums; else that is no registration.
    max_ratio : float
        Decidable when ``U <= max_ratio * tolerance``.
    shading : Shading, optional
    n_mc : int, optional
        Monte Carlo draws of evaluate() for position and profile (its
        default when None).
    seed : int
    label : str
    angles : tuple
        The fixture angles of the pose, for the report.

    Returns
    -------
    PosePrediction
    """
    from partinspect.cad.registration import RegistrationError, register
    from partinspect.tolerances.evaluate import N_MC, evaluate_characteristic
    from partinspect.vision.matching import epipolar_geometry

    model = model or DetectorModel()
    geo = epipolar_geometry(calib)
    P = np.asarray(part_to_camera, float)
    wanted = {fid for c in characteristics for fid in c.features}
    if datums:
        wanted |= set(datums)
    # Every non-smooth feature takes part in the registration, as in a real run.
    todo = [f for f in inventory.features if f.id in wanted or not f.smooth]
    formed = {fid for c in characteristics if c.type in ("straightness", "circularity", "profile") for fid in c.features}
    features = {f.id: predict_feature(f, scene, calib, P, model, geo, shading, f.id in formed) for f in todo}
    measured = [fp for fp in features.values() if fp.measured]
    circles = [fp for fp in measured if fp.kind != "line"]
    lines = [fp for fp in measured if fp.kind == "line"]
    reg, reg_error = None, None
    used_datums = None if not datums else [d for d in datums if d in features and features[d].measured]
    records = ([fp.record for fp in circles], [fp.record for fp in lines])
    try:
        try:
            if datums and not used_datums:
                raise RegistrationError("none of the datum features is measurable")
            reg = register(*records, inventory, datums=used_datums, pose_hint=P)
        except RegistrationError:
            if not datums_fallback:
                raise
            reg = register(*records, inventory, datums=None, pose_hint=P)
    except RegistrationError as exc:
        reg_error = f"no registration: {exc.problem}"
    if reg is not None:
        reg = tied_registration(reg, [fp.record for fp in circles], [fp.record for fp in lines], inventory,
                                used_datums, P)
    preds = []
    parts = reg.features_in_part_frame() if reg is not None else None

    def evaluate(c, r, p):
        return evaluate_characteristic(c, p, r, inventory, seed=seed, n_mc=n_mc or N_MC, one_scene=not model.systematic)

    rival_parts = [r.registration.features_in_part_frame() for r in reg.competing] if reg is not None else []
    for c in characteristics:
        ev = evaluate(c, reg, parts) if reg is not None else None
        pred = _characteristic_prediction(c, ev, features, max_ratio, reg_error)
        if rival_parts and ev is not None and ev.standard_uncertainty is not None:
            pred = _across_poses(pred, ev, reg, rival_parts, evaluate)
        preds.append(pred)
    return PosePrediction(P, features, preds, reg, reg_error, max_ratio, label, tuple(angles),
                          reg.ambiguity if reg is not None and reg.competing else "")


def tied_registration(reg, circles, lines, inventory, datums, part_to_camera):
    """``reg`` with the poses that explain its features as well as the true pose, as ``inspect`` would find them.

    The prediction registers with the true pose as hint, which skips the
    search and so never sees a tie. ``inspect`` searches
    (:func:`partinspect.cad.registration.register` without a hint): where
    the features measured are symmetric and the CAD model is not (a
    clocking feature out of sight), several poses tie
    (:mod:`partinspect.cad.ties`). The same search is made here on the
    predicted features; where it finds a tie, the registration is made
    again from the true pose and the tied ones, the true pose first, so the
    competing poses are named relative to it.

    Parameters
    ----------
    reg : Registration
        At the true pose.
    circles, lines : list
        The predicted measured features' records, rig frame.
    inventory : Inventory
    datums : list of str or None
    part_to_camera : ndarray, shape (4, 4)
        The true pose.

    Returns
    -------
    Registration
        ``reg`` itself when nothing ties (or the search fails: the hinted
        registration stands), else one with ``competing`` poses.
    """
    from partinspect.cad.registration import RegistrationError, register

    try:
        found = register(circles, lines, inventory, datums=datums)
        if not found.competing:
            return reg
        hints = np.concatenate([np.asarray(part_to_camera, float)[None], found.poses])
        return register(circles, lines, inventory, datums=datums, pose_hint=hints)
    except RegistrationError:
        return reg


def _across_poses(pred, ev, reg, rival_parts, evaluate):
    """``pred`` not decidable when its characteristic depends on which of the tied poses is right.

    As ``inspect`` judges it (:func:`partinspect.tolerances.ambiguity.dependence`):
    its CAD features matched to other measured edges under a competing
    pose, or its value there differing beyond the uncertainty. Such a
    characteristic comes out inconclusive whatever its U.
    """
    from partinspect.tolerances.ambiguity import alike, dependence, depends_on_words

    c = pred.characteristic
    rivals = [evaluate(c, r.registration, p) if alike([c], reg, r.registration) else None
              for r, p in zip(reg.competing, rival_parts)]
    what = dependence(c, ev, reg, rivals)
    if what is None:
        return pred
    return dataclasses.replace(pred, decidable=False, reason=f"{depends_on_words(reg)}; {what}")
