"""Image features: the segments of one image merged where they are one edge, refitted in ideal pixels.

The segmentation (:mod:`partinspect.vision.contours`) ends a piece wherever
its points stop passing a line or ellipse test, so one physical edge
interrupted by an occlusion, a specular spot, a corner of the segmentation
or a stretch of lower contrast comes out in several pieces. Here they are
merged, many to one: collinear lines and co-elliptic arcs are tried as one,
and the union is taken when the RMS of its residuals is within a factor of
the pieces' (for arcs, or within a fixed misfit in px) and it keeps most of
each piece's points. Every feature is fitted to its points in *ideal*
pixels (distortion removed, :mod:`partinspect.vision.ideal`), where the
projective geometry of two views holds, with the orthogonal line fit or the
geometric ellipse fit of :mod:`partinspect.vision.fitting` [1]_.

Two kinds of points are kept out of a feature's fit, because their
displacement is not what their standard uncertainty says:

- points of an arc whose standard uncertainty across the edge is many times
  the arc's median (``FADE_RATIO``, ``FADE_END_RATIO``): the edge has faded
  there, and the sub-pixel position follows whatever else is beside it;
- outliers, by Chauvenet's criterion [2]_: the worst point is dropped and
  the fit redone while its normalised residual exceeds the threshold at
  which a feature of N clean points loses one with chance
  ``OUTLIER_ALPHA``, at most ``MAX_OUTLIER_FRACTION`` of the points (corner
  ends, a neighbouring edge's smoothing: one such point would set a form
  zone).

Points are in pixels: distorted as detected (``uv``), ideal for the fits;
standard uncertainties in px (JCGM 100).

References
----------
.. [1] Paper of this project, section 3 (orthogonal line fit, geometric
       ellipse fit of the segments).
.. [2] Taylor, J. R. (1997). An Introduction to Error Analysis, 2nd ed.,
       section 6.2 (Chauvenet's criterion).
"""

from dataclasses import dataclass, replace

import cv2
import numpy as np

from partinspect.vision.fitting import (
    EllipseJob,
    as_points,
    axis_bound,
    direct_residuals,
    ellipse_geometry,
    ellipse_with_covariance,
    fit_ellipse,
    fit_ellipses,
    fit_line,
    line_with_covariance,
)
from partinspect.vision.ideal import IDEAL_FIELDS, IdealPoints, ideal_points
from partinspect.vision.pixel_phase import without_phase_ripple

__all__ = [
    "ImageFeature",
    "image_features",
    "one_polarity",
    "point_polarity",
    "arc_stretch",
    "at_points",
    "chauvenet_z",
    "OUTLIER_ALPHA",
    "OUTLIER_Z_MAX",
    "MAX_OUTLIER_FRACTION",
]


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
    phase_factor : ndarray, shape (N, k) or None
        Lines whose points' sub-pixel phase ripple was removed
        (:mod:`partinspect.vision.pixel_phase`): the correction's error
        across the line per unit normal deviate, px. None elsewhere.
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
    phase_factor: np.ndarray | None = None

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
segment of lower contrast): there the edge profile has flattened (a weak
or broad step), and the sub-pixel position follows whatever else is beside
the edge. Where a hole's rim fades against its lit inner wall, the contour
runs on along the wall's shading, and a short arc's ellipse bends to take
such a tail in and still passes every residual test."""
FADE_END_RATIO = 2.5
"""The same at the ends of each segment of an arc, from the end inwards
while the points exceed this many times the arc's median: a rim fades
towards the end of its visible stretch, and its last points there are
displaced by more than their standard uncertainty says. A segment whose
median itself exceeds this many times the arc's is judged against its own
(:func:`_unfaded`)."""


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
    parts = [np.split(getattr(ideal, f), cuts) for f in IDEAL_FIELDS]
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
    against its own. Every other segment is judged against the arc's: its
    own median would keep the points at a fading end.
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


@dataclass
class _Trial:
    """One feature through the rounds of :func:`_make_features`: its points and its fit so far."""

    kind: str
    seg_ids: list
    index: np.ndarray
    """Indices into the EdgePoints of its segments' fitted points."""
    piece: np.ndarray
    """Position in ``seg_ids`` of the segment of each point."""
    all_ideal: IdealPoints
    """All the points in ideal pixels."""
    keep: np.ndarray
    """Positions (into ``index``) of the points fitted this round."""
    budget: int
    """Outliers it may still lose."""
    start: object = None
    """Start of its next ellipse fit (None: the direct fit's)."""
    ideal: IdealPoints = None
    fit: object = None


def _trial(kind, seg_ids, segments, seg_ideal):
    """The first round of the feature of segments ``seg_ids``: their points, less an arc's faded ones."""
    index = np.concatenate([segments[i].fit_index for i in seg_ids])
    piece = np.repeat(np.arange(len(seg_ids)), [len(segments[i].fit_index) for i in seg_ids])
    all_ideal = IdealPoints(*(np.concatenate([getattr(seg_ideal[i], f) for i in seg_ids])
                              for f in IDEAL_FIELDS))
    keep = np.arange(len(index)) if kind == "line" else _unfaded(all_ideal.normal_std, [
        len(segments[i].fit_index) for i in seg_ids])
    # One arc segment: its own fit (of the same points, in distorted
    # pixels, corrected for the smoothing) starts the fit next to its
    # minimum; the direct fit can start a short piece far from it.
    start = None
    if kind == "arc" and len(seg_ids) == 1 and segments[seg_ids[0]].kind == "arc":
        start = segments[seg_ids[0]].fit.params
    return _Trial(kind, seg_ids, index, piece, all_ideal, keep, int(MAX_OUTLIER_FRACTION * len(index)), start)


def _fit_kept(trials, corr_length):
    """One round of fits: each trial's kept points, the lines one by one, the arcs' ellipses together."""
    jobs = []
    for t in trials:
        t.ideal = ideal = IdealPoints(*(np.ascontiguousarray(getattr(t.all_ideal, f)[t.keep]) for f in IDEAL_FIELDS))
        if t.kind == "line":
            t.fit = fit_line(ideal.xy, ideal.cov, corr_length=corr_length, with_cov=False)
        else:
            # No smoothing-bias correction (fit_ellipse's ``blur``): the
            # rims of holes are not uniform discs, and there it moves the
            # points off the true ellipse rather than onto it. After
            # dropping one point the previous fit is a start next to the
            # new minimum (same minimum, fewer iterations).
            jobs.append((t, EllipseJob(as_points(ideal.xy, 6), ideal.cov, corr_length, None, t.start,
                                       max_axis=axis_bound(ideal.xy))))
    # Converged at fit_ellipse's pixel tolerance or once the remaining
    # step is below a thousandth of the parameters' standard
    # uncertainties: a short piece's ellipse is uncertain by pixels, and
    # its cost so flat that the pixel tolerance takes a hundred
    # iterations to reach, for nothing; such a fit (or a union of two
    # edges) stops after FIT_ITERATIONS, as the segmentation's.
    for (t, _), fit in zip(jobs, fit_ellipses([job for _, job in jobs], FIT_ITERATIONS, with_cov=False,
                                              sigma_tol=FIT_SIGMA_TOL)):
        t.fit = fit


def _drop_worst(t):
    """Drop a trial's worst point if it is an outlier (``OUTLIER_ALPHA``) and its budget allows; whether it did."""
    fit = t.fit
    z = np.abs(fit.residuals) / np.maximum(fit.point_std, 1e-12)
    worst = int(np.argmax(z))
    if z[worst] <= _outlier_threshold(z) or t.budget == 0:
        return False
    t.keep = np.delete(t.keep, worst)
    t.budget -= 1
    t.start = fit.params if t.kind == "arc" else None
    return True


def _feature(t, edges):
    """The ImageFeature of a trial's last fit, with its polarity."""
    kind, fit, ideal = t.kind, t.fit, t.ideal
    index = t.index[t.keep]
    uv, cov = edges.xy[index], edges.cov[index]
    blur = float(np.median(edges.width[index]))
    along = _along_fit_normal(kind, ideal, fit)
    polarity = (1 if along.mean() > 0 else -1) if kind == "arc" else 0
    # Polarity per piece (the mean over its points), so that a stray
    # point does not make a feature mixed.
    piece = t.piece[t.keep]
    sums = np.bincount(piece, along, minlength=len(t.seg_ids))
    signs = np.sign(sums[np.bincount(piece, minlength=len(t.seg_ids)) > 0])
    mixed = bool(signs.min() != signs.max())
    return ImageFeature(kind, tuple(int(i) for i in t.seg_ids), index, uv, cov, ideal, fit, blur, polarity, mixed)


def _make_features(requests, segments, edges, seg_ideal):
    """Image features of several (kind, segment ids) requests at once.

    Points of arcs where the edge has faded are left out (``FADE_RATIO``,
    ``FADE_END_RATIO``); each feature is fitted, its worst outlier dropped
    and the fit redone while one remains: a single displaced point (a
    corner-rounded end that passed the segmentation's trim) would
    otherwise enter the 3D points and make a straight edge look out of
    straightness by tenths of a mm. The ellipse fits of all requests in one
    such round run together
    (:func:`partinspect.vision.fitting.fit_ellipses`), each as it would
    alone. The fits come without their covariances (``cov`` None): most
    features made are merge trials that are not kept;
    :func:`_with_covariance` completes the kept ones, as the fits would
    have computed them.
    """
    trials = [_trial(kind, seg_ids, segments, seg_ideal) for kind, seg_ids in requests]
    active = trials
    while active:
        _fit_kept(active, edges.sigma)
        active = [t for t in active if _drop_worst(t)]
    return [_feature(t, edges) for t in trials]


def _with_covariance(f, corr_length):
    """Feature f (of :func:`_make_features`) with its fit's covariance."""
    if f.fit.cov is not None:
        return f
    complete = line_with_covariance if f.kind == "line" else ellipse_with_covariance
    return replace(f, fit=complete(f.fit, f.ideal.xy, corr_length))


def _without_ripple(f, edges):
    """A kept line with its points' sub-pixel phase ripple removed, its outliers screened again.

    See :mod:`partinspect.vision.pixel_phase`. The ripple can hide a
    displaced point (a corner-rounded end) that the screen before its
    removal let through, so the screen (``OUTLIER_ALPHA``) runs again on
    the corrected residuals, the ripple estimated again after each point
    dropped, within the feature's outlier budget.
    """
    budget = int(MAX_OUTLIER_FRACTION * len(f.index))
    while True:
        g = without_phase_ripple(f, edges)
        if g is f:
            return f
        z = np.abs(g.fit.residuals) / np.maximum(g.fit.point_std, 1e-12)
        worst = int(np.argmax(z))
        if z[worst] <= _outlier_threshold(z) or budget == 0:
            return g
        f = at_points(f, np.delete(np.arange(len(f.index)), worst),
                      lambda ideal: fit_line(ideal.xy, ideal.cov, corr_length=edges.sigma))
        budget -= 1


def point_polarity(f):
    """Each point's polarity on an arc: +1 where brighter outside its fitted ellipse, -1 where brighter inside.

    The sign of the edge normal (dark to bright) along the ellipse's
    outward normal at the point's foot, as :func:`_feature` reads the
    arc's polarity, shape (N,).
    """
    return np.sign(_along_fit_normal("arc", f.ideal, f.fit))


def _along_fit_normal(kind, ideal, fit):
    """Each point's edge normal (dark to bright) along its fit's normal (outward for arcs), shape (N,): its polarity's sign."""
    if kind == "arc":
        _, n_out, _ = ellipse_geometry(ideal.xy, fit.params, fit.phases)
    else:
        n_out = fit.normal[None, :]
    return np.einsum("ni,ni->n", n_out, ideal.normal)


def one_polarity(fl, fr, corr_length, min_points=6):
    """A matched pair of arcs, either of mixed polarity, restricted to one polarity in both images, refitted.

    Across a broken (rounded or chamfered) rim the grey level is not one
    step but a profile over the band: where the band is lit brighter than
    both the face and the wall (or darker than both) it shows as a ridge,
    whose two flanks are steps of opposite polarity about a blurred band's
    width apart, and where the wall changes from lit to shadowed the step
    changes place across the band. A rim's pieces of opposite polarity then
    lie on different curves, and each camera may follow either: a pair
    measured on both triangulates one image's flank against the other's,
    out of round by the flanks' distance. On a sharp rim the two
    polarities are one curve (``mixed_polarity``); only a broken one's pair
    is restricted, to the polarity both images see most of (the larger of
    the two polarities' smaller counts in the two images).

    Parameters
    ----------
    fl, fr : ImageFeature
        The left and right arcs of one matched pair.
    corr_length : float
        The edge filter's scale, px: the refit's correlation length along
        the edge, as :func:`image_features` fits.
    min_points : int
        Fewest points of the kept polarity in each image.

    Returns
    -------
    (ImageFeature, ImageFeature) or None
        Each arc with only its points of that polarity (:func:`arc_stretch`:
        the ellipse and its covariance fitted again, ideal px; an arc with
        no point of the other polarity is returned as it is), or None where
        an image has fewer than ``min_points`` of it.
    """
    if fl.kind != "arc" or not (fl.mixed_polarity or fr.mixed_polarity):
        return fl, fr
    signs = [point_polarity(f) for f in (fl, fr)]
    keep = max((1.0, -1.0), key=lambda s: min(np.count_nonzero(p == s) for p in signs))
    out = []
    for f, p in zip((fl, fr), signs):
        at = np.flatnonzero(p == keep)
        if len(at) < min_points:
            return None
        out.append(f if len(at) == len(p) else replace(arc_stretch(f, at, corr_length), mixed_polarity=False,
                                                       polarity=int(keep)))
    return tuple(out)


def arc_stretch(feature, keep, corr_length):
    """An image arc feature restricted to some of its points and fitted again.

    Parameters
    ----------
    feature : ImageFeature
        An arc (an :class:`partinspect.vision.stereo.EdgeFeature` too: its
        per point edge data are kept alike).
    keep : ndarray of int, shape (K,)
        Positions of the kept points in the feature's point arrays.
    corr_length : float
        Correlation length of the points' noise along the edge, px.

    Returns
    -------
    ImageFeature
        Same kind, segments, polarity and blur; its points and their per
        point data (ideal coordinates, edge normals, background readings)
        those at ``keep``; its ellipse (with covariance) fitted to those
        points alone, from the whole arc's ellipse as start, without the
        smoothing-bias correction (as the chain fits arcs).
    """
    return at_points(feature, keep, lambda ideal: fit_ellipse(ideal.xy, ideal.cov, corr_length=corr_length,
                                                              start=feature.fit.params), _ARC_POINT_FIELDS)


def at_points(feature, keep, fit, fields=()):
    """A feature restricted to its points at positions ``keep`` and fitted again.

    Parameters
    ----------
    feature : ImageFeature
    keep : ndarray of int, shape (K,)
        Positions of the kept points in the feature's point arrays.
    fit : callable
        ``fit(ideal)``: the new fit of the kept :class:`IdealPoints`.
    fields : sequence of str
        Further per point attributes (of an
        :class:`partinspect.vision.stereo.EdgeFeature`) kept alike, those
        the feature has.

    Returns
    -------
    ImageFeature
        Of the feature's type, its other attributes as they were.
    """
    keep = np.asarray(keep, int)
    ideal = feature.ideal.at(keep)
    per_point = {name: getattr(feature, name)[keep] for name in fields if getattr(feature, name, None) is not None}
    return replace(feature, index=feature.index[keep], uv=feature.uv[keep], cov_uv=feature.cov_uv[keep],
                   ideal=ideal, fit=fit(ideal), **per_point)


_ARC_POINT_FIELDS = ("edge_normal", "background_offset", "background_bound", "background_std")
"""An :class:`partinspect.vision.stereo.EdgeFeature`'s per point data beside its points."""


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
    ellipse poorly, and worse than its first-order uncertainty says (its
    cost is flat along a curved valley), so comparing the pieces' ellipses
    refuses pieces of one rim; the points themselves tell. The geometric
    fit improves on the direct one by far less than ``MERGE_SCREEN`` in
    RMS for points of one ellipse (the direct fit is biased, not far off)
    and for points of two (both leave the misfit between them), so a union
    failing the screen would fail its test too.

    Arcs of opposite polarity are tried: a hole's rim against its inner
    wall, lit on one side and in shadow on the other, changes polarity
    along it (``ImageFeature.mixed_polarity``); the refit of a union of two
    different rims shows the two. Lines of opposite polarity are not: two
    different edges that happen to be collinear in one image (common in a
    view at grazing incidence) are one line within the noise there, and
    merged they match nothing.
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


def _made_once(requests, made, segments, edges, seg_ideal):
    """The features of (kind, segment ids) requests, each made once.

    A feature is fixed by its kind and segments: ``made`` keeps those made
    by that key, and the ones not made yet are made together (their
    ellipse fits batched).
    """
    todo = list(dict.fromkeys((kind, tuple(ids)) for kind, ids in requests if (kind, tuple(ids)) not in made))
    for key, f in zip(todo, _make_features([(kind, list(ids)) for kind, ids in todo], segments, edges, seg_ideal)):
        made[key] = f
    return [made[(kind, tuple(ids))] for kind, ids in requests]


def _pair_key(a, b):
    return (a.kind, a.segments, b.segments)


def _feature_rms(f, rms):
    """:func:`_rms` of a feature, kept in ``rms`` by its kind and segments."""
    key = (f.kind, f.segments)
    if key not in rms:
        rms[key] = _rms(f)
    return rms[key]


def _try_pairs(pairs, tried, rms, make, *, max_angle, max_offset, max_axis_ratio, merge_ratio, max_misfit):
    """Test the pairs of features not tried yet, and refit the unions of those that pass.

    ``tried`` keeps each pair's outcome by :func:`_pair_key`: None for no
    candidate (other kinds, or refused by :func:`_mergeable`), else (RMS of
    the union's residuals, the RMS it must reach, the union, the fractions
    of the two parts' points it keeps). A pair is tested and its union made
    once, not in every round of the merge; the unions of one round are
    made together (``make``, :func:`_made_once`). The options are
    :func:`image_features`'.
    """
    new = [(a, b) for a, b in pairs if _pair_key(a, b) not in tried]
    union = []
    limits = {}
    for a, b in new:
        if a.kind != b.kind:
            tried[_pair_key(a, b)] = None
            continue
        limit = merge_ratio * max(_feature_rms(a, rms), _feature_rms(b, rms))
        limit = max(limit, max_misfit) if a.kind == "arc" else limit
        if _mergeable(a, b, max_angle, max_offset, max_axis_ratio, limit):
            union.append((a, b))
            limits[_pair_key(a, b)] = limit
        else:
            tried[_pair_key(a, b)] = None
    for (a, b), u in zip(union, make([(a.kind, a.segments + b.segments) for a, b in union])):
        tried[_pair_key(a, b)] = (_feature_rms(u, rms), limits[_pair_key(a, b)], u, _kept(a, u), _kept(b, u))


def _merge_once(feats, tried):
    """The features after one merge step, or None when there is none left to make.

    The step is the best union of two features (smallest RMS), else the
    drop of an arc that is an outlier stretch of another's union; every
    pair of ``feats`` must be in ``tried`` (:func:`_try_pairs`).
    """
    # The union's RMS is pooled: a short stretch of another edge, or a
    # displaced stretch of this one (a rim beside a second edge closer than
    # the filter resolves), barely raises it, and the outlier rejection hides
    # it further by dropping its points. A union is taken only if it keeps
    # more than half of the points of each part: pieces of one edge lose far
    # fewer to the union, displaced stretches about that many or more. An
    # arc most of whose points the union rejects, while the union fits the
    # other part within the limit, is an outlier stretch of that rim: it is
    # dropped, as its points would have been had the two been found as one
    # piece. Lines are only not merged: a short edge parallel to a long one
    # and within the merge offset may be an edge of its own, a chamfer's.
    best = None
    outlier = None
    for i in range(len(feats)):
        for j in range(i + 1, len(feats)):
            trial = tried[_pair_key(feats[i], feats[j])]
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
        merged = [f for k, f in enumerate(feats) if k not in (i, j)] + [u]
        merged.sort(key=lambda f: f.segments[0])
        return merged
    if outlier is not None:
        return [f for k, f in enumerate(feats) if k != outlier]
    return None


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
        pixel over a long stretch, which would pass ``max_misfit`` and bend
        the merged line out of straightness. The union must also keep more
        than half of each part's points (:func:`_merge_once`); arcs of
        opposite polarity are tried, lines not (:func:`_mergeable`).

    Returns
    -------
    list of ImageFeature
        In the order of their first segment.
    """
    used = [i for i, s in enumerate(segments) if len(s.fit_index) >= min_fit_points]
    seg_ideal = _segment_ideal(segments, edges, K, D, used)
    made = {}

    def make(requests):
        return _made_once(requests, made, segments, edges, seg_ideal)

    feats = make([(segments[i].kind, [i]) for i in used])
    if merge:
        tried, rms = {}, {}
        while True:
            _try_pairs([(feats[i], feats[j]) for i in range(len(feats)) for j in range(i + 1, len(feats))],
                       tried, rms, make, max_angle=max_angle, max_offset=max_offset, max_axis_ratio=max_axis_ratio,
                       merge_ratio=merge_ratio, max_misfit=max_misfit)
            merged = _merge_once(feats, tried)
            if merged is None:
                break
            feats = merged
    feats = [_with_covariance(f, edges.sigma) for f in feats]
    return [_without_ripple(f, edges) if f.kind == "line" else f for f in feats]
