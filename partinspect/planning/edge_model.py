"""How well the edge detector will locate an edge it has not seen yet.

A detected edge point's standard uncertainty across the edge follows from
the pixel noise ``s_n`` (grey levels, quantisation included:
:attr:`DetectorModel.pixel_noise`), the contrast ``h`` (grey levels), the
optical blur ``b`` and the edge filter's scale ``s`` (px). Blur, the pixel's
box aperture and the filter make the gradient profile across a step a
Gaussian of width ``w = sqrt(s^2 + b^2 + 1/12)`` px; the detector puts the
edge at its maximum, which noise moves by the noise of the derivative over
the profile's curvature. Canny's localisation result [1]_, extended to a
blurred edge and 2-D smoothing:

    sigma_edge = c * sqrt(3 / 8) * (s_n / h) * (w / s)^3          (px)

``c`` = :data:`EDGE_STD_FACTOR` accounts for the discrete detector (a
parabola through the logarithms of three magnitudes [2]_). This closed form
is the quick estimate; the prediction (:func:`stated_std_pattern`) uses the
detector's own first-order propagation at the magnitudes the profile gives
at each point's direction and sub-pixel phase, which follows the detector
near 45 deg and gives the scatter of stated values a form zone sees.
Neighbouring points' errors share smoothed noise, correlation
``exp(-d^2 / (4 s^2))``; the detector gives one point per pixel along the
image axis nearer the edge's direction (:func:`detector_parameters`).

References
----------
.. [1] Canny, J. (1986). A computational approach to edge detection. IEEE
       TPAMI 8(6), 679-698, section II (the localisation criterion:
       ``E[x^2] = s_n^2 int f'^2 / (A f'(0))^2`` for filter f and step A).
.. [2] Devernay, F. (1995). A non-maxima suppression method for edge
       detection with sub-pixel accuracy. INRIA RR-2724.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "EDGE_STD_FACTOR",
    "DetectorModel",
    "profile_width",
    "edge_point_std",
    "detector_parameters",
    "near_image",
    "stated_std_pattern",
]

EDGE_STD_FACTOR = 0.955
"""Discrete detector over the continuous model: calibrated on
:func:`partinspect.vision.edges.edge_points` itself, on blurred straight
steps over the range of directions and contrasts the chain meets."""


@dataclass(frozen=True)
class DetectorModel:
    """What the prediction assumes about the images and the detector.

    Attributes
    ----------
    noise : float
        Standard deviation of the sensor noise before 8-bit quantisation, grey
        levels.
    quantised : bool
        8-bit images: quantisation adds variance 1/12 grey level^2.
    blur : float
        Optical blur, standard deviation of the Gaussian PSF, px.
    sigma : float
        Scale of the edge filter, px (the chain's default 1).
    contrast : float or None
        Grey-level step at every edge; None to take it from the shading of the
        part's faces (the light of :mod:`partinspect.cad.raycast`).
    end_trim : float or None
        Pixels lost at each end of a visible stretch of edge (the filter mixes
        the gradients of two edges meeting at a corner); None for
        :attr:`run_trim` on straight edges and :attr:`arc_trim` on curved ones.
    min_points : int
        Fewest edge points in an image for a feature to be matched (the
        matcher's ``min_points``).
    systematic : bool
        Include the chain's Type B uncertainty of points on curved edges beside
        shaded surfaces (:func:`partinspect.planning.predict.background_terms`).
        False predicts the image-noise part alone, what the spread over noise
        draws of one rendered scene shows: the fits still weight the points as
        the chain does, only the covariances leave the Type B part out, and a
        form value's u is its spread over images of one scene with the Type B
        displacements held (they change which points set the zone).
    """

    noise: float = 2.0
    blur: float = 0.6
    sigma: float = 1.0
    contrast: float | None = None
    end_trim: float | None = None
    min_points: int = 12
    quantised: bool = True
    systematic: bool = True

    @property
    def run_trim(self):
        """Pixels lost at each end of a visible stretch of edge: ``end_trim``, or ``3 sigma``.

        The segmentation leaves ``3 sigma + 1`` px at a piece's open ends out of
        its fit (:func:`partinspect.vision.contours.segment_contour`'s ``trim``),
        counted from where the piece ends, which need not be where the visible
        edge ends. 3 sigma is chosen so that the predicted point counts match the
        chain's: less leaves partial arcs' ends, which fix their curvature, too
        long; more drops short lines below the matcher's ``min_points`` that the
        chain still finds.
        """
        return float(self.end_trim) if self.end_trim is not None else 3.0 * self.sigma

    @property
    def arc_trim(self):
        """Pixels lost at each end of a visible stretch of a curved edge: ``end_trim``, or ``3 sigma + 1``.

        The segmentation moves the break between two fitted pieces to where their
        models meet (:func:`partinspect.vision.contours._adjust_breaks`), so an arc
        ends at its junction and loses the segmentation's full trim there. A
        partial arc's radius depends steeply on its ends, which a line's does not,
        so curved edges take this trim and lines keep ``run_trim`` for the counts.
        """
        return float(self.end_trim) if self.end_trim is not None else 3.0 * self.sigma + 1.0

    @property
    def pixel_noise(self):
        """Noise the pixels carry, grey levels: ``sqrt(noise^2 + 1/12)`` when quantised."""
        return float(np.hypot(self.noise, np.sqrt(1.0 / 12.0))) if self.quantised else float(self.noise)


def profile_width(blur, sigma):
    """Standard deviation of the gradient profile across a step edge, px.

    ``sqrt(sigma^2 + blur^2 + 1/12)``: filter, optics and the pixel's box
    aperture (variance 1/12) in series.
    """
    return float(np.sqrt(sigma * sigma + blur * blur + 1.0 / 12.0))


def edge_point_std(contrast, noise, blur=0.6, sigma=1.0):
    """Standard uncertainty of a detected edge point across the edge.

    Parameters
    ----------
    contrast : float or array_like
        Grey-level step across the edge (absolute value used).
    noise : float
        Image noise standard deviation, grey levels.
    blur, sigma : float
        Optical blur and edge-filter scale, px.

    Returns
    -------
    float or ndarray
        px; ``EDGE_STD_FACTOR * sqrt(3/8) * noise / contrast * (w / sigma)^3``
        (module notes), ``inf`` where the contrast is zero.
    """
    w = profile_width(blur, sigma)
    h = np.abs(np.asarray(contrast, float))
    with np.errstate(divide="ignore"):
        out = EDGE_STD_FACTOR * np.sqrt(3.0 / 8.0) * noise * (w / sigma) ** 3 / h
    return out if out.ndim else float(out)


def detector_parameters(t, uv, spacing=1.0, valid=None):
    """Where along an edge the detector puts its points: one per pixel of the dominant axis.

    The detector keeps one maximum per pixel along the image axis closest
    to the gradient, so an edge running at angle ``a`` to the nearer axis
    gets a point every ``1 / cos a`` px along it. The image curve is
    measured in that "dominant-axis length" ``int max(|du|, |dv|)`` and
    points are put at every ``spacing`` of it.

    Parameters
    ----------
    t : ndarray, shape (M,)
        Increasing parameter of a dense sampling of the edge (e.g. arc
        length in mm, or angle).
    uv : ndarray, shape (M, 2)
        The image positions of those samples, px (finite).
    spacing : float
        Dominant-axis pixels between points.
    valid : ndarray of bool, shape (M,), optional
        Samples whose image position means something; a piece of the curve
        with an end not valid has no length and gets no point (see
        :func:`near_image`).

    Returns
    -------
    ndarray, shape (N,)
        Parameters of the points, at the middles of equal pieces (no point
        on an end).
    """
    step = np.abs(np.diff(uv, axis=0)).max(axis=1)
    if valid is not None:
        step[~(valid[:-1] & valid[1:])] = 0.0
    ell = np.r_[0.0, np.cumsum(step)]
    n = int(np.floor(ell[-1] / spacing))
    if n < 1:
        return np.zeros(0)
    targets = (np.arange(n) + 0.5) * (ell[-1] / n)
    return np.interp(targets, ell, t)


def near_image(uv, size):
    """Which image positions lie within one image size of the image, boolean (M,).

    Far outside the field a calibration was made in, its distortion
    polynomial describes no lens: a point there can be thrown millions of
    pixels away, and an edge passing there would seem to run across them.
    Within one image width and height of the image the model still holds
    roughly, and the detector's points (in the image) are all there.

    Parameters
    ----------
    uv : ndarray, shape (M, 2)
        Projected positions, px.
    size : (int, int)
        The image's width and height, px.
    """
    w, h = size
    u, v = uv[:, 0], uv[:, 1]
    return np.isfinite(uv).all(axis=1) & (u > -w) & (u < 2 * w) & (v > -h) & (v < 2 * h)


def stated_std_pattern(uv, normal, contrast, model, rng=None):
    """The standard uncertainty the detector will state for each point of an edge, and how it scatters.

    The detector states each point's uncertainty from the noisy gradient
    magnitudes it read (:func:`partinspect.vision.edges.stated_std_spread`), so
    the stated values scatter from point to point, and the chain's form Monte
    Carlo draws its errors with them: a zone (a maximum) is set by the points
    stated most uncertain, so the chain's form u is above the one a uniform
    uncertainty gives. The prediction draws one such pattern so that its form
    u is the one the chain will state.

    Parameters
    ----------
    uv, normal : ndarray, shape (N, 2)
        Predicted edge points in order along the edge and their unit normals,
        px (distorted image).
    contrast : ndarray, shape (N,)
        Grey-level step at each point.
    model : DetectorModel
    rng : numpy.random.Generator, optional
        Default: seeded with 0, so a prediction is repeatable.

    Returns
    -------
    std : ndarray, shape (N,)
        The standard uncertainty the detector states for each point of a
        noise-free edge, px (``inf`` where the contrast is zero).
    pattern : ndarray, shape (N,)
        ``exp(cv * eta)``: ``cv`` the scatter of the log of the stated
        uncertainty for the noise-free magnitudes of a Gaussian profile of width
        :func:`profile_width` at the point's sub-pixel phase, ``eta`` a unit
        Gaussian field along the edge with the correlation of the points' own
        errors (their magnitudes share the smoothed noise).
    """
    from partinspect.vision.edges import stated_std_spread
    from partinspect.vision.pointerrors import correlated_field

    uv = np.asarray(uv, float)
    if len(uv) == 0:
        return np.zeros(0), np.ones(0)
    normal = np.asarray(normal, float)
    horiz = np.abs(normal[:, 0]) >= np.abs(normal[:, 1])
    n_ax = np.where(horiz, np.abs(normal[:, 0]), np.abs(normal[:, 1]))
    along = np.where(horiz, uv[:, 0], uv[:, 1])
    phase = along - np.rint(along)
    w = profile_width(model.blur, model.sigma)
    h = np.maximum(np.abs(np.asarray(contrast, float)), 1e-9)
    d = (np.array([-1.0, 0.0, 1.0])[None, :] - phase[:, None]) * n_ax[:, None]
    m = (h / (np.sqrt(2.0 * np.pi) * w))[:, None] * np.exp(-d * d / (2.0 * w * w))
    cv, std = stated_std_spread(m, n_ax, model.sigma, model.pixel_noise)
    std = np.where(np.asarray(contrast, float) == 0, np.inf, std)
    s = np.r_[0.0, np.cumsum(np.hypot(*np.diff(uv, axis=0).T))]
    rng = np.random.default_rng(0) if rng is None else rng
    eta = correlated_field(s, model.sigma, rng, 1)[0]
    return std, np.exp(cv * eta)
