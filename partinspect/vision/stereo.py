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
uncorrelated), plus the Type B part of rims below; :class:`Feature3D`
keeps the three apart.

Rims of holes (circles and arcs). Before the 3D fit (:func:`feature_views`)
the detector's curvature bias, an error of ours, is removed
(:func:`partinspect.vision.correspondences.deblurred`), and so is, as far
as it is known, the displacement by the shaded inner wall beside the rim,
which a real camera sees too (``BACKGROUND_CORRECTION`` times the
first-order shift read beside each point,
:func:`partinspect.vision.edges.background_gradients`). As GUM asks for a
recognised systematic effect, the rest is a Type B standard uncertainty
per point, correlated along the rim over ``EDGE_BIAS_CORR_ANGLE``
(neighbouring points are displaced alike): in the 3D fit, which weights and
propagates it with the random part into the centre, normal and radius, the
shading's bound read as a rectangular distribution's half-width with the
detector's own error in quadrature (:func:`rim_type_b`, JCGM 100 4.3.7); in
the form's point errors, whose zone single points set, ``EDGE_BIAS_FACTOR``
times the bound with ``EDGE_BIAS_FLOOR`` (:func:`make_feature3d`). The correction's own
noise is random, correlated over :func:`correction_corr_length`, and drawn
by the Monte Carlo (:mod:`partinspect.vision.montecarlo`); the Type B part
is not. How large that Type B really is depends on the optics and the
surface, so the level the rim's own fit residuals show of it, at its
correlation length, scales its share in the centre and normal
(:func:`type_b_scale`, :mod:`partinspect.vision.bias_evidence`).

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

import cv2
import numpy as np

from partinspect.vision.contours import chain_edges, segment_contours
from partinspect.vision.correspondences import correspond, deblurred
from partinspect.vision.pointerrors import point_error_model, short_scale_ratio
from partinspect.vision.edges import (BACKGROUND_POSITION_COUPLING, EDGE_BIAS_FACTOR, background_shift_std,
                                      edge_points)
from partinspect.vision.fitting import ellipse_geometry, fit_ellipse, information_matrices
from partinspect.vision.forked import forked
from partinspect.frames import orthonormal_frame, plane_basis
from partinspect.vision.calibration_points import point_responses
from partinspect.vision.calibration_uncertainty import calibration_responses, residual_changes, uncertainty_directions
from partinspect.vision.bias_evidence import bias_evidence
from partinspect.vision.fit3d import (View, circle_consistency, circle_residuals_at, fit_circle_3d, fit_line_3d,
                                      minimal_residuals)
from partinspect.vision.ideal import camera_matrices, to_ideal
from partinspect.vision.line_profile import line_band_shift
from partinspect.vision.imagefeatures import MAX_OUTLIER_FRACTION, ImageFeature, chauvenet_z, image_features
from partinspect.vision.matching import arc_circle, epipolar_geometry, match_features
from partinspect.vision.noise import noise_level_function

__all__ = ["ImageResult", "EdgeFeature", "Feature3D", "StereoResult", "measure_stereo", "measure_images",
           "feature_views", "views_of", "rim_type_b", "line_type_b", "type_b_scale", "edge_band", "correction_std_of", "correction_corr_length", "smoothed_background", "smoothing_operators", "coupled_noise",
           "as_fitted", "random_covariance",
           "corrected_correspondences", "fit_feature", "make_feature3d", "measure_pair_feature"]

# Points of arcs: the corrections and the Type B component of the module
# notes, "Rims of holes".
BACKGROUND_CORRECTION = 1.4
"""Factor on ``EdgePoints.background_shift`` removed from the points of arcs.
The detector moves further than the first-order shift says, more so beside
a surface seen at grazing incidence (a background rising as the square root
of the distance) than beside a linear one; 1.4 centres what remains of the
rim points' displacement on zero."""
BACKGROUND_SMOOTHING = 2.0
"""px: the background displacement and bound of the points of an arc are
averaged along the edge with a Gaussian of this standard deviation (the
shading beside an edge changes over several pixels, the noise of each
reading over about one)."""
MISMATCH_P = 1e-6
"""A matched pair of arcs whose 3D circle fits both images worse than their
two ellipses by more than this chance allows
(:func:`partinspect.vision.fit3d.circle_consistency`) is not kept: they are
the rims of two different holes. True pairs' p-values run low (the Type B
displacements bend two free ellipses more easily than one circle), so only
a gross misfit, beyond 5 sigma, counts."""
EDGE_BIAS_CORR_ANGLE = 0.2
"""Correlation length of that remainder along the edge, rad of the ellipse
(times its semi-major axis gives px)."""
RIM_DETECTOR_ERROR = 0.005
"""px: the detector's and the curvature correction's own error on a rim
point beside flat shading, which no shading reading sees: the floor of a
rim point's Type B in its 3D fit (:func:`rim_type_b`), in quadrature, and
the least Type B a rim's residuals may size its centre's share down to
(:func:`type_b_scale`). It is set above what the curvature correction
leaves on exact discs under several blur shapes and what rim points beside
flat shading show on noiseless renders (docs/validation.md,
bench_psf_shape); without a floor the fit leans on those points as if they
were exact."""
RIM_BOUND_READING = 1.0 / np.sqrt(3.0)
"""Type B standard uncertainty of a rim point in its 3D fit per px of the
shading bound (:func:`rim_type_b`): the correction's remainder is taken to
lie anywhere within +-bound, no value likelier than another, a rectangular
distribution of half-width a with u = a / sqrt(3) (JCGM 100, 4.3.7). The
fit's centre and radius are averages of the remainders round the rim (the
radius their mean, the centre their first harmonic), which that reading
states; ``EDGE_BIAS_FACTOR`` (0.75) is the single points' spread the form
is judged with."""
EDGE_BIAS_FLOOR = 0.01
"""px: the floor, in quadrature, of a rim point's Type B in the form's
point errors (``EDGE_BIAS_FACTOR`` times the bound, :func:`make_feature3d`)
and in the calibration check (:mod:`partinspect.vision.epipolar_drift`): a
form zone is set by single points' extremes, where these errors average out
along the rim less than the correlation says. The 3D fit takes
``RIM_DETECTOR_ERROR``."""
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
class Feature3D:
    """A 3D line, circle or arc measured from a matched pair of image features.

    Attributes
    ----------
    kind : str
        "line", "circle" (edge points seen over at least 300 degrees) or "arc".
    left, right : int
        Indices of the image features (``StereoResult.left.features``...).
    point, direction : ndarray, shape (3,) or None
        Lines: a point (nearest the data's centroid) and unit direction.
    start, end : ndarray, shape (3,) or None
        Lines: the extent of the triangulated points projected on the line.
    center, normal : ndarray, shape (3,) or None
        Circles and arcs; the normal points towards the left camera.
    radius : float
        Circles and arcs, mm (NaN for lines).
    angle_start, angle_end : float
        Circles and arcs: angular extent of the edge points of either image
        (back-projected onto the fitted circle's plane), rad,
        counter-clockwise about ``normal`` from
        ``partinspect.frames.reference_direction(normal)``; 0 and 2 pi
        for a circle.
    covariance : ndarray, shape (3, 3)
        Covariance of ``center`` (circles) or ``point`` (lines), mm^2: all
        three parts below together.
    radius_std : float
        Standard uncertainty of the radius, mm (NaN for lines).
    axis_cov : ndarray, shape (3, 3)
        Covariance of ``normal`` or ``direction`` (unit vectors).
    param_cov : ndarray, shape (7, 7) or (6, 6)
        Covariance of (center, normal, radius) or (point, direction).
    param_cov_image, param_cov_calibration : ndarray
        Two parts of ``param_cov``: from the image noise on the edge points
        (what a Monte Carlo of image noise reproduces), and from the
        calibration's stated uncertainty (``G G^T`` of ``calibration_response``;
        zeros without one).
    fit : Line3D or Circle3D
        The two-view fit (its covariances are the image-noise and systematic
        parts).
    correspondences : Correspondences
        Triangulated points with their 3x3 covariances.
    param_cov_systematic : ndarray
        The third part of ``param_cov``: the Type B component of a rim's
        points (module notes, "Rims of holes") or of a line's offset in
        each image (module notes, "Lines").
    point_errors : PointErrorModel or None
        Draws of the errors of ``points`` with their correlations along the
        edge (:mod:`partinspect.vision.pointerrors`), for the form's Monte
        Carlo.
    guided : str or None
        The CAD edge this line was measured as by
        :func:`partinspect.vision.guided.guided_lines` (a stretch of longer
        image lines chosen by the edge's image under the registered pose);
        None for a pair the matching made.
    calibration_response : ndarray, shape (7, q) or (6, q), or None
        The parameters' first-order responses to the calibration's q
        principal directions of uncertainty
        (:func:`partinspect.vision.calibration_uncertainty.calibration_responses`):
        ``param_cov_calibration`` is ``G G^T``, and two features measured
        with one calibration have the cross-covariance ``G_a G_b^T``, for
        the calibration's error is one error shared by all of them.
    band_place : BandPlace or None
        A broken rim whose points were moved, each by its predicted place
        across the break, onto the sharp rim's image and fitted again
        (:func:`partinspect.vision.band_place.rims_at_sharp_edge`): the
        size measured is the wall's. None otherwise.
    """

    kind: str
    left: int
    right: int
    point: np.ndarray | None
    direction: np.ndarray | None
    start: np.ndarray | None
    end: np.ndarray | None
    center: np.ndarray | None
    normal: np.ndarray | None
    radius: float
    angle_start: float
    angle_end: float
    covariance: np.ndarray
    radius_std: float
    axis_cov: np.ndarray
    param_cov: np.ndarray
    param_cov_image: np.ndarray
    param_cov_calibration: np.ndarray
    fit: object
    correspondences: object
    param_cov_systematic: np.ndarray | None = None
    point_errors: object = None
    guided: str | None = None
    calibration_response: np.ndarray | None = None
    band_place: object = None

    @property
    def points(self):
        """The triangulated correspondences, shape (N, 3), rig frame, mm: what
        registration and the form characteristics evaluate."""
        return self.correspondences.points

    @property
    def point_covs(self):
        """Their 3x3 covariances, shape (N, 3, 3), mm^2: each point's whole
        standard uncertainty as the point errors model it.

        Where there is a ``point_errors`` model (every feature of
        :func:`measure_stereo`) these are its marginal covariances: for a
        rim's points the image noise, the noise of the background
        correction (with the share it takes from the point's own) and the
        Type B rest of the shading's displacement, with the right fit's part.
        The triangulation's own ``correspondences.cov`` carries the first
        and the last only, too little for a rim's points; for a line the
        two are the same.
        """
        if self.point_errors is not None:
            return self.point_errors.covariances()
        return self.correspondences.cov

    @property
    def params(self):
        """(center, normal, radius) or (point, direction) as one vector."""
        if self.kind == "line":
            return np.r_[self.point, self.direction]
        return np.r_[self.center, self.normal, self.radius]


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
    background_offset: np.ndarray | None = None
    background_bound: np.ndarray | None = None
    background_std: np.ndarray | None = None
    band_shift: np.ndarray | None = None
    band_modes: np.ndarray | None = None
    band_mode_names: tuple | None = None


def smoothed_background(xy, values, std, corr_length, length=BACKGROUND_SMOOTHING):
    """The background readings of an arc's points averaged along the edge, as the chain uses them.

    Parameters
    ----------
    xy : ndarray, shape (N, 2)
        The points of one edge (any order), px.
    values : ndarray, shape (N, k)
        Per point readings (the background shift as a 2-vector, its bound).
    std : ndarray, shape (N,)
        Standard deviation of each point's shift from image noise, px,
        correlated along the edge as the points' own,
        ``exp(-d^2 / (4 corr_length^2))`` (read through the edge filter).
    corr_length : float
        The edge filter's sigma, px.
    length : float
        Standard deviation of the Gaussian weights along the edge, px.

    Returns
    -------
    mean : ndarray, shape (N, k)
        The Gaussian means.
    mean_std : ndarray, shape (N,)
        Standard deviation of the means' shift from image noise, px
        (correlated along the edge over :func:`correction_corr_length`).
    """
    w, rho = smoothing_operators(xy, corr_length, length)
    return w @ values, _smoothed_std(w, rho, std)


def _smoothed_std(w, rho, std):
    """Standard deviation of ``w @ x`` for ``x`` of standard deviations ``std`` correlated as ``rho`` (N,)."""
    from scipy import sparse

    a = w @ sparse.diags(np.asarray(std, float))
    # var_i = sum_jk a_ij rho_jk a_ik, the row sums of (a rho) * a.
    var = np.asarray((a @ rho).multiply(a).sum(axis=1)).ravel()
    return np.sqrt(np.maximum(var, 0.0))


OPERATORS_KEPT = 64
"""How many edges' :func:`smoothing_operators` are kept for a second call."""
_operators = {}


def smoothing_operators(xy, corr_length, length):
    """Sparse (N, N): the row-normalised Gaussian weights along the edge and the noise's correlation.

    Kept for the last ``OPERATORS_KEPT`` edges by their points' bytes and
    the two lengths: a rim's image chain (:func:`smoothed_background`) and
    its pair's 3D fit (:func:`coupled_noise`) ask for the same ones, and
    building them is most of what either costs. The matrices returned are
    shared: not to be changed in place.
    """
    xy = np.ascontiguousarray(xy, float)
    key = (xy.shape, xy.tobytes(), float(corr_length), float(length))
    if key not in _operators:
        _operators[key] = _smoothing_operators(xy, corr_length, length)
        while len(_operators) > OPERATORS_KEPT:
            del _operators[next(iter(_operators))]  # the oldest
    return _operators[key]


def _smoothing_operators(xy, corr_length, length):
    # Imported here: these are all this module needs of them.
    from scipy import sparse
    from scipy.spatial import cKDTree

    n = len(xy)
    # Both kernels are below exp(-40) ~ 4e-18 of their peak beyond this
    # distance: only pairs within it are kept (sparse), which changes the
    # dense sums by less than rounding and makes the cost linear in N (at
    # a given point density) instead of the dense O(N^2) matrices and the
    # O(N^3) triple product.
    radius = np.sqrt(80.0) * max(length, np.sqrt(2.0) * corr_length)
    pairs = cKDTree(xy).query_pairs(radius, output_type="ndarray")
    i = np.concatenate([pairs[:, 0], pairs[:, 1], np.arange(n)])
    j = np.concatenate([pairs[:, 1], pairs[:, 0], np.arange(n)])
    diff = xy[i] - xy[j]
    d2 = diff[:, 0] * diff[:, 0] + diff[:, 1] * diff[:, 1]
    w = sparse.csr_matrix((np.exp(-d2 / (2.0 * length * length)), (i, j)), shape=(n, n))
    w = sparse.diags(1.0 / np.asarray(w.sum(axis=1)).ravel()) @ w
    rho = sparse.csr_matrix((np.exp(-d2 / (4.0 * corr_length * corr_length)), (i, j)), shape=(n, n))
    return w, rho


def coupled_noise(xy, sigma, background_std, corr_length, length=BACKGROUND_SMOOTHING):
    """Noise an arc's corrected points take from their correction, read from the same noise as their positions.

    A point's position error ``d`` (across the edge, correlated along it as
    ``exp(-dist^2 / (4 corr_length^2))``) moves its background reading by
    ``BACKGROUND_POSITION_COUPLING * d``
    (:data:`partinspect.vision.edges.BACKGROUND_POSITION_COUPLING`); the
    chain averages the readings along the edge (weights ``W``, as
    :func:`smoothed_background`) and removes ``BACKGROUND_CORRECTION``
    times the mean, so a corrected point's error is ``d - k (W d)`` (``k``
    the product of the two factors) plus the correction's independent
    rest. ``d - k (W d)`` is modelled as ``d`` plus an independent smooth
    part, correlated as the averaged correction
    (:func:`correction_corr_length`), whose variance makes the power at
    long wavelengths exact: there ``W d = d`` and the sum has ``(1 - k)^2``
    times the power of ``d``. That is what a fit over the whole edge
    (centre, radius) sees; a point alone sees a little less.

    Parameters
    ----------
    xy : ndarray, shape (N, 2)
        The points of one edge, px.
    sigma : ndarray, shape (N,)
        Standard deviation of each point's position across the edge, px.
    background_std : ndarray, shape (N,)
        Standard deviation of the averaged background shift from image
        noise, px (:func:`smoothed_background`'s ``mean_std``): the share
        from the positions and the rest together.
    corr_length, length : float
        As :func:`smoothed_background`.

    Returns
    -------
    smooth_std : ndarray, shape (N,)
        Standard deviation of the smooth part, px.
    rest_std : ndarray, shape (N,)
        Standard deviation of the averaged shift's noise independent of the
        positions, px (before ``BACKGROUND_CORRECTION``).
    weights : scipy.sparse matrix, shape (N, N)
        ``W``, for drawing ``W d``.
    """
    sigma = np.asarray(sigma, float) * np.ones(len(xy))
    w, rho = smoothing_operators(xy, corr_length, length)
    from_positions = BACKGROUND_POSITION_COUPLING * _smoothed_std(w, rho, sigma)
    rest = np.sqrt(np.maximum(np.asarray(background_std, float) ** 2 - from_positions ** 2, 0.0))
    k = BACKGROUND_CORRECTION * BACKGROUND_POSITION_COUPLING
    # Power at zero wavelength of a field correlated as exp(-d^2 / (4 l^2)): variance times l.
    share = ((1.0 - k) ** 2 - 1.0) * corr_length / float(np.hypot(corr_length, length))
    return sigma * np.sqrt(max(share, 0.0)), rest, w


def _with_edge_data(feature, edges, image):
    base = {f.name: getattr(feature, f.name) for f in fields(ImageFeature)}
    i = feature.index
    base.update(edge_normal=edges.normal[i], corr_length=float(edges.sigma))
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
    along the edge over :func:`correction_corr_length`, the share it takes
    from the points' own noise included as :func:`coupled_noise` models it,
    and each point
    carries the Type B standard uncertainty :func:`rim_type_b` of what
    remains, correlated along the edge over ``EDGE_BIAS_CORR_ANGLE`` times
    the ellipse's semi-major axis. Lines are used as found, each view
    carrying :func:`line_type_b` of its points' shading bounds as one
    offset along the whole line (``bias_corr_length`` None).

    ``correction_std``: the two features' :func:`correction_std`, if
    already computed (they depend on neither the calibration nor ``uv``).
    ``band``: per view, the Type B standard uncertainty, px, of where a
    broken edge's step lies across its band (:func:`edge_band`), added in
    quadrature to every point; along a line it is one offset for the whole
    view, along a rim correlated as the shading's rest. A feature's
    ``band_modes`` (a broken rim moved onto its sharp edge's image) are the
    views' ``modes``.
    """
    P1, P2 = camera_matrices(calib)
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
        if arc:
            xy = deblurred(xy, f.fit, f.blur)
        if offset is not None:
            bias = rim_type_b(f.background_bound)
            bias_length = EDGE_BIAS_CORR_ANGLE * float(max(f.fit.params[2], f.fit.params[3]))
        elif not arc:
            shade = line_type_b(getattr(f, "background_bound", None), getattr(f, "band_shift", None))
            bias = np.full(len(xy), shade) if shade > 0 else None
        if band is not None:
            b = band[len(views)]
            bias = np.full(len(xy), b) if bias is None else np.hypot(bias, b)
        views.append(View(xy, sigma, P, corr_length, bias, bias_length, sigma_c, correction_corr_length(corr_length),
                          getattr(f, "band_modes", None), getattr(f, "band_mode_names", None)))
    return views


def rim_type_b(bound):
    """Type B standard uncertainty of rim points in their 3D fit, px, from their shading bounds.

    ``RIM_BOUND_READING`` times the bound (what the shading correction may
    have left, read as a rectangular distribution over +-bound, JCGM 100
    4.3.7), with ``RIM_DETECTOR_ERROR`` in quadrature (the detector's own
    error on a curved edge). Correlated along the rim over
    ``EDGE_BIAS_CORR_ANGLE``, it sets the fit's weights and the systematic
    part of its centre, normal and radius.

    Parameters
    ----------
    bound : ndarray, shape (N,)
        ``EdgeFeature.background_bound`` of each point, px.

    Returns
    -------
    ndarray, shape (N,)
        px.

    References
    ----------
    .. [1] JCGM 100:2008 (GUM), 4.3.7 (a quantity known only to lie within
           bounds: rectangular distribution, u = a / sqrt(3)).
    """
    return np.hypot(RIM_BOUND_READING * np.asarray(bound, float), RIM_DETECTOR_ERROR)


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


def type_b_scale(views, fit):
    """The factor on a rim's stated Type B standard uncertainties that its fit's residuals support.

    The centre and normal take it (:func:`_image_param_cov`); the radius
    and the points' error model (the form) keep the stated level, since a
    displacement common to the whole rim leaves no residual.

    ``k^2`` of :func:`partinspect.vision.bias_evidence.bias_evidence` is
    the systematic displacement's observed over stated variance at its own
    correlation length. It is taken at its upper two-standard-error bound:
    its spread is the noise's (``se``) and the systematic part's own, a
    variance read over ``nu`` stretches of its correlation length
    (``2 k^4 / nu``). A smooth shading puts much of its displacement into
    the longest waves round the rim, which the fit takes up and the
    residuals do not show, so the level is stated at what the residuals
    allow, not at their best guess, and not above the stated level unless
    the best guess is; never below ``RIM_DETECTOR_ERROR`` per point, the
    detector's own error on a curved edge.

    Parameters
    ----------
    views : sequence of View
        The fit's views, with the stated Type B.
    fit : Circle3D

    Returns
    -------
    float
    """
    r, J = circle_residuals_at(views, fit)
    ev = bias_evidence(views, r, J)
    if ev is None:
        return 1.0
    k2, se = ev
    biased = [v for v in views if v.bias is not None]
    # The systematic part's own sampling spread: a variance read over nu
    # independent stretches of its correlation length (2 sqrt(pi) l each).
    nu = sum(len(v.xy) / (2.0 * np.sqrt(np.pi) * v.bias_corr_length) for v in biased)
    upper = k2 + 2.0 * np.sqrt(se * se + 2.0 * max(k2, 0.0) ** 2 / max(nu, 1.0))
    # Residuals too noisy to bound the level leave the stated one; they raise
    # it only where their best guess itself lies above it.
    upper = min(upper, max(1.0, k2))
    stated = np.sqrt(np.mean(np.concatenate([np.square(v.bias) for v in biased])))
    return float(max(np.sqrt(upper), RIM_DETECTOR_ERROR / stated))


def edge_band(points, geo, edge_break):
    """Per view, the standard uncertainty, px, of where a broken edge's step lies across its band.

    ``edge_break`` is the RMS distance, mm, of the apparent step from the
    sharp edge over the break's band and sizes; at the points' median depth
    in each camera it is ``edge_break * f / Z`` px. The two cameras see the
    step at different places on a rounded edge, so each view carries its own.

    Parameters
    ----------
    points : ndarray, shape (N, 3)
        The feature's triangulated points, rig frame, mm.
    geo : EpipolarGeometry
    edge_break : float

    Returns
    -------
    (float, float)
    """
    z_left = float(np.median(points[:, 2]))
    z_right = float(np.median(points @ np.asarray(geo.R)[2] + np.asarray(geo.T).ravel()[2]))
    return edge_break * geo.K1[0, 0] / z_left, edge_break * geo.K2[0, 0] / z_right


def correction_std_of(f, corr_length):
    """Standard deviation of the noise of an arc's corrected points, px (None where no correction is made).

    The correction and the point share noise (:func:`coupled_noise`): that
    share goes with the correction's smooth noise, the rest of which is
    its own.
    """
    if f.kind != "arc" or getattr(f, "background_offset", None) is None:
        return None
    smooth, rest, _ = coupled_noise(f.uv, f.ideal.normal_std, f.background_std, corr_length)
    return np.hypot(BACKGROUND_CORRECTION * rest, smooth)


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


def correction_corr_length(corr_length):
    """Correlation length along the edge of the noise of the background correction, px.

    The gradients beside the edge are read through the edge filter, so
    their noise is correlated as the points' own, ``exp(-d^2 / (4 l^2))``
    with l = ``corr_length``; the Gaussian average over
    ``BACKGROUND_SMOOTHING`` px along the edge (:func:`smoothed_background`)
    widens that to the same form with l^2 + ``BACKGROUND_SMOOTHING``^2.
    Taken as short as the image noise's, the correction's share of a rim's
    radius variance would be understated.
    """
    return float(np.hypot(corr_length or 0.0, BACKGROUND_SMOOTHING))


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


def _angular_extent(points, center, normal):
    x, y, _ = orthonormal_frame(normal)
    q = points - center
    ang = np.sort(np.mod(np.arctan2(q @ y, q @ x), 2 * np.pi))
    gaps = np.diff(np.r_[ang, ang[0] + 2 * np.pi])
    k = int(np.argmax(gaps))
    start = ang[(k + 1) % len(ang)]
    extent = 2 * np.pi - gaps[k]
    return float(start), float(start + extent), float(extent)


# ------------------------------------------------------------------ the chain


def _image_param_cov(fit, kind, type_b_scale=1.0):
    """The fit's covariance of (point, direction) or (center, normal, radius): (image noise, systematic).

    A circle's systematic part has its centre and normal rows and columns
    multiplied by ``type_b_scale`` (:func:`type_b_scale`): what the rim's
    residuals show of the Type B displacement's variation along the rim,
    which moves the centre and tilts the normal. The radius keeps the
    stated Type B: a displacement common to the whole rim moves only the
    radius and leaves no residual to judge it by.
    """
    if kind == "line":
        C = np.zeros((6, 6))
        C[:3, :3] = fit.covariance
        C[3:, 3:] = fit.direction_cov
        d0 = fit.direction
        e1, e2 = plane_basis(d0).T
        # Cross terms from the 4x4 minimal covariance (same basis as fit3d's to first order).
        E = np.stack([e1, e2], 1)
        C[:3, 3:] = E @ fit.param_cov[:2, 2:] @ E.T
        C[3:, :3] = C[:3, 3:].T
        # The systematic part: each view's one offset along the line (the
        # shading beside it, a broken edge's band; feature_views).
        if fit.param_cov_systematic is None or not np.any(fit.param_cov_systematic):
            return C, np.zeros((6, 6))
        Eb = np.zeros((6, 4))
        Eb[:3, :2], Eb[3:, 2:] = E, E
        S = Eb @ fit.param_cov_systematic @ Eb.T
        return C - S, S
    _, _, M = minimal_residuals(fit, kind, [])
    sys = np.zeros_like(fit.param_cov) if fit.param_cov_systematic is None else fit.param_cov_systematic
    img, sys = M @ (fit.param_cov - sys) @ M.T, M @ sys @ M.T
    d = np.r_[np.full(6, type_b_scale), 1.0]
    return img, sys * np.outer(d, d)


def _on_plane(xy, K, R, T, center, normal):
    """Ideal pixels (N, 2) of a camera ``x_cam = R @ X + T`` back-projected onto a plane, rig frame."""
    d = np.c_[xy, np.ones(len(xy))] @ np.linalg.inv(K).T @ R  # ray directions, rig frame
    o = -R.T @ T
    with np.errstate(divide="ignore", invalid="ignore"):
        s = ((center - o) @ normal) / (d @ normal)
    X = o + s[:, None] * d
    return X[np.isfinite(X).all(axis=1) & (s > 0)]


def corrected_correspondences(fl, fr, views, corr, geo, corr_length):
    """An arc's correspondences redone on its points as the 3D fit uses them (:func:`as_fitted`).

    Those are the triangulated points the form is judged on, the right
    ellipse's outlier screen judging each point by the form's point-level
    Type B (:func:`_form_view`). The 3D fit
    itself is started from the correspondences as found (``corr``): a
    start from the corrected ones can send a short arc to another local
    minimum. Lines, and arcs left with fewer than 6 corrected
    correspondences, keep ``corr``.
    """
    if fl.kind != "arc":
        return corr
    # The partner ellipse's outlier screen judges single points: by the
    # single points' Type B, as the form they are judged on (_form_view).
    new = correspond(fl, as_fitted(fr, _form_view(views[1], fr), corr_length), geo, xy=views[0].xy)
    return new if len(new) >= 6 else corr


def as_fitted(f, view, corr_length):
    """An arc with the points of its fit3d ``view`` (corrected as :func:`feature_views` does) and its ellipse refitted to them.

    The correspondences place each left point's partner on the right
    fitted ellipse: fitted to the points as found, a rim's shading bends
    that ellipse away from the corrected rim the 3D fit measures, and the
    triangulated points (whose zone is the circularity) with it. Lines
    are returned as they are (their points are not corrected).

    Each point is weighted by its whole standard uncertainty
    (``view.total_sigma``: noise, the correction's noise and the Type B
    rest), as the 3D fit weighs it. Where a second step lies within the
    background reading's reach (the far wall's shadow seen through a hole,
    a countersink's cone) the correction moves a stretch of the rim by
    tenths of a pixel, and its Type B bound says so; weighted by the image
    noise alone such a stretch bends the whole ellipse, and near the
    epipolar tangents a partner moved along the ellipse moves its 3D point
    tens of times as far (validation.md, "Rims' partner ellipse").

    Points farther from the refitted ellipse than Chauvenet's threshold
    times their whole standard uncertainty are left out of it, worst
    first and the ellipse refitted each time, at most
    ``MAX_OUTLIER_FRACTION`` of them; the feature keeps all its points
    (they still say where the right image sees the edge). Where a hole seen
    very obliquely has its rim fade at an ellipse's tip, the contour can run
    on there through points off the rim by more than their whole standard
    uncertainty; the image fit, which judges residuals by the image
    noise alone and scales its threshold by their spread, keeps them, and
    they bend the right ellipse on which every partner lies.

    Returns
    -------
    EdgeFeature
        Its ``fit.cov`` is the random part of the ellipse's covariance
        (:func:`random_covariance`), what the point errors' model
        (:mod:`partinspect.vision.pointerrors`) draws anew for every image.
    """
    if f.kind != "arc":
        return f
    total = np.asarray(view.total_sigma, float) * np.ones(len(view.xy))
    keep = np.arange(len(view.xy))
    budget = int(MAX_OUTLIER_FRACTION * len(keep))
    start = f.fit.params
    while True:
        fit = fit_ellipse(view.xy[keep], total[keep] ** 2, corr_length=corr_length, start=start)
        z = np.abs(fit.residuals) / total[keep]
        worst = int(np.argmax(z))
        if budget == 0 or z[worst] <= chauvenet_z(len(keep)):
            break
        keep = np.delete(keep, worst)
        budget -= 1
        start = fit.params
    cov = random_covariance(fit, view, keep)
    return replace(f, ideal=replace(f.ideal, xy=view.xy), fit=replace(fit, cov=cov))


def random_covariance(fit, view, keep):
    """The random part of the covariance of an ellipse fitted to ``view``'s points ``keep``, each weighted by its whole uncertainty.

    The fit is a weighted regression, weights ``1 / t^2`` with ``t`` the
    points' ``total_sigma``, whose random errors are the image noise
    (``view.sigma``, correlated along the edge over ``view.corr_length``)
    and the correction's noise (over ``view.correction_corr_length``),
    independent of each other: their part of the estimate's covariance is
    the sandwich ``S^-1 (H_w^T D R D H_w) S^-1`` summed over the two, with
    ``H_w`` the rows ``h_i / t_i``, ``S = H_w^T H_w`` and ``D`` the errors'
    standard uncertainties over ``t`` [1]_. The Type B rest is not in it:
    it is fixed for the scene, and the weights already keep it out of the
    ellipse as far as the other points allow.

    Parameters
    ----------
    fit : EllipseFit
        Of the points ``view.xy[keep]``, ideal px.
    view : View
    keep : ndarray of int
        The points the fit used.

    Returns
    -------
    ndarray, shape (5, 5)
        px^2, px rad, rad^2 as ``EllipseFit.cov``; a circle's free angle
        (``fit.cov`` infinite there) keeps its infinite variance.

    References
    ----------
    .. [1] JCGM 100:2008, 5.2 (correlated input quantities); the sandwich
           covariance of a weighted least-squares estimate.
    """
    n = len(view.xy)
    xy = view.xy[keep]
    t = (np.asarray(view.total_sigma, float) * np.ones(n))[keep]
    _, _, h = ellipse_geometry(xy, fit.params, fit.phases)
    hw = h / t[:, None]
    M = np.zeros((5, 5))
    for std, length in ((view.sigma, view.corr_length), (view.sigma_correction, view.correction_corr_length)):
        if std is not None:
            a = hw * ((np.asarray(std, float) * np.ones(n))[keep] / t)[:, None]
            M += information_matrices(a, np.ones(len(a)), xy, length)[1]
    Sinv = np.linalg.pinv(hw.T @ hw, rcond=1e-13, hermitian=True)
    cov = Sinv @ M @ Sinv
    cov = 0.5 * (cov + cov.T)
    if fit.cov is not None and not np.isfinite(fit.cov[4, 4]):
        # A circle: its axis angle is undetermined and moves no point.
        cov[4, :] = cov[:, 4] = 0.0
        cov[4, 4] = np.inf
    return cov


def _point_errors(fl, corr, view, calibration=None):
    """The :class:`~partinspect.vision.pointerrors.PointErrorModel` of a feature's triangulated points.

    The left points' random part (``view.sigma``, correlated over the edge
    filter's scale, and the background correction's noise over its own
    length) and the Type B rest of a rim's shading displacement
    (``view.bias``, over its own length), as the 3D fit models them. Where
    the residuals scatter significantly more from point to point than that
    noise predicts (:func:`~partinspect.vision.pointerrors.short_scale_ratio`
    above 1 by more than twice its standard error: on a very clean image the
    sub-pixel estimator's own ripple is as large as the noise), the random
    part is scaled up to what the residuals show: a Type A evaluation of the
    scatter the form is judged against. It is never scaled down: a ratio
    below 1 may hide structure longer than the differences see.
    ``calibration``: the points' responses to the calibration's uncertainty
    (:func:`~partinspect.vision.calibration_points.point_responses`), or None.
    """
    sigma = np.asarray(view.sigma, float) * np.ones(len(fl.ideal.xy))
    ratio, se = short_scale_ratio(fl.fit.residuals, sigma, fl.ideal.xy, view.corr_length)
    if ratio > 1.0 + 2.0 * se:
        sigma = sigma * np.sqrt(ratio)
    comps = [(sigma, view.corr_length)]
    if view.sigma_correction is not None:
        comps.append((view.sigma_correction, view.correction_corr_length))
    systematic = ()
    if view.bias is not None:
        systematic = (len(comps),)
        comps.append((view.bias, view.bias_corr_length))
    # The left feature's fit rejected its points beyond Chauvenet's threshold
    # (imagefeatures._make_features): the form's simulation cuts its tails there too.
    return point_error_model(corr, fl.ideal.normal, comps, systematic, chauvenet_z(len(fl.ideal.xy)), calibration,
                             fl.phase_factor)


def make_feature3d(match, fl, fr, fit, corr, cal_response, geo, view, type_b_scale=1.0, point_response=None):
    """The :class:`Feature3D` record of a matched pair's two-view fit.

    Parameters
    ----------
    match : Match
        Its ``left`` and ``right`` indices are recorded.
    fl, fr : EdgeFeature
        The left and right image features.
    fit : Line3D or Circle3D
        Their two-view fit.
    corr : Correspondences
        Their triangulated points (the form is judged on them).
    cal_response : ndarray, shape (6, q) or (7, q)
        The parameters' responses to the calibration's uncertainty
        (:func:`partinspect.vision.calibration_uncertainty.calibration_responses`;
        q = 0 without it).
    geo : EpipolarGeometry
    view : View
        The left view of the fit (:func:`feature_views`): the points'
        random and systematic parts for their error model.
    type_b_scale : float
        What a rim's residuals show of its stated Type B (:func:`type_b_scale`),
        applied to the centre and normal (:func:`_image_param_cov`).
    point_response : ndarray, shape (N, 3, q), optional
        The triangulated points' responses to the calibration's uncertainty
        (:func:`partinspect.vision.calibration_points.point_responses`), which
        the points' error model draws for the form; None: not drawn.

    Returns
    -------
    Feature3D
        The covariance is the fit's image-noise and systematic parts plus
        the calibration's ``G G^T``, each also kept apart. A circle or arc is a "circle"
        when the edge points of either image, back-projected onto its
        plane, cover at least 300 degrees of it.
    """
    kind = fl.kind
    img_cov, sys_cov = _image_param_cov(fit, kind, type_b_scale)
    G = np.asarray(cal_response, float)
    cal_cov = G @ G.T
    total = img_cov + cal_cov + sys_cov
    errors = _point_errors(fl, corr, _form_view(view, fl), point_response)
    if kind == "line":
        t = (corr.points - fit.point) @ fit.direction
        return Feature3D("line", match.left, match.right, fit.point, fit.direction,
                         fit.point + t.min() * fit.direction, fit.point + t.max() * fit.direction,
                         None, None, float("nan"), float("nan"), float("nan"),
                         total[:3, :3], float("nan"), total[3:, 3:], total, img_cov, cal_cov, fit, corr, sys_cov,
                         errors, calibration_response=G)
    # The fit used each image's own edge points, so the rim it measured is
    # what either image sees; the correspondences cover only what both do.
    pts = np.vstack([_on_plane(fl.ideal.xy, geo.K1, np.eye(3), np.zeros(3), fit.center, fit.normal),
                     _on_plane(fr.ideal.xy, geo.K2, geo.R, geo.T, fit.center, fit.normal)])
    a0, a1, extent = _angular_extent(pts, fit.center, fit.normal)
    kind3 = "circle" if extent >= np.deg2rad(300.0) else "arc"
    if kind3 == "circle":
        a0, a1 = 0.0, 2 * np.pi
    return Feature3D(kind3, match.left, match.right, None, None, None, None, fit.center, fit.normal,
                     float(fit.radius), a0, a1, total[:3, :3], float(np.sqrt(total[6, 6])), total[3:6, 3:6],
                     total, img_cov, cal_cov, fit, corr, sys_cov, errors, calibration_response=G)


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
        of every feature then carries it as a Type B (:func:`edge_band`).

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
    evidence (:func:`type_b_scale`) and grows as n^2; a line's, linearly.
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
                # the single points' Type B (the form's, _form_view), which
                # the fit's averaged level understates for it.
                points_under = _form_views_of(views_under, fl, fr)
                delta, p = _one_circle(fl, fr, points_under, calib,
                                       fit_feature(fl, fr, points_under(calib), corr.points, geo))
            if p < MISMATCH_P:
                hint = ("" if band is not None else "; a rounded or chamfered rim shows each camera its step at "
                        "a different place: if the part's edges are broken, state edge_break in the tolerance spec")
                return None, (f"the two images' arcs are not one circle: its fit's chi-square exceeds "
                              f"the two ellipses' by {delta:.0f} (p = {p:.1e}){hint}")
        # A broken edge's band moves the whole rim alike, which leaves no
        # residual: its stated level stands.
        scale = type_b_scale(views, fit) if fl.kind == "arc" and band is None else 1.0
        corr = corrected_correspondences(fl, fr, views, corr, geo, corr_length)
    except (np.linalg.LinAlgError, ValueError) as exc:
        return None, f"3D fit failed: {exc}"
    G = calibration_responses(fit, fl.kind, views_under, calib)
    # What the calibration's error does to the points themselves (it bends a
    # rim, not only moves it): the form's Monte Carlo draws it.
    P = point_responses(corr, calib) if G.shape[1] else None
    return make_feature3d(match, fl, fr, fit, corr, G, geo, _without_band(views[0], band, fl.kind), scale, P), None


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


def _form_views_of(views_under, fl, fr):
    """``views_under`` (:func:`views_of`) with each view's Type B at the single points' level (:func:`_form_view`)."""
    def views(calib, remap=False):
        left, right = views_under(calib, remap=remap)
        return [_form_view(left, fl), _form_view(right, fr)]

    return views


def _form_view(view, f):
    """The view with the Type B the form's point errors draw.

    A rim's points carry ``EDGE_BIAS_FACTOR`` times their shading bound with
    ``EDGE_BIAS_FLOOR`` in quadrature there, the single points' spread of
    what the correction leaves, since a form zone is set by its points'
    extremes; the 3D fit's centre and radius, averages round the rim, take
    :func:`rim_type_b`. What the view carries beyond that (a broken edge's
    band, :func:`edge_band`) is kept. Lines, and arcs without shading
    readings, are returned as they are.
    """
    if view.bias is None or f.kind != "arc" or getattr(f, "background_bound", None) is None:
        return view
    bound = np.asarray(f.background_bound, float)
    other = np.maximum(np.square(view.bias) - np.square(rim_type_b(bound)), 0.0)
    return replace(view, bias=np.sqrt(np.square(np.hypot(EDGE_BIAS_FACTOR * bound, EDGE_BIAS_FLOOR)) + other))


def _without_band(view, band, kind=None):
    """The left view with a broken edge's band taken out of its Type B, for the form's point errors.

    Along a straight edge the step's place on the band is one offset, which
    moves no point relative to the others, and so is the shading beside it
    (:func:`line_type_b`): a line's view keeps no Type B. Around a rim the
    band's variation is the characteristic's own Type B
    (:mod:`partinspect.tolerances.edge_break`), not a point error to draw.
    """
    if kind == "line" and view.bias is not None:
        return replace(view, bias=None)
    if band is None or view.bias is None:
        return view
    rest = np.sqrt(np.maximum(np.square(view.bias) - band[0] ** 2, 0.0))
    return replace(view, bias=rest if np.any(rest > 0) else None)
