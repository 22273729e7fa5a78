"""The stereo measurement chain: an image pair to 3D lines and circles with covariances.

Per image: noise estimate -> sub-pixel edge points with covariances ->
contours -> line and ellipse segments -> image features in ideal pixels;
then the features are matched across the images by the epipolar
constraint, corresponding points triangulated with their error ellipsoids,
and each matched feature fitted in 3D to the edge points of both images at
once (:mod:`partinspect.vision.fit3d`), started from a PCA line or a
plane-and-circle fit through the triangulated points.

Uncertainty (GUM, JCGM 100): each 3D feature's covariance is the
first-order propagation of the edge points' covariances (sandwich form, the
along-edge correlation of smoothed noise included), plus the calibration's
part when ``calib.std`` is given
(:mod:`partinspect.vision.calibration_uncertainty`, parameters taken as
uncorrelated), plus the Type B part of rims and lines below;
:class:`~partinspect.vision.feature3d.Feature3D` keeps the three apart.

Rims of holes (circles and arcs). Before the 3D fit (:func:`feature_views`)
their points are corrected for the detector's curvature bias and for the
shading of the inner wall beside them, and each carries the Type B rest
of that correction; the rules are :mod:`partinspect.vision.rim_errors`'s.
A rim's correspondences are taken on the right ellipse refitted to the
corrected points (:mod:`partinspect.vision.arc_partner`), and its record
with its points' error model is a
:class:`~partinspect.vision.feature3d.Feature3D`.

Lines. Their points are used as found: along a straight edge the shading
beside it runs along it too, so it moves the whole line alike, by one
offset per image that the two-view fit turns into a displacement of the
3D line in depth and across, which its residuals cannot show. Where the
faces beside a line are not of uniform grey (a curved face beside it, a
fillet's band seen near grazing incidence) that offset is a Type B
standard uncertainty of the line in each image, fully correlated along it
(:func:`line_type_b`): it weights the line's two images in its fit and is
propagated with the random part into its covariance, so into a
registration's weights and the characteristics. Two readings size it: the
shading 3-4 px off the points, and a band nearer than that, read from the
grey profile across the line (:mod:`partinspect.vision.line_profile`).

Frames: 2D points in distorted pixels as detected, or ideal pixels where
said; 3D geometry in the rig frame (left camera, mm).

References
----------
.. [1] Hartley, R., & Zisserman, A. (2004). Multiple View Geometry in
       Computer Vision, 2nd ed.
.. [2] Lindstrom, P. (2010). Triangulation made easy. CVPR 2010.
.. [3] Quan, L. (1996). Conic reconstruction and correspondence from two
       views. IEEE PAMI 18(2), 151-160.
.. [4] JCGM 100:2008, Guide to the expression of uncertainty in
       measurement, section 5.1.
"""

from dataclasses import dataclass, fields, replace
from itertools import count

import cv2
import numpy as np

from partinspect.vision.arc_partner import corrected_correspondences
from partinspect.vision.contours import chain_edges, segment_contours
from partinspect.vision.correspondences import correspond, curvature_bias
from partinspect.vision.edges import EDGE_BIAS_FACTOR, background_shift_std, edge_points
from partinspect.vision.feature3d import make_feature3d
from partinspect.vision.forked import forked
from partinspect.vision.calibration_points import point_responses
from partinspect.vision.calibration_uncertainty import calibration_responses, residual_changes, uncertainty_directions
from partinspect.vision.band_modes import band_harmonics, edge_band
from partinspect.vision.fit3d import View, circle_consistency, circle_residuals_at, fit_circle_3d, fit_line_3d
from partinspect.vision.ideal import camera_matrices, to_ideal
from partinspect.vision.imagefeatures import ImageFeature, image_features, one_polarity
from partinspect.vision.line_profile import line_band_shift
from partinspect.vision.matching import arc_circle, epipolar_geometry, match_features
from partinspect.vision.noise import noise_level_function
from partinspect.vision.ramps import ramp_share
from partinspect.vision.rim_errors import (BACKGROUND_CORRECTION, EDGE_BIAS_CORR_ANGLE, correction_corr_length,
                                           correction_std_of, curvature_mode, form_view, radius_type_b_scale,
                                           rim_type_b, smoothed_background, type_b_scale)

__all__ = ["ImageResult", "EdgeFeature", "StereoResult", "measure_stereo", "measure_images", "feature_views",
           "views_of", "line_type_b", "edge_band", "fit_feature", "measure_pair_feature"]

MISMATCH_P = 1e-6
"""A matched pair of arcs whose 3D circle fits both images worse than their
two ellipses by more than this chance allows
(:func:`partinspect.vision.fit3d.circle_consistency`) is not kept: they are
the rims of two different holes. True pairs' p-values run low (the Type B
displacements bend two free ellipses more easily than one circle), so only
a gross misfit, beyond 5 sigma, counts."""
LINE_BOUND_READING = float(np.hypot(BACKGROUND_CORRECTION, EDGE_BIAS_FACTOR))
"""Type B standard uncertainty of a line's offset in one image per px of
the median shading bound of its points (:func:`line_type_b`). A line is not
corrected, so what the shading moves it by is all left: the displacement
the rims' correction would remove (``BACKGROUND_CORRECTION`` times the
first-order shift, whose size the bound is) and what that correction
leaves (``EDGE_BIAS_FACTOR`` times the bound), in quadrature
(JCGM 100 F.2.4.5: a known effect left uncorrected goes into the
uncertainty)."""


@dataclass(frozen=True)
class ImageResult:
    """The 2D chain of one image.

    Attributes
    ----------
    noise : float
        Estimated image noise, grey levels.
    edges : EdgePoints
        Distorted pixels.
    segments : list of Segment
    features : list of ImageFeature
        Segments merged into edges, refitted in ideal pixels.
    """

    noise: float
    edges: object
    segments: list
    features: list


@dataclass(frozen=True)
class StereoResult:
    """Everything :func:`measure_stereo` found.

    Attributes
    ----------
    left, right : ImageResult
    geometry : EpipolarGeometry
    matching : Matching
        Matches and unmatched features with their reasons.
    features : tuple of Feature3D
    failed : tuple of (Match, str)
        Matched pairs whose 3D fit failed, with the reason.
    calibration_included : bool
        Whether the calibration's stated uncertainty was propagated.
    guided_failed : tuple of (str, str)
        CAD edges whose own stretches of longer image lines were found in
        both images but not measured, with the reason
        (:func:`partinspect.vision.guided.guided_lines`).
    withdrawn : tuple of (str, str)
        CAD edges whose 3D line was taken out after registration, with the
        reason (:func:`partinspect.vision.posed.cleared_stereo`).
    edge_break : float or None
        RMS distance, mm, of a broken edge's apparent step from the sharp
        edge (:func:`measure_stereo`); None for sharp edges.
    """

    left: ImageResult
    right: ImageResult
    geometry: object
    matching: object
    features: tuple
    failed: tuple
    calibration_included: bool
    guided_failed: tuple = ()
    withdrawn: tuple = ()
    edge_break: float | None = None


@dataclass(frozen=True)
class EdgeFeature(ImageFeature):
    """An :class:`~partinspect.vision.imagefeatures.ImageFeature` with what the 3D fit needs of its edge points.

    Attributes
    ----------
    edge_normal : ndarray, shape (N, 2) or None
        ``EdgePoints.normal`` of each point (distorted px), and
    corr_length : float or None
        the edge filter's scale its points were found with, px (the
        correlation length of their noise along the edge): what a Monte
        Carlo of the feature draws with, kept on the feature so that one
        measured in another adaptive round than its neighbours
        (:mod:`partinspect.adaptive`) carries its own.
    ramp_share : float or None
        The share of its peak gradient that the grey-level slope beside it
        keeps on both sides (:func:`partinspect.vision.ramps.ramp_share`):
        above ``RAMP_SHARE`` it is a shading ramp's crest, not a step
        edge, and the matching leaves it out.

    Arcs, averaged along the edge over ``BACKGROUND_SMOOTHING`` px (lines:
    ``background_bound`` alone, as read at each point; the others None):

    background_offset : ndarray, shape (N, 2) or None
        First-order displacement of each point by the grey-level gradients
        beside the edge (``EdgePoints.background_shift`` times the normal),
        distorted px.
    background_bound : ndarray, shape (N,) or None
        ``EdgePoints.background_bound`` of each point, px.
    background_std : ndarray, shape (N,) or None
        Standard deviation of ``background_offset`` along the normal from
        image noise, px.

    A broken rim moved onto its sharp edge's image
    (:func:`partinspect.vision.band_place.rims_at_sharp_edge`):

    Lines:

    band_shift : ndarray, shape (N,) or None
        The displacement of the points by a narrow band beside the line,
        px, as the profile across the image line they were found on reads
        it (:func:`partinspect.vision.line_profile.line_band_shift`; one
        value for the points of one image line).

    band_modes : ndarray, shape (k, N) or None
        The displacement of each point across the edge by one standard
        uncertainty of each of its band place's shared errors, ideal px
        (``View.modes``).
    band_mode_names : tuple of k str or None
        Their names: the two images of one rim share them.
    """

    edge_normal: np.ndarray | None = None
    corr_length: float | None = None
    ramp_share: float | None = None
    background_offset: np.ndarray | None = None
    background_bound: np.ndarray | None = None
    background_std: np.ndarray | None = None
    band_shift: np.ndarray | None = None
    band_modes: np.ndarray | None = None
    band_mode_names: tuple | None = None


def _with_edge_data(feature, edges, image):
    base = {f.name: getattr(feature, f.name) for f in fields(ImageFeature)}
    i = feature.index
    base.update(edge_normal=edges.normal[i], corr_length=float(edges.sigma),
                ramp_share=ramp_share(image, edges.xy[i], edges.normal[i], edges.strength[i]))
    if edges.background_shift is None:
        return EdgeFeature(**base)
    if feature.kind != "arc":
        shift = line_band_shift(image, feature.uv, edges.normal[i], edges.sigma, edges.background_bound[i])
        return EdgeFeature(**base, background_bound=edges.background_bound[i], band_shift=np.full(len(i), shift))
    std = background_shift_std(edges, i)
    values = np.c_[edges.background_shift[i, None] * edges.normal[i], edges.background_bound[i]]
    mean, mean_std = smoothed_background(edges.xy[i], values, std, edges.sigma)
    return EdgeFeature(**base, background_offset=mean[:, :2], background_bound=mean[:, 2], background_std=mean_std)


def measure_images(image, K, D, *, sigma=1.0, edge_options=None, segment_options=None):
    """The 2D chain of one image (distorted pixels in, ideal-pixel features out).

    ``edge_options`` go to :func:`partinspect.vision.edges.edge_points`
    (e.g. the hysteresis factors ``k_low``, ``k_high``), ``segment_options``
    to :func:`partinspect.vision.contours.segment_contours` (e.g.
    ``alpha``, ``min_length``): the knobs the adaptive steps turn.
    """
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    level = noise_level_function(img)
    noise = level.noise
    edges = edge_points(img, sigma, noise=noise, noise_level=level, **(edge_options or {}))
    segments = segment_contours(edges, chain_edges(edges), **(segment_options or {}))
    feats = [_with_edge_data(f, edges, img) for f in image_features(edges, segments, K, D)]
    return ImageResult(noise, edges, segments, feats)


# ------------------------------------------------------------------ 3D fits


def feature_views(fl, fr, corr_length, calib, uv=None, remap=False, correction_std=None, band=None):
    """fit3d Views of a matched pair: ideal points, their
    across-edge standard uncertainties, the cameras of ``calib``.

    ``uv`` optionally replaces the two features' distorted points (Monte
    Carlo); with it, or with ``remap`` (a perturbed calibration), the
    distorted points are mapped to ideal pixels again with ``calib``.

    Points of arcs are corrected first (module notes, "Rims of holes"):
    ``BACKGROUND_CORRECTION`` times the first-order displacement by the
    shading beside the edge is removed (distorted pixels), then the
    curvature bias of the edge detector
    (:func:`partinspect.vision.correspondences.deblurred`, ideal pixels);
    the correction's noise is the view's ``sigma_correction``, correlated
    along the edge over :func:`~partinspect.vision.rim_errors.correction_corr_length`, the share it takes
    from the points' own noise included as :func:`~partinspect.vision.rim_errors.coupled_noise` models it,
    and each point
    carries the Type B standard uncertainty :func:`~partinspect.vision.rim_errors.rim_type_b` of what
    remains, correlated along the edge over ``EDGE_BIAS_CORR_ANGLE`` times
    the ellipse's semi-major axis. Lines are used as found, each view
    carrying :func:`line_type_b` of its points' shading bounds as one
    offset along the whole line (``bias_corr_length`` None).

    ``correction_std``: the two features' :func:`correction_std`, if
    already computed (they depend on neither the calibration nor ``uv``).
    ``band``: where a broken edge's step lies across its band
    (:func:`~partinspect.vision.band_modes.edge_band`); along a line its
    Type B, px, is one offset for the whole view, added in quadrature to
    every point; round a rim its place is the modes of
    :func:`~partinspect.vision.band_modes.band_harmonics`, one coefficient
    each common to both views and one each view's own, sized by ``band``'s
    parallax share. A feature's
    ``band_modes`` (a broken rim moved onto its sharp edge's image) are the
    views' ``modes``.
    """
    P1, P2 = camera_matrices(calib)
    # The rim's curvature mode: one name for its two views, no other's (a
    # joint fit of several rims keeps their modes apart).
    curvature_name = ("curvature", next(_MODE_NAMES)) if fl.kind == "arc" else None
    band_name = next(_MODE_NAMES) if band is not None and fl.kind == "arc" else None
    if correction_std is None:
        correction_std = (correction_std_of(fl, corr_length), correction_std_of(fr, corr_length))
    views = []
    for f, P, K, D, pts, sigma_c in ((fl, P1, calib.K1, calib.D1, None if uv is None else uv[0], correction_std[0]),
                                     (fr, P2, calib.K2, calib.D2, None if uv is None else uv[1], correction_std[1])):
        arc = f.kind == "arc"
        offset = getattr(f, "background_offset", None) if arc else None
        sigma, bias, bias_length = f.ideal.normal_std, None, None
        if pts is None and not remap:
            xy = f.ideal.xy
            if offset is not None:
                xy = xy - BACKGROUND_CORRECTION * np.einsum("nij,nj->ni", f.ideal.jacobian, offset)
        else:
            pts = f.uv if pts is None else pts
            if offset is not None:
                pts = pts - BACKGROUND_CORRECTION * offset
            xy = to_ideal(pts, K, D)
        modes, names = getattr(f, "band_modes", None), getattr(f, "band_mode_names", None)
        if arc:
            curvature, normal = curvature_bias(xy, f.fit, f.blur)
            xy = xy + curvature[:, None] * normal
            # One unknown factor of the rim, shared by its two views.
            modes, names = _with_mode(modes, names, curvature_mode(curvature), curvature_name)
        if offset is not None:
            bias = rim_type_b(f.background_bound)
            bias_length = EDGE_BIAS_CORR_ANGLE * float(max(f.fit.params[2], f.fit.params[3]))
        elif not arc:
            shade = line_type_b(getattr(f, "background_bound", None), getattr(f, "band_shift", None))
            bias = np.full(len(xy), shade) if shade > 0 else None
        if band is not None and arc:
            harmonics = band_harmonics(xy, f.fit, band[len(views)])
            # What the cameras see alike moves the 3D rim (one coefficient of
            # both views); the parallax's share differs between them.
            common = np.sqrt(max(1.0 - band.parallax ** 2, 0.0))
            waves = range(len(harmonics))
            modes, names = _with_mode(modes, names, np.vstack([common * harmonics, band.parallax * harmonics]),
                                      [("band", band_name, j) for j in waves]
                                      + [("band", band_name, len(views), j) for j in waves])
        elif band is not None:
            b = band[len(views)]
            bias = np.full(len(xy), b) if bias is None else np.hypot(bias, b)
        views.append(View(xy, sigma, P, corr_length, bias, bias_length, sigma_c, correction_corr_length(corr_length),
                          modes, names))
    return views


_MODE_NAMES = count()


def _with_mode(modes, names, rows, name):
    """``View.modes`` and ``mode_names`` with more rows (k, N) and their names (one name, or a list of k)."""
    new = tuple(name) if isinstance(name, list) else (name,)
    if modes is None:
        return rows, new
    return np.vstack([modes, rows]), tuple(names) + new


def line_type_b(bound, band=None):
    """Type B standard uncertainty of a line's offset in one image from the shading beside it, px.

    Two readings of one displacement, in quadrature. ``LINE_BOUND_READING``
    times the median of its points' ``EdgePoints.background_bound``: the
    shading 3-4 px off the edge. The shading beside a straight edge runs
    along it, so every point is displaced alike: one offset for the whole
    line in that image (fully correlated along it), read from the points
    together. The median, not the mean: the few points near the line's
    ends, where another edge comes within the reading's reach, read that
    edge, not the shading; and beside uniform faces the bound is zero (the
    noise's expected part is taken out of each point's), so a clean line
    keeps none. And the magnitude of the median ``band``: a narrow band
    whose flank lies within the step's own response, which that reading
    misses (:func:`partinspect.vision.line_profile.line_band_shift`, zero
    beside uniform faces); where both see a shading each under-reads it
    (the band's model 75-90 % of it), so neither is left out.

    Parameters
    ----------
    bound : ndarray, shape (N,) or None
        ``EdgeFeature.background_bound`` of the line's points in one image,
        px.
    band : ndarray, shape (N,) or None
        ``EdgeFeature.band_shift`` of the same points, px.

    Returns
    -------
    float
        px; 0 without readings.

    References
    ----------
    .. [1] JCGM 100:2008 (GUM), 4.3 (Type B evaluation) and F.2.4.5
           (a known systematic effect left uncorrected).
    """
    shade = 0.0 if bound is None or len(bound) == 0 else LINE_BOUND_READING * float(np.median(bound))
    if band is None or len(band) == 0:
        return shade
    return float(np.hypot(shade, np.median(band)))


def views_of(fl, fr, corr_length, band=None):
    """:func:`feature_views` of a pair as a function of the calibration, ``views(calib, remap=False)``.

    What depends on neither the calibration nor the points (the
    correction's noise) is computed once, for
    :func:`partinspect.vision.calibration_uncertainty.calibration_responses`,
    which asks for the views under many calibrations.
    """
    stds = (correction_std_of(fl, corr_length), correction_std_of(fr, corr_length))

    def views(calib, remap=False):
        return feature_views(fl, fr, corr_length, calib, remap=remap, correction_std=stds, band=band)

    return views


def _initial_line(points):
    c = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - c, full_matrices=False)
    return c, vt[0]


def _initial_circle(points):
    c = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - c, full_matrices=False)
    n = vt[2]
    e1, e2 = vt[0], vt[1]
    q = np.c_[(points - c) @ e1, (points - c) @ e2]
    # Kasa's algebraic circle in the plane.
    A = np.c_[2 * q, np.ones(len(q))]
    sol, *_ = np.linalg.lstsq(A, (q * q).sum(1), rcond=None)
    r = np.sqrt(max(sol[2] + sol[0] ** 2 + sol[1] ** 2, 1e-12))
    return c + sol[0] * e1 + sol[1] * e2, n, r


def fit_feature(fl, fr, views, points, geo):
    """The two-view 3D fit of one matched pair, initialised from triangulated points.

    An arc (part of a rim) is fitted from a second start as well, and the
    fit with the smaller chi-square kept: the circle through the
    triangulated points of a short arc can be far off, and the two-view
    fit then stops in another minimum of its cost. The second start
    takes the centre and radius from the two images' ellipses as the
    matching compares them (:func:`partinspect.vision.matching.arc_circle`;
    ``geo`` the pair's EpipolarGeometry) and the normal from the points.
    """
    if fl.kind == "line":
        p0, d0 = _initial_line(points)
        return fit_line_3d(views, p0, d0)
    c0, n0, r0 = _initial_circle(points)
    fit = fit_circle_3d(views, c0, n0, r0)
    if fl.kind == "arc":
        center, radii, depths = arc_circle(geo, fl, fr)
        if min(depths) > 0 and min(radii) > 0:
            try:
                alt = fit_circle_3d(views, center, n0, float(np.mean(radii)))
            except (np.linalg.LinAlgError, ValueError):
                alt = None
            if alt is not None and np.isfinite(alt.chi2) and alt.chi2 < fit.chi2 * (1.0 - 1e-9):
                fit = alt
    return fit


# ------------------------------------------------------------------ the chain


def measure_stereo(left, right, calib, *, sigma=1.0, progress=None, match_options=None, edge_options=None,
                   segment_options=None, parallel=True, edge_break=None):
    """Measure the 3D lines and circles of a part from a calibrated stereo pair.

    Parameters
    ----------
    left, right : ndarray, shape (H, W) or (H, W, 3)
        The images as recorded (distorted), grey levels.
    calib : StereoCalibration
        With optional ``std`` (standard uncertainties of the intrinsics and
        extrinsics), which are then propagated into every 3D feature
        (:mod:`partinspect.vision.calibration_uncertainty`: numerical
        sensitivities, one Gauss-Newton step of the two-view fit per
        calibration parameter and sign).
    sigma : float
        Scale of the edge filter, px (the paper's sigma = 1 to start).
    progress : callable, optional
        ``progress(message)`` at each stage.
    match_options : dict, optional
        Keyword arguments of :func:`partinspect.vision.matching.match_features`.
    edge_options, segment_options : dict, optional
        Passed to :func:`measure_images` for both images.
    parallel : bool
        Measure the right image in a forked child process while this one
        measures the left, then about half of the matched pairs' 3D fits
        (by cost) in that same child
        (:func:`partinspect.vision.forked.forked`; made here where no child
        can run). The results are the same either way, bit for bit; False
        runs everything one after the other.
    edge_break : float, optional
        The part's edges are broken (rounded or chamfered): the RMS
        distance, mm, of the apparent step from the sharp edge. Each point
        of every feature then carries it as a Type B
        (:func:`~partinspect.vision.band_modes.edge_band`),
        and a pair of arcs either of which has both polarities is measured
        on one polarity's points (:func:`measure_pair_feature`).

    Returns
    -------
    StereoResult
    """
    say = progress or (lambda message: None)
    options = dict(sigma=sigma, edge_options=edge_options, segment_options=segment_options)
    say("edges and segments: left image")
    if not parallel:
        L = measure_images(left, calib.K1, calib.D1, **options)
        say("edges and segments: right image")
        R = measure_images(right, calib.K2, calib.D2, **options)
        geo, matching = _matched(L, R, calib, match_options, say)
        return _stereo_result(L, R, geo, matching, _measure_pairs(list(matching.matches), L, R, calib, geo,
                                                                  edge_break), calib, edge_break)
    # The two 2D chains are independent and mostly Python: a second
    # process, not a thread, runs one alongside the other. The compiled
    # fit kernel is loaded first, or each process would load it.
    from partinspect.vision._kernels import warm

    warm()
    with forked(measure_images, right, calib.K2, calib.D2, **options) as right_result:
        L = measure_images(left, calib.K1, calib.D1, **options)
        say("edges and segments: right image")
        R = right_result()
        geo, matching = _matched(L, R, calib, match_options, say)
        matches = list(matching.matches)
        if not right_result.forked or len(matches) < 2:
            fitted = _measure_pairs(matches, L, R, calib, geo, edge_break)
        else:
            # Independent fits, shared out between the two processes by
            # their cost; the child that measured the right image makes its
            # share with its own copy of it (no second process started).
            here, there = _halves([_fit_cost(L.features[m.left], R.features[m.right]) for m in matches])
            theirs = [matches[i] for i in there]
            second = right_result.then(_measure_pairs_right, theirs, [L.features[m.left] for m in theirs],
                                       calib, geo, L.edges.sigma, edge_break)
            fitted = list(matches)
            for i, f in zip(here, _measure_pairs([matches[i] for i in here], L, R, calib, geo, edge_break)):
                fitted[i] = f
            for i, f in zip(there, second()):
                fitted[i] = f
    return _stereo_result(L, R, geo, matching, fitted, calib, edge_break)


def _matched(L, R, calib, match_options, say):
    """The pair's epipolar geometry and its image features matched."""
    geo = epipolar_geometry(calib)
    say("matching")
    matching = match_features(L.features, R.features, geo, **(match_options or {}))
    say(f"3D fits of {len(matching.matches)} matched features")
    return geo, matching


def _stereo_result(L, R, geo, matching, fitted, calib, edge_break):
    matches = matching.matches
    feats = [f3 for f3, _ in fitted if f3 is not None]
    failed = [(m, why) for m, (f3, why) in zip(matches, fitted) if f3 is None]
    return StereoResult(L, R, geo, matching, tuple(feats), tuple(failed), bool(uncertainty_directions(calib)),
                        edge_break=edge_break)


def _fit_cost(fl, fr):
    """Relative CPU time of one pair's 3D fit, from its points.

    A rim's is dominated by the dense (n, n) products of its Type B
    evidence (:func:`~partinspect.vision.rim_errors.type_b_scale`) and grows as n^2; a line's, linearly.
    The constants follow profiles of the sample parts' pairs; only the
    ratios matter.
    """
    n = 0.5 * (len(fl.uv) + len(fr.uv))
    return 8.0 + (n / 70.0) ** 2 if fl.kind == "arc" else 1.5 + n / 200.0


def _halves(costs):
    """Indices of two shares of about equal total cost, each in increasing order.

    The longest-processing-time-first rule: the costliest remaining job
    goes to the share with the least so far (within 4/3 of the best split).

    References
    ----------
    .. [1] Graham, R. L. (1969). Bounds on multiprocessing timing
           anomalies. SIAM Journal on Applied Mathematics 17(2), 416-429.
    """
    shares, totals = ([], []), [0.0, 0.0]
    for i in sorted(range(len(costs)), key=lambda i: -costs[i]):
        k = int(totals[1] < totals[0])
        shares[k].append(i)
        totals[k] += costs[i]
    return sorted(shares[0]), sorted(shares[1])


def _measure_pairs(matches, L, R, calib, geo, edge_break):
    """`measure_pair_feature` of each match, in order: a list of (Feature3D or None, reason)."""
    return [measure_pair_feature(m, L.features[m.left], R.features[m.right], calib, geo, L.edges.sigma, edge_break)
            for m in matches]


def _measure_pairs_right(R, matches, lefts, calib, geo, corr_length, edge_break):
    """`_measure_pairs` given the right image's result and the matches' left features (``lefts``, in order)."""
    return [measure_pair_feature(m, fl, R.features[m.right], calib, geo, corr_length, edge_break)
            for m, fl in zip(matches, lefts)]


def measure_pair_feature(match, fl, fr, calib, geo, corr_length, edge_break=None):
    """The 3D feature of one matched pair of image features.

    Parameters
    ----------
    match : Match
        Its ``left`` and ``right`` are the indices the feature records.
    fl, fr : EdgeFeature
        The left and right image features.
    calib : StereoCalibration
    geo : EpipolarGeometry
    corr_length : float
        Correlation length of the edge points' noise along the edge, px
        (the edge filter's scale).
    edge_break : float or None
        See :func:`measure_stereo`.

    Returns
    -------
    feature : Feature3D or None
    reason : str or None
        Why there is no feature: too few corresponding points, two arcs
        that are not one circle, or a failed fit.
    """
    if edge_break is not None:
        # Across a broken rim the two polarities are two curves (one_polarity).
        try:
            pair = one_polarity(fl, fr, corr_length)
        except (np.linalg.LinAlgError, ValueError) as exc:
            return None, f"refit on one polarity failed: {exc}"
        if pair is None:
            return None, "the two images' arcs have too few points of one polarity (a broken rim's two steps)"
        fl, fr = pair
    corr = correspond(fl, fr, geo)
    if len(corr) < 6:
        return None, f"only {len(corr)} corresponding points"
    band = None if edge_break is None else edge_band(corr.points, geo, edge_break)
    try:
        # The pair's views as a function of the calibration: the
        # correction's noise, which depends on neither, is computed once.
        views_under = views_of(fl, fr, corr_length, band)
        views = views_under(calib)
        fit = fit_feature(fl, fr, views, corr.points, geo)
        if fl.kind == "arc":
            delta, p = _one_circle(fl, fr, views_under, calib, fit)
            if p < MISMATCH_P:
                # The test asks whether single points of both images lie on
                # one circle: judged again, before refusing the pair, with
                # the single points' Type B (the form's, form_view), which
                # the fit's averaged level understates for it.
                points_under = form_views_of(views_under, fl, fr)
                delta, p = _one_circle(fl, fr, points_under, calib,
                                       fit_feature(fl, fr, points_under(calib), corr.points, geo))
            if p < MISMATCH_P:
                hint = ("" if band is not None else "; a rounded or chamfered rim shows each camera its step at "
                        "a different place: if the part's edges are broken, state edge_break in the tolerance spec")
                return None, (f"the two images' arcs are not one circle: its fit's chi-square exceeds "
                              f"the two ellipses' by {delta:.0f} (p = {p:.1e}){hint}")
        # A broken edge's band moves the whole rim alike, which leaves no
        # residual: its stated level stands.
        scale, radius_scale = 1.0, 1.0
        if fl.kind == "arc" and band is None:
            at = circle_residuals_at(views, fit)  # the one Jacobian both factors read
            scale, radius_scale = type_b_scale(views, fit, at), radius_type_b_scale(views, fit, at)
        corr = corrected_correspondences(fl, fr, views, corr, geo, corr_length)
    except (np.linalg.LinAlgError, ValueError) as exc:
        return None, f"3D fit failed: {exc}"
    G = calibration_responses(fit, fl.kind, views_under, calib)
    # What the calibration's error does to the points themselves (it bends a
    # rim, not only moves it): the form's Monte Carlo draws it.
    P = point_responses(corr, calib) if G.shape[1] else None
    return make_feature3d(match, fl, fr, fit, corr, G, geo, _without_band(views[0], band, fl.kind), scale, P,
                          radius_scale), None


def _one_circle(fl, fr, views_under, calib, fit):
    """:func:`~partinspect.vision.fit3d.circle_consistency` of an arc pair's fit: (delta, p).

    Where the stated calibration makes the arcs inconsistent, they are
    asked again to be one circle seen through a calibration its stated
    uncertainty allows.
    """
    views = views_under(calib)
    starts = (fl.fit.params, fr.fit.params)
    delta, p = circle_consistency(views, fit, starts)
    if p < MISMATCH_P and uncertainty_directions(calib):
        r0, J, D, _ = residual_changes(fit, "arc", views_under, calib)
        delta, p = circle_consistency(views, fit, starts, (r0, J, D))
    return delta, p


def form_views_of(views_under, fl, fr):
    """``views_under`` (:func:`views_of`) with each view's Type B at the single points' level (:func:`~partinspect.vision.rim_errors.form_view`)."""
    def views(calib, remap=False):
        left, right = views_under(calib, remap=remap)
        return [form_view(left, fl), form_view(right, fr)]

    return views


def _without_band(view, band, kind=None):
    """The left view with a broken edge's band taken out of its Type B, for the form's point errors.

    Along a straight edge the step's place on the band is one offset, which
    moves no point relative to the others, and so is the shading beside it
    (:func:`line_type_b`): a line's view keeps no Type B. Around a rim the
    band's place (its modes, :func:`~partinspect.vision.band_modes.band_harmonics`)
    is the characteristic's own Type B (:mod:`partinspect.tolerances.edge_break`),
    not a point error to draw: its modes are dropped.
    """
    if kind == "line" and view.bias is not None:
        return replace(view, bias=None)
    if band is None or view.modes is None:
        return view
    keep = [j for j, name in enumerate(view.mode_names) if not (isinstance(name, tuple) and name[0] == "band")]
    if len(keep) == len(view.mode_names):
        return view
    return replace(view, modes=view.modes[keep] if keep else None,
                   mode_names=tuple(view.mode_names[j] for j in keep) if keep else None)
