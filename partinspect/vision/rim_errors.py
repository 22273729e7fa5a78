"""The error model of a rim's edge points: the shading correction, its noise and its Type B rest.

Before a rim's 3D fit (:func:`partinspect.vision.stereo.feature_views`)
the detector's curvature bias, an error of ours, is removed
(:func:`partinspect.vision.correspondences.deblurred`), and so is, as far
as it is known, the displacement by the shaded inner wall beside the rim,
which a real camera sees too (``BACKGROUND_CORRECTION`` times the
first-order shift read beside each point,
:func:`partinspect.vision.edges.background_gradients`, averaged along the
edge by :func:`smoothed_background`). As GUM asks for a recognised
systematic effect, the rest is a Type B standard uncertainty per point,
correlated along the rim over ``EDGE_BIAS_CORR_ANGLE`` (neighbouring points
are displaced alike): in the 3D fit, which weights and propagates it with
the random part into the centre, normal and radius, the shading's bound
read as a rectangular distribution's half-width with the detector's own
error in quadrature (:func:`rim_type_b`, JCGM 100 4.3.7; the latter not in
the radius, :func:`radius_type_b_scale`), and what the curvature
correction leaves as one mode of the whole rim (:func:`curvature_mode`);
in the form's
point errors, whose zone single points set, ``EDGE_BIAS_FACTOR`` times the
bound with ``EDGE_BIAS_FLOOR`` (:func:`form_view`). The correction's own
noise is random, correlated over :func:`correction_corr_length`, shares part
of the points' own noise (:func:`coupled_noise`), and is drawn by the Monte
Carlo (:mod:`partinspect.vision.montecarlo`); the Type B part is not. How
large that Type B really is depends on the optics and the surface, so the
level the rim's own fit residuals show of it, at its correlation length,
scales its share in the centre and normal (:func:`type_b_scale`,
:mod:`partinspect.vision.bias_evidence`).

Frames: points in pixels (distorted as detected, or ideal where said).

References
----------
.. [1] JCGM 100:2008, Guide to the expression of uncertainty in
       measurement, 4.3.7 (rectangular distribution) and 5.1.
.. [2] Devernay, F. (1995). A non-maxima suppression method for edge
       detection with sub-pixel accuracy. INRIA RR-2724.
"""

from dataclasses import replace

import numpy as np

from partinspect.vision.bias_evidence import bias_evidence
from partinspect.vision.edges import BACKGROUND_POSITION_COUPLING, EDGE_BIAS_FACTOR
from partinspect.vision.fit3d import circle_residuals_at, information_parts

__all__ = ["BACKGROUND_CORRECTION", "BACKGROUND_SMOOTHING", "EDGE_BIAS_CORR_ANGLE", "RIM_DETECTOR_ERROR",
           "RIM_BOUND_READING", "CURVATURE_REMAINDER", "EDGE_BIAS_FLOOR", "smoothed_background",
           "smoothing_operators", "coupled_noise", "rim_type_b", "curvature_mode", "type_b_scale",
           "radius_type_b_scale", "correction_std_of", "correction_corr_length", "form_view"]


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


EDGE_BIAS_CORR_ANGLE = 0.2
"""Correlation length of that remainder along the edge, rad of the ellipse
(times its semi-major axis gives px)."""


RIM_DETECTOR_ERROR = 0.005
"""px: the detector's own error on a rim point beside flat shading, which
no shading reading sees (points there lie 0.003-0.006 px off the true rim
on noiseless renders; the pixel's box and the bilinear samples are not the
Gaussian profile the detector assumes): the floor of a rim point's Type B
in its 3D fit (:func:`rim_type_b`), in quadrature. It weights the points
and reaches the centre and normal, but not the radius
(:func:`radius_type_b_scale`): the detector's share in the radius, an
error common to the whole rim, is the curvature correction's remainder
(``CURVATURE_REMAINDER``)."""


CURVATURE_REMAINDER = 0.09
"""Standard uncertainty of what the curvature correction
(:func:`partinspect.vision.correspondences.deblurred`) leaves on a rim, as
a fraction of the correction at each point. On exact discs (radii 15-80 px,
three sub-pixel positions, Gaussian, disc and digital-Gaussian blurs; no
noise; ``bench_psf_shape``) the remainder lies between -0.11 and +0.18 of
the correction; read as a rectangular distribution over that range
(JCGM 100 4.3.7), its second moment about zero is ``m^2 + a^2 / 3`` with
m = 0.035, a = 0.145: u = 0.09. It is one unknown factor for the whole
rim (the blur's shape), so it moves every point alike in proportion to its
correction: a shared mode of the rim's two views
(:func:`curvature_mode`), which goes to the radius, not a displacement
that averages out round the rim."""


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
point errors (``EDGE_BIAS_FACTOR`` times the bound, :func:`~partinspect.vision.feature3d.make_feature3d`)
and in the calibration check (:mod:`partinspect.vision.epipolar_drift`): a
form zone is set by single points' extremes, where these errors average out
along the rim less than the correlation says."""


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


def rim_type_b(bound):
    """Type B standard uncertainty of rim points in their 3D fit, px, from their shading bounds.

    ``RIM_BOUND_READING`` times the bound (what the shading correction may
    have left, read as a rectangular distribution over +-bound, JCGM 100
    4.3.7), with ``RIM_DETECTOR_ERROR`` in quadrature (the detector's own
    error beside flat shading). Correlated along the rim over
    ``EDGE_BIAS_CORR_ANGLE``, it sets the fit's weights and the systematic
    part of its centre, normal and radius (the radius without the floor,
    :func:`radius_type_b_scale`).

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


def curvature_mode(correction):
    """The displacement of a rim's points by one standard uncertainty of the curvature correction's remainder, px.

    Parameters
    ----------
    correction : ndarray, shape (N,)
        The curvature correction applied at each point, px
        (:func:`partinspect.vision.correspondences.curvature_bias`).

    Returns
    -------
    ndarray, shape (1, N)
        ``CURVATURE_REMAINDER`` times it: one row of ``View.modes``, the
        same unknown factor in both views of the rim.
    """
    return CURVATURE_REMAINDER * np.abs(np.asarray(correction, float))[None, :]


def type_b_scale(views, fit, at=None):
    """The factor on a rim's stated Type B standard uncertainties that its fit's residuals support.

    The centre and normal take it (:func:`~partinspect.vision.feature3d._image_param_cov`); the radius
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
    detector's own error.

    Parameters
    ----------
    views : sequence of View
        The fit's views, with the stated Type B.
    fit : Circle3D
    at : (ndarray, ndarray), optional
        :func:`~partinspect.vision.fit3d.circle_residuals_at` of the views
        and fit, if already computed.

    Returns
    -------
    float
    """
    r, J = circle_residuals_at(views, fit) if at is None else at
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
    # it only where their best guess itself lies above it. Residuals smaller
    # than the stated noise alone (an over-stated noise, a short rim) put the
    # bound below zero: no evidence of a systematic part, which leaves the
    # floor, never the square root of a negative number.
    upper = float(np.clip(upper, 0.0, max(1.0, k2)))
    stated = np.sqrt(np.mean(np.concatenate([np.square(v.bias) for v in biased])))
    return float(max(np.sqrt(upper), RIM_DETECTOR_ERROR / stated))


def radius_type_b_scale(views, fit, at=None):
    """The factor on a rim's radius's systematic standard uncertainty that leaves out the detector's floor.

    The fit's Type B per point is the shading's rest with
    ``RIM_DETECTOR_ERROR`` in quadrature (:func:`rim_type_b`), correlated
    over ``EDGE_BIAS_CORR_ANGLE``. Propagated so, the floor states the
    detector's own error as a displacement varying round the rim whose
    mean moves the radius; the detector's error common to the whole rim is
    the curvature correction's remainder, which the views carry as their
    shared mode (:func:`curvature_mode`). So the radius's systematic
    variance is taken with the floor moved out of the Type B (into the
    points' random part, which leaves their weights and the fit as they
    are): the ratio of the two sandwich variances, through the fit's own
    weighted Jacobian.

    Parameters
    ----------
    views : sequence of View
        The fit's views, with the Type B of :func:`rim_type_b` (a broken
        rim's band in it is not separated: such a rim's radius keeps the
        stated level, 1).
    fit : Circle3D
    at : (ndarray, ndarray), optional
        As :func:`type_b_scale`'s.

    Returns
    -------
    float
        The factor on the radius's row and column of the systematic
        covariance, at most 1.
    """
    if not any(v.bias is not None for v in views):
        return 1.0
    _, J = circle_residuals_at(views, fit) if at is None else at
    floor2 = RIM_DETECTOR_ERROR * RIM_DETECTOR_ERROR
    moved = [v if v.bias is None else
             replace(v, sigma=np.sqrt(np.square(v.sigma) + floor2),
                     bias=np.sqrt(np.maximum(np.square(v.bias) - floor2, 0.0)))
             for v in views]
    S, _, Mb = information_parts(views, J, random=False)
    _, _, Mb_rest = information_parts(moved, J, random=False)
    Sinv = np.linalg.inv(S)
    stated = float((Sinv @ Mb @ Sinv)[-1, -1])
    rest = float((Sinv @ Mb_rest @ Sinv)[-1, -1])
    return float(np.sqrt(min(rest / stated, 1.0))) if stated > 0 else 1.0


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


def form_view(view, f):
    """The view with the Type B the form's point errors draw.

    A rim's points carry ``EDGE_BIAS_FACTOR`` times their shading bound with
    ``EDGE_BIAS_FLOOR`` in quadrature there, the single points' spread of
    what the correction leaves, since a form zone is set by its points'
    extremes; the 3D fit's centre and radius, averages round the rim, take
    :func:`rim_type_b`. What the view carries beyond that (a broken edge's
    band, :func:`~partinspect.vision.band_modes.edge_band`) is kept. Lines, and arcs without shading
    readings, are returned as they are.
    """
    if view.bias is None or f.kind != "arc" or getattr(f, "background_bound", None) is None:
        return view
    bound = np.asarray(f.background_bound, float)
    other = np.maximum(np.square(view.bias) - np.square(rim_type_b(bound)), 0.0)
    return replace(view, bias=np.sqrt(np.square(np.hypot(EDGE_BIAS_FACTOR * bound, EDGE_BIAS_FLOOR)) + other))
