"""Sub-pixel edge points with a covariance for each, from one grey image.

Canny's detector with Gaussian-derivative gradients, thresholds derived from
the measured image noise, and Devernay's sub-pixel localisation -- here with
the quadratic fitted to the *logarithm* of the gradient magnitude, which is
exact for a straight edge blurred by a Gaussian (its gradient profile is a
Gaussian) and so removes the interpolation bias of the plain quadratic.
Each point's position covariance is the first-order propagation of the
image noise through that estimator, using the exact noise covariance of the
filtered gradient between the samples it reads.

Every point also records how the grey-level gradients *beside* the edge
(a shaded surface next to it, e.g. the inner wall of a hole at its rim)
displace it (:func:`background_gradients`); the points themselves are left
as found, and the 3D fit of circles uses these numbers
(:mod:`partinspect.vision.stereo`, "Rims of holes"). On a curved edge the
detector is biased towards the centre of curvature by the smoothing and by
the sampling (``CURVATURE_SAMPLING_BIAS``), removed by
:func:`partinspect.vision.correspondences.deblurred`.

Everything is on the original (distorted) image; pixel coordinates follow
OpenCV: the centre of the top-left pixel is (0, 0), x right, y down.

References
----------
.. [1] Canny, J. (1986). A computational approach to edge detection. IEEE
       TPAMI 8(6), 679-698.
.. [2] Devernay, F. (1995). A non-maxima suppression method for edge
       detection with sub-pixel accuracy. INRIA RR-2724.
.. [3] Paper of this project, section 3: edge detection with first
       derivatives of a Gaussian, sigma = 1 to start, thresholds set
       automatically from the image.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from partinspect.vision.noise import QUANTISATION_STD, estimate_noise

__all__ = [
    "EdgePoints",
    "edge_points",
    "gaussian_derivative_kernels",
    "gradient",
    "gradient_noise_std",
    "edge_error_correlation",
    "background_shift_std",
    "noise_scale_map",
]

# Variance of a point's position along the edge, px^2. The along-edge
# position is only where the sampling grid happened to put the point and
# carries no information; a tiny value keeps the 2x2 matrix invertible.
ALONG_EDGE_VARIANCE = 1e-6
# Sub-pixel localisation on a curved edge: besides the smoothing bias
# width^2 kappa / 2 (continuous theory), the three samples read 1 px apart
# along a pixel axis see the curve recede on both sides, which moves the
# found point a further CURVATURE_SAMPLING_BIAS sin^2(2 phi) kappa towards
# the centre of curvature (phi: angle between the normal and the nearest
# pixel axis; kappa in 1/px; the coefficient in px^2). Fitted on exact
# discs; it does not depend on the radius, the blur or the polarity.
CURVATURE_SAMPLING_BIAS = 0.135
# Distances from an edge point, px, at which the background gradient beside
# the edge is read (background_gradients): beyond 2.5 W (W ~ 1.2 px for
# sigma 1 and an optical blur of 0.6 px) the step's own response is a few
# per cent of its peak and is subtracted.
BACKGROUND_DISTANCES = (3.0, 3.5, 4.0)
# Mean squared magnitude of the image-noise part of one side's background
# gradient (the mean over BACKGROUND_DISTANCES), per grad_noise^2, read on
# white noise (the same for every direction of the normal). Half of it is
# the variance of the component along any one direction.
BACKGROUND_NOISE = 1.28
BACKGROUND_POSITION_COUPLING = -0.14
"""px of ``EdgePoints.background_shift`` per px of the point's own position
error along its normal, both from the same image noise: the readings beside
the edge are taken from the point as found and the step's own response
subtracted there, so a point found too far towards the bright side reads
a background shift towards the dark side. Read on white noise, the same at
every contrast, and correlated between points along the edge as the
points' own errors; the rest of the shift's noise is independent of the
position's."""
EDGE_BIAS_FACTOR = 0.75
"""Standard uncertainty of what remains of a point's displacement by the
shading beside it after the correction, in units of its (averaged)
``EdgePoints.background_bound``: about two thirds of the remaining
displacements lie within it, as within a standard uncertainty. The Type B
of rim points in the 3D fits (:mod:`partinspect.vision.stereo`, the bound
averaged along the edge) and, with the bound as read at each point, in the
segmentation's test of the whole of a closed contour and of two arcs
together (:mod:`partinspect.vision.contours`)."""
# px: wider profiles are not step edges (a plateau of the gradient magnitude
# on a shading ramp steeper than the thresholds); optical blur of a usable
# image keeps step edges well below it.
MAX_STEP_WIDTH = 3.0


@dataclass(frozen=True)
class EdgePoints:
    """Sub-pixel edge points of one image.

    Attributes
    ----------
    xy : ndarray, shape (N, 2), float64
        Positions, px, OpenCV pixel frame of the (distorted) image.
    normal : ndarray, shape (N, 2)
        Unit gradient direction (dark to bright) at each point.
    strength : ndarray, shape (N,)
        Gradient magnitude at the point's pixel, grey levels / px.
    cov : ndarray, shape (N, 2, 2)
        Covariance of each position, px^2: ``var_n n n^T + var_t t t^T``
        with var_n the first-order variance along the normal and
        var_t = ALONG_EDGE_VARIANCE.
    pixel : ndarray, shape (N, 2), int32
        (row, col) of the pixel each point was found at; no two points
        share a pixel, which is what chaining indexes by.
    shape : tuple of int
        (H, W) of the image.
    width : ndarray, shape (N,)
        Standard deviation of the Gaussian that the gradient profile across
        the edge is, px: sqrt(sigma^2 + optical blur^2 + pixel), measured from
        the curvature of the log-magnitude (noisy per point; take a median).
        Smoothing displaces curved edges towards their centre of curvature
        by width^2 kappa / 2, which the ellipse and circle fits can remove.
    sigma : float
        Scale of the Gaussian derivative filter, px. Position errors of
        points on the same edge are correlated over this length, see
        :func:`edge_error_correlation`.
    noise : float
        Standard deviation of the image noise used, grey levels.
    grad_noise : float
        Standard deviation of each gradient component due to that noise,
        grey levels / px.
    background_shift : ndarray, shape (N,) or None
        First-order displacement of each point along its normal, px, caused
        by the grey-level gradients *beside* the edge (a shaded surface on
        one side, e.g. the visible inner wall of a hole), see
        :func:`background_gradients`. Not applied to ``xy``.
    background_bound : ndarray, shape (N,) or None
        ``width^2 |g_b - g_d| / h``, px, from the difference of the
        background gradient vectors on the two sides: a scale for what the
        first-order ``background_shift`` may miss (points beside a shaded
        surface), see :func:`background_gradients`.
    noise_scale : ndarray, shape (N,) or None
        The image noise's standard deviation at each point over ``noise``,
        where it depends on the grey level (photon noise, pixel response
        non-uniformity; :func:`partinspect.vision.noise.noise_level_function`);
        None where it is the same everywhere. ``cov`` includes it.
    """

    xy: np.ndarray
    normal: np.ndarray
    strength: np.ndarray
    cov: np.ndarray
    pixel: np.ndarray
    width: np.ndarray
    shape: tuple
    sigma: float
    noise: float
    grad_noise: float
    background_shift: np.ndarray | None = None
    background_bound: np.ndarray | None = None
    noise_scale: np.ndarray | None = None

    def __len__(self):
        return len(self.xy)

    @property
    def normal_std(self):
        """Standard uncertainty of each position along its normal, px, shape (N,)."""
        return np.sqrt(np.einsum("ni,nij,nj->n", self.normal, self.cov, self.normal))

    def take(self, index):
        """The subset of points selected by an index array or boolean mask."""
        opt = [None if a is None else a[index] for a in (self.background_shift, self.background_bound,
                                                           self.noise_scale)]
        return EdgePoints(self.xy[index], self.normal[index], self.strength[index], self.cov[index],
                          self.pixel[index], self.width[index], self.shape, self.sigma, self.noise,
                          self.grad_noise, *opt)


def gaussian_derivative_kernels(sigma):
    """Sampled 1-D Gaussian and Gaussian-derivative correlation kernels.

    Returns
    -------
    g, d : ndarray, shape (2R+1,), R = ceil(4 sigma)
        ``g`` sums to 1; ``d`` is odd and scaled so that correlating it with
        the ramp I(x) = x gives exactly 1 (a unit-gain derivative).
    """
    if sigma <= 0:
        raise ValueError("sigma must be positive")
    R = int(np.ceil(4.0 * sigma))
    k = np.arange(-R, R + 1, dtype=float)
    g = np.exp(-0.5 * (k / sigma) ** 2)
    g /= g.sum()
    d = k * g
    d /= (k * d).sum()
    return g, d


def gradient(image, sigma=1.0):
    """Gaussian-derivative gradient (gx, gy), float32, grey levels / px."""
    g, d = gaussian_derivative_kernels(sigma)
    f = np.asarray(image, np.float32)
    gx = cv2.sepFilter2D(f, cv2.CV_32F, d.astype(np.float32), g.astype(np.float32),
                         borderType=cv2.BORDER_REFLECT)
    gy = cv2.sepFilter2D(f, cv2.CV_32F, g.astype(np.float32), d.astype(np.float32),
                         borderType=cv2.BORDER_REFLECT)
    return gx, gy


def gradient_noise_std(noise, sigma=1.0):
    """Standard deviation of each gradient component for white image noise.

    For the separable filter g(y) d(x) the response to white noise of
    standard deviation s has variance s^2 sum(d^2) sum(g^2). With continuous
    kernels sum(g^2) = 1 / (2 sqrt(pi) sigma) and sum(d^2) =
    1 / (4 sqrt(pi) sigma^3), so the std is s / (2 sqrt(2 pi) sigma^2); the
    sampled kernels are used here, which differ from that by < 1 % for
    sigma >= 0.8.
    """
    g, d = gaussian_derivative_kernels(sigma)
    return float(noise * np.sqrt((d * d).sum() * (g * g).sum()))


def _lag_covariances(sigma, max_lag=2):
    """Noise covariance of the along-axis gradient component at lags 0..max_lag.

    For samples displaced by k pixels along x, the x components have
    covariance sum_j g_j^2 * sum_i d_i d_{i+k} (times the noise variance),
    the y components sum_j d_j^2 * sum_i g_i g_{i+k}, and the cross terms
    vanish (sum g d = 0 by symmetry). Returned per unit noise variance as
    (along, across): along = component along the displacement axis.
    """
    g, d = gaussian_derivative_kernels(sigma)

    def acorr(u, k):
        return float((u[: len(u) - k] * u[k:]).sum()) if k else float((u * u).sum())

    gg, dd = acorr(g, 0), acorr(d, 0)
    along = np.array([gg * acorr(d, k) for k in range(max_lag + 1)])
    across = np.array([dd * acorr(g, k) for k in range(max_lag + 1)])
    return along, across


def edge_error_correlation(distance, sigma=1.0):
    """Correlation of the normal position errors of two points on one edge.

    Both points read gradients smoothed along the edge by the Gaussian of
    scale sigma, so their errors share noise: for a straight edge the
    correlation is the normalised autocorrelation of that Gaussian,
    exp(-distance^2 / (4 sigma^2)).

    Parameters
    ----------
    distance : array_like
        Distance between the points along the edge, px.
    sigma : float
        Scale of the edge filter, px.
    """
    distance = np.asarray(distance, float)
    return np.exp(-(distance ** 2) / (4.0 * sigma * sigma))


def _subpixel_offset(a, b, c):
    """Offset of the maximum from the three magnitudes a, b, c at -1, 0, +1.

    The vertex of the parabola through the logarithms of the magnitudes:
    exact for a Gaussian profile, and the magnitude of a blurred edge read
    along any line across it is close to one, so for a camera's blur its
    systematic error is a small fraction of the plain parabola's through
    (a, b, c). It grows as the PSF narrows, where the pixel's square makes
    the profile flat-topped; ``benchmarks/bench_subpixel.py`` measures it.

    Returns
    -------
    off : ndarray, shape (N,)
        Offset along the axis, px, within [-1/2, 1/2].
    J : ndarray, shape (N, 3)
        d(off)/d(a, b, c).
    """
    la, lb, lc = np.log(a), np.log(b), np.log(c)
    Dl = la - 2.0 * lb + lc  # < 0 at a strict maximum
    off = (la - lc) / (2.0 * Dl)
    J = np.column_stack([(lc - lb) / a, (la - lc) / b, (lb - la) / c]) / (Dl * Dl)[:, None]
    return off, J


def _magnitude_covariance(n_ax, sigma):
    """Noise covariance of the three magnitudes per unit noise variance, (s0, s1, s2) per point, shape (N, 3).

    The magnitude noise is n . delta_g, and for lag k along the axis the
    gradient components along / across the axis have covariances
    along[k] / across[k]; S = [[s0, s1, s2], [s1, s0, s1], [s2, s1, s0]].
    """
    n_ax2 = n_ax * n_ax
    along, across = _lag_covariances(sigma, 2)
    return np.stack([n_ax2 * along[k] + (1.0 - n_ax2) * across[k] for k in range(3)], axis=1)


def _normal_variance(J, n_ax, sigma):
    """Variance across the edge of a point found with offset Jacobian J, per unit image-noise variance, px^2."""
    s = _magnitude_covariance(n_ax, sigma)
    var_off = (J[:, 0] ** 2 + J[:, 1] ** 2 + J[:, 2] ** 2) * s[:, 0] \
        + 2.0 * (J[:, 0] * J[:, 1] + J[:, 1] * J[:, 2]) * s[:, 1] \
        + 2.0 * J[:, 0] * J[:, 2] * s[:, 2]
    return var_off * n_ax * n_ax


def stated_std_spread(magnitudes, n_ax, sigma, noise):
    """Relative standard deviation, from image noise, of the uncertainty a point is given.

    :func:`edge_points` states each point's standard uncertainty from the
    three gradient magnitudes it read, which carry noise: the stated value
    scatters from point to point, and a point whose noise flattened its
    profile both moves further and is stated more uncertain. First-order
    propagation of the magnitudes' noise into the logarithm of the stated
    standard uncertainty.

    Parameters
    ----------
    magnitudes : ndarray, shape (N, 3)
        Noise-free gradient magnitudes at the three samples (-1, 0, +1
        along the axis), grey levels / px.
    n_ax : ndarray, shape (N,)
        |n . e|, the normal's component along that axis.
    sigma, noise : float
        Edge filter scale, px; image noise, grey levels.

    Returns
    -------
    cv : ndarray, shape (N,)
        Standard deviation of log(stated standard uncertainty).
    std : ndarray, shape (N,)
        The stated standard uncertainty for noise-free magnitudes, px.
    """
    m = np.asarray(magnitudes, float)
    n_ax = np.asarray(n_ax, float)

    def log_std(mm):
        _, J = _subpixel_offset(*mm.T)
        return 0.5 * np.log(_normal_variance(J, n_ax, sigma))

    f0 = log_std(m)
    g = np.empty_like(m)
    for j in range(3):
        mm = m.copy()
        step = 1e-5 * m[:, j]
        mm[:, j] += step
        g[:, j] = (log_std(mm) - f0) / step
    s = _magnitude_covariance(n_ax, sigma)
    var = sum(g[:, i] * g[:, j] * s[:, abs(i - j)] for i in range(3) for j in range(3))
    return noise * np.sqrt(var), noise * np.exp(f0)


def _bilinear(img, x, y):
    """Bilinear samples of ``img`` at (x, y), px (OpenCV pixel frame, clamped at the borders)."""
    H, W = img.shape
    x = np.clip(x, 0.0, W - 1.000001)
    y = np.clip(y, 0.0, H - 1.000001)
    x0, y0 = np.floor(x).astype(np.intp), np.floor(y).astype(np.intp)
    fx, fy = x - x0, y - y0
    a, b = img[y0, x0], img[y0, x0 + 1]
    c, d = img[y0 + 1, x0], img[y0 + 1, x0 + 1]
    return (1 - fy) * ((1 - fx) * a + fx * b) + fy * ((1 - fx) * c + fx * d)


def background_gradients(gx, gy, xy, normal, strength, width, grad_noise=0.0, distances=BACKGROUND_DISTANCES):
    """How the grey-level gradients beside each edge point displace it.

    The edge point is the maximum of the smoothed gradient across the edge.
    For a step of height h whose profile (total Gaussian width W: filter,
    optics, pixel) has a background of slope s_b on its bright side and
    s_d on its dark side (along the normal n, dark to bright), the maximum
    moves by ``W^2 (s_b - s_d) / h`` along n to first order; a background
    that is the same linear ramp on both sides moves nothing. The
    background gradients g_b, g_d are read from the filtered gradient at
    ``distances`` px on either side (where the step's own response,
    ``m exp(-d^2 / (2 W^2))`` along n, is subtracted) and averaged over
    those distances.

    Parameters
    ----------
    gx, gy : ndarray, shape (H, W)
        The filtered gradient of the image.
    xy, normal : ndarray, shape (N, 2)
        Edge points, px, and their unit normals (dark to bright).
    strength, width : ndarray, shape (N,)
        Gradient magnitude at each point and the per-point profile widths
        (their median over the points narrower than ``MAX_STEP_WIDTH`` is
        used: the width is noisy per point).
    grad_noise : float
        Standard deviation of each gradient component from image noise,
        grey levels / px (:func:`gradient_noise_std`).
    distances : sequence of float
        Where the background is read, px from the point.

    Returns
    -------
    shift : ndarray, shape (N,)
        First-order displacement along the normal, ``W^2 n.(g_b - g_d) / h``,
        px. Its standard deviation from image noise is
        ``W^2 sqrt(BACKGROUND_NOISE) grad_noise / h``.
    bound : ndarray, shape (N,)
        ``W^2 |g_b - g_d| / h``, px, less the image noise's expected part
        in quadrature: the order of what the linear model misses (a slope
        steepening towards the edge, as on a surface seen near grazing
        incidence; a gradient along the edge). A background common to both
        sides (one shaded face, the step's own tail) does not count.
    """
    n = len(xy)
    if n == 0:
        return np.zeros(0), np.zeros(0)
    W = _step_width(width)
    h = strength * W * np.sqrt(2.0 * np.pi)  # step height, grey levels
    side = []
    for sign in (1.0, -1.0):
        g = np.zeros((n, 2))
        for d in distances:
            p = xy + sign * d * normal
            tail = strength * np.exp(-d * d / (2.0 * W * W))
            g[:, 0] += _bilinear(gx, p[:, 0], p[:, 1]) - tail * normal[:, 0]
            g[:, 1] += _bilinear(gy, p[:, 0], p[:, 1]) - tail * normal[:, 1]
        side.append(g / len(distances))
    diff = side[0] - side[1]
    shift = W * W * np.einsum("ni,ni->n", diff, normal) / h
    mag2 = np.maximum((diff * diff).sum(axis=1) - 2.0 * BACKGROUND_NOISE * grad_noise ** 2, 0.0)
    bound = W * W * np.sqrt(mag2) / h
    return shift, bound


def _step_width(width):
    """Profile width of the step edges among points, px: the median of ``width`` below ``MAX_STEP_WIDTH``.

    Points on a plateau of the gradient magnitude (a shading ramp above the
    thresholds) have no step width; 1 when no point has one.
    """
    steps = width < MAX_STEP_WIDTH
    return float(np.median(width[steps])) if steps.any() else 1.0


def background_shift_std(edges, index):
    """Standard deviation from image noise of ``EdgePoints.background_shift``, px.

    ``W^2 sqrt(BACKGROUND_NOISE) grad_noise / h`` with the step width W and
    the step height h that :func:`background_gradients` used.

    Parameters
    ----------
    edges : EdgePoints
    index : array_like
        The points wanted (indices or mask).

    Returns
    -------
    ndarray, shape (len(index),)
    """
    W = _step_width(edges.width)
    grad_noise = edges.grad_noise if edges.noise_scale is None else edges.grad_noise * edges.noise_scale[index]
    return W * np.sqrt(BACKGROUND_NOISE) * grad_noise / (edges.strength[index] * np.sqrt(2.0 * np.pi))


def noise_scale_map(image, noise_level, sigma=1.0):
    """The image noise's standard deviation at every pixel, relative to ``noise_level.noise``.

    A point's position (and a pixel's gradient) is read through the
    derivative filter from both sides of the step, whose weights are
    symmetric about it, so its noise variance is the filter-weighted mean
    of the pixels' variances; with a variance linear in the grey level and
    the square of it (photon noise, PRNU), that is the variance function at
    the local means of ``I`` and ``I^2`` over the filter's Gaussian
    footprint.

    Parameters
    ----------
    image : ndarray, shape (H, W)
    noise_level : NoiseLevel
    sigma : float
        The edge filter's scale, px.

    Returns
    -------
    ndarray, shape (H, W) or None
        None where the noise does not depend on the grey level.
    """
    if not noise_level.signal_dependent:
        return None
    f = np.asarray(image, np.float64)
    m1 = cv2.GaussianBlur(f, (0, 0), sigma)
    m2 = cv2.GaussianBlur(f * f, (0, 0), sigma)
    var = noise_level.b + noise_level.a * m1 + noise_level.c * m2
    return np.sqrt(np.maximum(var, QUANTISATION_STD ** 2)) / noise_level.noise


def edge_points(image, sigma=1.0, noise=None, low=None, high=None, *, k_low=4.0, k_high=8.0, noise_level=None):
    """Sub-pixel edge points with position covariances.

    Parameters
    ----------
    image : ndarray, shape (H, W) or (H, W, 3)
        Grey (or colour, converted) image, any dtype; not resampled.
    sigma : float
        Scale of the Gaussian derivative filter, px (the paper starts at 1).
    noise : float, optional
        Standard deviation of the image noise, grey levels; estimated with
        :func:`partinspect.vision.noise.estimate_noise` when None.
    low, high : float, optional
        Hysteresis thresholds on the gradient magnitude, grey levels / px.
        Default ``k_low`` and ``k_high`` times the gradient noise std: with
        no edge, the magnitude is Rayleigh-distributed and exceeds k std
        with probability exp(-k^2 / 2) (3e-4 for k = 4, 1e-14 for k = 8).
    noise_level : NoiseLevel, optional
        The noise as a function of the grey level
        (:func:`partinspect.vision.noise.noise_level_function`); where it
        depends on the grey level, each pixel's thresholds and each point's
        covariance follow the noise there (:func:`noise_scale_map`): a
        bright face's larger noise (photon noise, PRNU) must not pass the
        thresholds set for the average one, and a dark face's edges must
        not be held to them.

    Returns
    -------
    EdgePoints

    Notes
    -----
    Non-maximum suppression follows Devernay [2]_: a pixel is kept if its
    gradient magnitude is a maximum along the image axis closest to the
    gradient (strictly above the lower neighbour). The offset along that
    axis is the vertex of the parabola through the logarithms (a, b, c) of
    the three magnitudes, ``d = (a - c) / (2 (a - 2b + c))``.

    The position variance along the normal is first-order propagation:
    ``var(d) = J S J^T`` where J is the gradient of d with respect to the
    three magnitudes and S their noise covariance, computed exactly from
    the filter kernels (the samples are 1 px apart and strongly
    correlated); the magnitude noise is the gradient noise projected on the
    gradient direction. A displacement d along the axis e moves the point
    by d (e . n) along the normal n.
    """
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if noise is None:
        noise = estimate_noise(img)
    noise = float(noise)
    H, W = img.shape
    gx, gy = gradient(img, sigma)
    mag = cv2.magnitude(gx, gy)
    sg = gradient_noise_std(noise, sigma)
    low = k_low * sg if low is None else float(low)
    high = k_high * sg if high is None else float(high)
    if high < low:
        raise ValueError("high threshold below low threshold")
    scale_map = None if noise_level is None else noise_scale_map(img, noise_level, sigma)

    # Only pixels above the low threshold can be edge points: work on those.
    cand = mag > (max(low, 1e-12) if scale_map is None else np.maximum(low * scale_map, 1e-12))
    cand[0, :] = cand[-1, :] = cand[:, 0] = cand[:, -1] = False
    flat = np.flatnonzero(cand)
    magf = mag.ravel()
    gxf, gyf = gx.ravel()[flat], gy.ravel()[flat]
    horiz = np.abs(gxf) > np.abs(gyf)
    step = np.where(horiz, 1, W)
    b = magf[flat]
    a = magf[flat - step]
    c = magf[flat + step]
    ismax = (a < b) & (b >= c)
    flat, horiz, a, b, c = flat[ismax], horiz[ismax], a[ismax], b[ismax], c[ismax]
    gxf, gyf = gxf[ismax], gyf[ismax]

    # Hysteresis on the 8-connected maxima.
    mask = np.zeros(H * W, np.uint8)
    mask[flat] = 1
    n_lab, labels = cv2.connectedComponents(mask.reshape(H, W), connectivity=8, ltype=cv2.CV_32S)
    lab = labels.ravel()[flat]
    strong = np.zeros(n_lab, bool)
    strong[lab[b > (high if scale_map is None else high * scale_map.ravel()[flat])]] = True
    keep = strong[lab]
    flat, horiz, a, b, c, gxf, gyf = (v[keep] for v in (flat, horiz, a, b, c, gxf, gyf))

    a, b, c = (np.maximum(v.astype(np.float64), 1e-12) for v in (a, b, c))
    rows, cols = np.divmod(flat, W)
    m = b
    nrm = np.column_stack([gxf, gyf]).astype(np.float64) / m[:, None]
    n_ax = np.abs(np.where(horiz, nrm[:, 0], nrm[:, 1]))  # |n . e|, e the axis
    n_ax2 = n_ax * n_ax
    off, J = _subpixel_offset(a, b, c)
    ex = horiz.astype(np.float64)
    ey = 1.0 - ex
    xy = np.column_stack([cols + off * ex, rows + off * ey])

    var_n = noise * noise * _normal_variance(J, n_ax, sigma)
    pixel = np.column_stack([rows, cols]).astype(np.int32)
    scale = None if scale_map is None else scale_map[rows, cols].astype(np.float64)
    if scale is not None:
        var_n = var_n * scale * scale
    t = np.column_stack([-nrm[:, 1], nrm[:, 0]])
    cov = var_n[:, None, None] * nrm[:, :, None] * nrm[:, None, :] \
        + ALONG_EDGE_VARIANCE * t[:, :, None] * t[:, None, :]
    # Along the axis a Gaussian profile of std w reads as std w / |n . e|,
    # and the second difference of its logarithm is -(n . e)^2 / w^2.
    Dl = np.log(a) - 2.0 * np.log(b) + np.log(c)
    width = np.sqrt(np.maximum(-n_ax2 / np.minimum(Dl, -1e-12), 0.0))
    shift, bound = background_gradients(gx, gy, xy, nrm, m, width, sg if scale is None else sg * scale)
    return EdgePoints(xy, nrm, m, cov, pixel, width, (H, W), float(sigma), noise, sg, shift, bound, scale)
