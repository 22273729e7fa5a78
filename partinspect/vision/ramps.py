"""Whether an image feature is a step edge or the crest of a shading ramp.

The edge detector keeps the maxima of the smoothed gradient across an
edge. A step between two faces puts almost all of its grey-level change
within a few edge widths W of the maximum: 3 px and more away (beyond
2.5 W for the blur of a usable image) the gradient is the faces' own
shading, a small fraction of the step's peak. A face whose grey changes
smoothly (a shaded curved surface, a light's fall-off across a plane) has
maxima of its gradient too, wherever the shading's slope peaks, and where
that slope is above the detector's thresholds they chain into lines and
arcs like edges. There the gradient 3-6 px either side is still most of
the peak, on both sides and in the same direction: no step, a ramp's
crest. Such a feature locates no edge of the part, yet its line can pair with an
edge in the other image (a line pair always triangulates) and be fitted
tens of mm off with a small stated uncertainty.

The test reads the grey profile across the feature averaged along it
(:func:`partinspect.vision.line_profile.across_profile`), fits a straight
line to each side beyond ``SIDE`` px, and compares the two slopes along
the edge normal with the peak gradient.

Frames: distorted pixels as the points were found; profiles run along
each point's edge normal, dark to bright.

References
----------
.. [1] Canny, J. (1986). A computational approach to edge detection. IEEE
       PAMI 8(6), 679-698 (a step edge's response and the interaction of
       nearby edges).
"""

import numpy as np

from partinspect.vision.edges import MAX_STEP_WIDTH
from partinspect.vision.line_profile import REACH, across_profile

__all__ = ["SIDE", "STEP", "RAMP_SHARE", "side_slopes", "ramp_share"]

SIDE = 3.0
"""px: the profile beyond this on each side is the faces' own shading. A
step's gradient there is under 0.05 of its peak for edge widths up to
1.2 px (``exp(-9 / 2 W^2)``), the same distance the first-order shading
reading starts from (:data:`partinspect.vision.edges.BACKGROUND_DISTANCES`)."""

STEP = 0.5
"""px between the profile's samples: seven per side, enough for a straight
line's slope (the points' average is what makes it precise)."""

RAMP_SHARE = float(np.exp(-(0.5 * (SIDE + REACH)) ** 2 / (2.0 * MAX_STEP_WIDTH**2)))
"""A feature is a ramp's crest when the grey-level slope on both of its
sides, beyond ``SIDE``, is more than this share of its peak gradient, in
the same direction (0.32). It is the share that a gradient profile of
Gaussian shape and standard deviation ``MAX_STEP_WIDTH``, the widest a
step edge's profile is taken to be (:mod:`partinspect.vision.edges`),
keeps at the middle of the sides' span, ``(SIDE + REACH) / 2`` px: a
wider profile is shading, not a step blurred by the optics."""


def side_slopes(image, uv, normal):
    """The grey-level slopes beside a feature, either side of it, grey levels / px.

    Parameters
    ----------
    image : ndarray, shape (H, W)
        The image as recorded, grey levels.
    uv, normal : ndarray, shape (N, 2)
        The feature's edge points, distorted px, and their unit normals
        (dark to bright).

    Returns
    -------
    ndarray, shape (2,)
        The slope along the normal of a straight line fitted by least
        squares to the averaged profile, sampled every ``STEP`` px, from
        ``-REACH`` to ``-SIDE`` (the dark side) and from ``SIDE`` to
        ``REACH`` (the bright side).
    """
    t, grey = across_profile(image, np.asarray(uv, float), np.asarray(normal, float), step=STEP)
    dark, bright = t <= -SIDE, t >= SIDE
    return np.array([np.polyfit(t[s], grey[s], 1)[0] for s in (dark, bright)])


def ramp_share(image, uv, normal, strength):
    """The smaller share of a feature's peak gradient that its sides carry.

    Parameters
    ----------
    image : ndarray, shape (H, W)
    uv, normal : ndarray, shape (N, 2)
        As :func:`side_slopes`.
    strength : ndarray, shape (N,)
        The gradient magnitude at each point (``EdgePoints.strength``),
        grey levels / px.

    Returns
    -------
    float
        ``min(side_slopes) / median(strength)``: about 0 beside a step
        between faces of uniform grey, negative where one side falls back,
        about 1 on a ramp of uniform slope; above ``RAMP_SHARE`` the
        feature is a ramp's crest. NaN for a feature without points or
        gradient.
    """
    peak = float(np.median(strength)) if len(strength) else 0.0
    if not peak > 0.0 or len(uv) == 0:
        return float("nan")
    return float(side_slopes(image, uv, normal).min() / peak)
