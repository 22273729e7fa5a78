"""Image noise level estimated from the image itself.

The noise of a camera image is what sets every edge point's standard
uncertainty downstream, so it is measured on the very image being processed,
not assumed.

References
----------
.. [1] Immerkaer, J. (1996). Fast noise variance estimation. Computer Vision
       and Image Understanding 64(2), 300-302: the 3x3 mask that cancels
       every locally quadratic image (so smooth shading does not count as
       noise) and its response variance 36 sigma^2.
.. [2] Tai, S.-C., Yang, S.-M. (2008). A fast method for image noise
       estimation using Laplacian operator and adaptive edge detection.
       ISCCSP 2008: excluding edge pixels before applying [1].
.. [3] Foi, A., Trimeche, M., Katkovnik, V., Egiazarian, K. (2008).
       Practical Poissonian-Gaussian noise modeling and fitting for
       single-image raw-data. IEEE Trans. Image Process. 17(10),
       1737-1754: the noise level function from local means and
       variances of one image.
.. [4] EMVA Standard 1288, release 4.0 (2021): the linear camera model
       (photon noise, read noise, quantisation) and the pixel response
       non-uniformity (PRNU), a gain that differs from pixel to pixel.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import special

__all__ = ["estimate_noise", "QUANTISATION_STD", "NoiseLevel", "noise_level_function", "rounding_std"]

# Immerkaer's mask: the difference of two Laplacians, zero on any quadratic.
_MASK = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
_MASK_NORM = 6.0  # sqrt(sum(_MASK**2)) = sqrt(36)
QUANTISATION_STD = 1.0 / np.sqrt(12.0)
"""Grey levels: the standard deviation of rounding to integers, the least
noise an integer image's edge pixels carry."""


def _truncated_variance_factor(k):
    """E[z^2 | |z| < k] for a standard normal z."""
    p = special.erf(k / np.sqrt(2.0))
    return 1.0 - 2.0 * k * np.exp(-0.5 * k * k) / np.sqrt(2.0 * np.pi) / p


def _max3x3_at(a, step):
    """Maxima of ``a`` over the 3x3 neighbourhoods of its interior pixels on a grid of ``step``.

    The grid is ``a[1:-1:step, 1:-1:step]``; the result equals
    ``cv2.dilate(a, ones((3, 3)))[1:-1:step, 1:-1:step]`` (maxima are exact)
    without the neighbourhoods of the pixels that are not kept.
    """
    H, W = a.shape
    rows = np.maximum(np.maximum(a[0:H - 2:step], a[1:H - 1:step]), a[2:H:step])
    return np.maximum(np.maximum(rows[:, 0:W - 2:step], rows[:, 1:W - 1:step]), rows[:, 2:W:step])


MAX_LEVELS = 1 << 16
"""Most lattice levels :func:`_levels` indexes (an 8-bit image's responses take 4081, its 3x3 means 2296)."""


def _levels(x, scale):
    """``x`` (1-D) as codes into its levels, ``levels[codes] == x`` exactly, or None.

    An integer image's Immerkaer responses are integers and its 3 x 3 means
    ninths of integers: ``rint(x * scale)`` indexes them, and medians and
    bin lookups become counts and table lookups over a few thousand levels
    instead of selections and binary searches over every sample, with the
    very same results (the equality is checked, not assumed).

    Parameters
    ----------
    x : ndarray, shape (N,)
    scale : float
        Lattice spacing's inverse: 1 for responses, 9 for 3 x 3 means.

    Returns
    -------
    (codes, levels) or None
        ``codes`` (N,) int, ``levels`` of ``x``'s dtype, increasing over the
        codes present; None where ``x`` is not on the lattice (a float
        image) or spans more than ``MAX_LEVELS`` levels.
    """
    if x.size == 0:
        return None
    c = np.rint(x * scale)
    if not (c.min() >= 0 and c.max() < MAX_LEVELS):  # False for NaN too
        return None
    codes = c.astype(np.intp)
    levels = np.zeros(int(codes.max()) + 1, x.dtype)
    levels[codes] = x
    # One level per code, so levels rise with the codes present: rint is monotone.
    return (codes, levels) if np.array_equal(levels[codes], x) else None


def _median(x, lattice=None):
    """``np.median(x)``, the same number, from the counts of ``x``'s lattice levels where given (:func:`_levels`).

    The median is the mean of the two middle order statistics (the same one
    twice for an odd count), each read off the cumulative counts.
    """
    if lattice is None:
        return np.median(x)
    codes, levels = lattice
    n = codes.size
    middle = np.searchsorted(np.cumsum(np.bincount(codes, minlength=len(levels))), [(n - 1) // 2, n // 2],
                             side="right")
    return np.median(levels[middle])


def _filtered(img):
    """The image as float32, its Immerkaer responses and its Sobel gradient magnitude, (H, W) each."""
    f = img.astype(np.float32)
    resp = cv2.filter2D(f, cv2.CV_32F, _MASK, borderType=cv2.BORDER_REFLECT)
    gx = cv2.Sobel(f, cv2.CV_32F, 1, 0, ksize=3, borderType=cv2.BORDER_REFLECT)
    gy = cv2.Sobel(f, cv2.CV_32F, 0, 1, ksize=3, borderType=cv2.BORDER_REFLECT)
    return f, resp, cv2.magnitude(gx, gy)


def _grey(image):
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    return img


def estimate_noise(image, *, clip=3.0, edge_k=4.0, iterations=3):
    """Standard deviation of the additive image noise, in grey levels.

    The image is filtered with Immerkaer's mask [1]_, whose response to white
    noise of standard deviation sigma has standard deviation 6 sigma and which
    is zero on any locally quadratic intensity. Edges are the only structure
    left; they are removed as in [2]_ by dropping every pixel whose Sobel
    gradient is significant at ``edge_k`` noise standard deviations (and its
    8 neighbours), and saturated pixels are dropped too. The noise is then
    the truncated second moment of the remaining responses within ``clip``
    standard deviations, corrected for the truncation and iterated; unlike a
    median this is smooth in the data, so it stays unbiased for 8-bit images
    with sub-grey-level noise.

    Parameters
    ----------
    image : ndarray, shape (H, W) or (H, W, C)
        Grey or colour image (colour is converted to grey), any dtype.
    clip : float
        Truncation of the responses, in standard deviations.
    edge_k : float
        Gradient significance level for the edge mask, in standard deviations.
    iterations : int
        Refinements of the edge mask and the estimate.

    Returns
    -------
    float
        Standard deviation of the pixel noise, grey levels. Quantisation is a
        part of it: an 8-bit image with Gaussian noise sigma reads as
        sqrt(sigma^2 + 1/12), which is the noise the pixels actually carry;
        an image reads at least its rounding (:func:`rounding_std`), even
        one with (almost) no noise, whose flat areas round alike:
        ``QUANTISATION_STD`` for an integer image, the floating-point
        spacing's for a float one.

    Notes
    -----
    Assumes white (pixel-independent) noise of constant level over the
    image; for a sensor whose noise grows with brightness the figure is an
    average over the unsaturated non-edge pixels, and
    :func:`noise_level_function` gives the noise at each grey level.
    """
    img = _grey(image)
    if img.ndim != 2 or min(img.shape) < 3:
        raise ValueError(f"need a 2-D image of at least 3x3 pixels, got shape {img.shape}")
    return _estimate_noise(img, _filtered(img), clip, edge_k, iterations)


def _noise_step(img):
    """The subsample's grid step: a regular subsample of the interior is
    plenty (the relative precision of the estimate from n samples is about
    1 / sqrt(2 n)) and keeps the robust iterations cheap on large images."""
    return max(1, int(np.sqrt(img.size / 4e5)))


def _grid(img, filtered, step):
    """On the grid ``[1:-1:step, 1:-1:step]``: the Immerkaer responses, the
    largest gradient of each 3x3 neighbourhood, and which neighbourhoods
    hold no saturated (or zero) pixel.

    A pixel is next to an edge when the largest gradient in its 3x3
    neighbourhood exceeds a threshold: that maximum is taken once, at the
    grid's pixels only, and thresholded at each iteration.
    """
    top = np.iinfo(img.dtype).max if np.issubdtype(img.dtype, np.integer) else None
    resp = filtered[1][1:-1:step, 1:-1:step]
    valid = np.ones(resp.shape, bool)
    if top is not None:
        valid &= ~_max3x3_at((img == 0) | (img == top), step)
    return resp, _max3x3_at(filtered[2], step), valid


def _estimate_noise(img, filtered, clip=3.0, edge_k=4.0, iterations=3, grid=None, lattice=None):
    """:func:`estimate_noise` of ``img`` from its :func:`_filtered` images (and their :func:`_grid`).

    ``lattice``: :func:`_levels` of ``abs(resp)`` on the grid, if known.
    """
    top = np.iinfo(img.dtype).max if np.issubdtype(img.dtype, np.integer) else None
    resp, grad_max, valid = _grid(img, filtered, _noise_step(img)) if grid is None else grid
    r = resp[valid]
    if r.size == 0:
        raise ValueError("no unsaturated pixels to estimate the noise from")
    # Start from the median absolute deviation, robust to the edge outliers.
    sigma = float(_median(np.abs(r), None if lattice is None else (lattice[0][valid.ravel()], lattice[1]))) \
        / 0.6744897501960817 / _MASK_NORM
    if sigma == 0.0 and top is None:
        sigma = float(np.sqrt(np.mean(r * r))) / _MASK_NORM  # most responses exactly zero: start from the RMS
    # Both loops stop early once nothing can change any more, which gives
    # the same sigma as running them to the end: the pixels kept at a
    # threshold are a nested family, so an unchanged count means the very
    # same pixels, hence the same mean and the same sigma next time round.
    n_keep, settled = -1, False
    for _ in range(iterations):
        # Each Sobel component has noise std sqrt(12) sigma, so |g| exceeds
        # k sqrt(12) sigma with probability exp(-k^2 / 2) without an edge.
        thr = edge_k * np.sqrt(12.0) * max(sigma, 1e-3)
        keep = valid & ~(grad_max > thr)
        n = int(np.count_nonzero(keep))
        if n < 100 or (n == n_keep and settled):
            break
        n_keep, settled = n, False
        r = resp[keep]
        r2 = (r * r).astype(np.float64)
        n_sel = -1
        for _ in range(5):
            lim = (clip * _MASK_NORM * sigma) ** 2
            below = r2 < lim
            m = int(np.count_nonzero(below))
            if m == n_sel:
                settled = True
                break
            if m == 0:
                break
            n_sel = m
            sigma = float(np.sqrt(r2[below].mean() / _truncated_variance_factor(clip))) / _MASK_NORM
    # An image with noise well under its rounding step reads as nearly
    # noise-free where it is flat, where rounding is the same for every
    # pixel; across an edge, where the grey levels change, each pixel still
    # carries the rounding error of a step over sqrt(12): a grey level for
    # an integer image, the floating-point spacing for a noise-free render
    # kept in floats (without it, zero, and every weight infinite).
    return max(sigma, rounding_std(img))


def rounding_std(img):
    """Standard deviation of the rounding of ``img``'s grey levels to its type, grey levels.

    ``QUANTISATION_STD`` for an integer image; for a floating-point one the
    spacing of its type at its largest magnitude over sqrt(12).
    """
    if np.issubdtype(img.dtype, np.integer):
        return QUANTISATION_STD
    top = np.abs(img).max(initial=1.0)
    return float(np.spacing(np.asarray(top, img.dtype))) / np.sqrt(12.0)


NLF_SIGNIFICANCE = 13.8
"""Chi-square (2 degrees of freedom, p = 0.001) by which the grey-dependent
noise model must fit the binned variances better than a constant before it
replaces the constant: noise that does not depend on the grey level stays
one number, as :func:`estimate_noise` gives it."""
NLF_BINS = 12
"""Bins of grey level the noise's variance is read in (fewer on small images)."""
NLF_MIN_PIXELS = 300
"""Least pixels per bin: the variance's relative standard error is
``sqrt(2 / n)``, 8 % at 300."""


@dataclass(frozen=True)
class NoiseLevel:
    """Noise variance as a function of the grey level, ``var(I) = b + a I + c I^2``.

    ``b``: read noise and quantisation; ``a``: photon (shot) noise, the
    gain in grey levels per electron; ``c``: the square of the pixel
    response non-uniformity (a gain that differs from pixel to pixel acts
    on one image as noise proportional to the grey level) [3]_ [4]_.

    Attributes
    ----------
    b, a, c : float
        Coefficients, grey levels^2, grey levels, and 1.
    noise : float
        :func:`estimate_noise` of the same image, grey levels: the constant
        the rest of the chain uses (thresholds) and what ``var`` equals
        when ``signal_dependent`` is False.
    signal_dependent : bool
        Whether the grey-dependent model was significantly better than a
        constant (``NLF_SIGNIFICANCE``).
    """

    b: float
    a: float
    c: float
    noise: float
    signal_dependent: bool

    def std(self, grey):
        """Noise standard deviation at grey level(s) ``grey``, grey levels."""
        grey = np.asarray(grey, dtype=np.float64)
        if not self.signal_dependent:
            return np.full(grey.shape, self.noise)
        return np.sqrt(np.maximum(self.b + self.a * grey + self.c * grey * grey, QUANTISATION_STD ** 2))


def _bin_variances(resp, grey, n_bins, resp_lattice=None, grey_lattice=None):
    """Per bin of local grey level: (mean grey, mean grey^2, noise variance, pixel count).

    Each bin's variance is the truncated second moment of the Immerkaer
    responses, as in :func:`estimate_noise` (robust to the few edge pixels
    the mask let through). ``resp_lattice``, ``grey_lattice``:
    :func:`_levels` of ``abs(resp)`` and of ``grey``, where they lie on one;
    the bins and medians are then read from counts (the same numbers).
    """
    q = np.linspace(0.0, 1.0, n_bins + 1)
    if grey_lattice is None:
        edges = np.unique(np.quantile(grey, q))
    else:
        # The same quantiles from the levels laid out in order by their
        # counts: a quantile depends on the order statistics only, and the
        # selection is cheap on sorted data.
        codes, levels = grey_lattice
        edges = np.unique(np.quantile(np.repeat(levels, np.bincount(codes, minlength=len(levels))), q))
    last = max(len(edges) - 2, 0)
    if grey_lattice is None:
        idx = np.clip(np.searchsorted(edges, grey, side="right") - 1, 0, last)
    else:  # each level's bin, looked up
        idx = np.clip(np.searchsorted(edges, grey_lattice[1], side="right") - 1, 0, last)[grey_lattice[0]]
    # Each bin's pixels as one contiguous run of the bin-sorted order.
    # Bin numbers as bytes: numpy's stable sort of them is a radix sort.
    order = np.argsort(idx.astype(np.uint8) if len(edges) <= 256 else idx, kind="stable")
    bounds = np.r_[0, np.cumsum(np.bincount(idx, minlength=max(len(edges) - 1, 1)))]
    # The squared responses' levels (the sign squares away alike).
    r2_levels = None if resp_lattice is None else (resp_lattice[1].astype(np.float64) / _MASK_NORM) ** 2
    out = []
    for k in range(max(len(edges) - 1, 1)):
        sel = order[bounds[k]:bounds[k + 1]]
        n = len(sel)
        if n < NLF_MIN_PIXELS:
            continue
        r2 = (resp[sel].astype(np.float64) / _MASK_NORM) ** 2
        lattice = None if r2_levels is None else (resp_lattice[0][sel], r2_levels)
        var = float(_median(r2, lattice)) / 0.4549364231195724  # median of chi-square(1)
        n_below = -1
        for _ in range(5):
            below = r2 < 9.0 * var
            m = int(np.count_nonzero(below))
            # The same count is the same samples (thresholds on one array
            # keep nested sets), hence the same variance from here on.
            if m == 0 or m == n_below:
                break
            n_below = m
            var = float(r2[below].mean() / _truncated_variance_factor(3.0))
        g = grey[sel].astype(np.float64)
        out.append((g.mean(), (g * g).mean(), var, n))
    return np.array(out).reshape(-1, 4)


def _weighted_fit(design, v, w):
    """Non-negative weighted least squares of v on the columns of design; (coefficients, chi-square)."""
    from scipy.optimize import nnls

    sw = np.sqrt(w)
    coef, _ = nnls(design * sw[:, None], v * sw)
    return coef, float(np.sum(w * (design @ coef - v) ** 2))


def noise_level_function(image, noise=None, *, edge_k=4.0, n_bins=NLF_BINS):
    """The image noise's variance as a function of the grey level, from the image itself.

    Immerkaer's responses [1]_ on a grid of every third pixel (so no two
    share a pixel and they are independent) away from edges and saturated
    pixels, grouped by the local mean grey (3 x 3, the mask's support) into
    ``n_bins`` bins of equal count; each bin's robust variance; then the
    non-negative weighted fit of ``b + a I + c I^2`` to them (weights from
    each variance's own sampling variance, ``2 var^2 / n``) [3]_. The
    model is kept only if it beats a constant by ``NLF_SIGNIFICANCE``:
    a sensor with grey-independent noise gets the constant back.

    Parameters
    ----------
    image : ndarray, shape (H, W) or (H, W, C)
    noise : float, optional
        :func:`estimate_noise` of the image, if already known; else it is
        estimated here (from the same filtered image), and the result's
        ``noise`` holds it.
    edge_k : float
        Gradient significance for the edge mask, in local noise standard
        deviations (as in :func:`estimate_noise`).
    n_bins : int

    Returns
    -------
    NoiseLevel
    """
    img = _grey(image)
    filtered = _filtered(img)
    resp, grad_max, valid = grid = _grid(img, filtered, 3)
    resp_lattice = _levels(np.abs(resp).ravel(), 1.0)
    if noise is None:
        noise = (_estimate_noise(img, filtered, grid=grid, lattice=resp_lattice) if _noise_step(img) == 3 else
                 _estimate_noise(img, filtered))
    noise = float(noise)
    constant = NoiseLevel(noise * noise, 0.0, 0.0, noise, False)
    grey = cv2.blur(filtered[0], (3, 3), borderType=cv2.BORDER_REFLECT)[1:-1:3, 1:-1:3]
    grey_lattice = _levels(grey.ravel(), 9.0)
    floor = rounding_std(img) ** 2
    level = constant
    for _ in range(2):
        # The edge mask's threshold follows the noise at each pixel's grey:
        # a bright face's larger noise must not read as edges.
        keep = valid & ~(grad_max > edge_k * np.sqrt(12.0) * np.maximum(level.std(grey), 1e-3))
        if np.count_nonzero(keep) < 3 * NLF_MIN_PIXELS:
            return constant
        # Small images get fewer, fuller bins: each variance to about 8 %.
        flat = keep.ravel()
        bins = _bin_variances(resp[keep], grey[keep], min(n_bins, np.count_nonzero(keep) // NLF_MIN_PIXELS),
                              *(None if lat is None else (lat[0][flat], lat[1]) for lat in (resp_lattice, grey_lattice)))
        if len(bins) < 3:
            return constant
        m1, m2, v, n = bins.T
        v = np.maximum(v, floor)
        w = n / (2.0 * v * v)
        (b0,), chi_const = _weighted_fit(np.ones((len(v), 1)), v, w)
        coef, chi_full = _weighted_fit(np.column_stack([np.ones_like(m1), m1, m2]), v, w)
        if chi_const - chi_full < NLF_SIGNIFICANCE:
            return constant
        level = NoiseLevel(float(coef[0]), float(coef[1]), float(coef[2]), noise, True)
    return level
