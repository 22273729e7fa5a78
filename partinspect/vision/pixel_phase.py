"""The edge detector's error with the sub-pixel phase, read from a line's own residuals and removed.

An edge point is found as the vertex of a parabola through three gradient
magnitudes one pixel apart along an image axis
(:func:`partinspect.vision.edges.edge_points`). Where the blurred profile
is not exactly the shape the estimator assumes (a sharp lens, whose blur
is narrower than the pixel, flattens it; a sensor's fill factor and
micro-lenses change it), the vertex is displaced by an amount that depends
only on where the edge crosses the pixel, its sub-pixel phase ``phi``
(the offset from the pixel centre, -1/2 to 1/2), and on the profile,
which is the same all along a straight edge. For a profile symmetric about
its centre the displacement is odd in ``phi`` and vanishes at 0 and 1/2:
a sine series ``sum_k a_k sin(2 pi k phi)`` [1]_ [2]_.

Along a straight edge the phase runs through its cycle at a rate set by
the edge's slope, so this "pixel locking" shows as a ripple of the points
about the fitted line; near a slope of a simple ratio (45 degrees, an
image axis) the phase drifts slowly and the ripple becomes a wave tens of
pixels long, which a form zone reads as out-of-straightness and which the
noise model, point-to-point, does not carry. A real form deviation of
the part cannot follow the pixel grid's phase, so regressing the residuals
on the phase harmonics separates the two: the fitted ripple is removed
from the points, and its coefficients' uncertainty carried. The phase is
the edge's, where the fitted line crosses each point's search axis
(:func:`line_phase`), not the point's own, which carries its noise.

Only the part of the ripple that the line fit does not absorb is removed
(the regressors are made orthogonal to the line's offset and tilt under
the fit's weights), so the fitted line and its covariance stay those of
the uncorrected points, and what is removed is what the form sees.

References
----------
.. [1] Shimizu, M., Okutomi, M. (2005). Sub-pixel estimation error
       cancellation on area-based matching. IJCV 63(3), 207-224 (the
       estimator's error as an odd periodic function of the sub-pixel
       phase).
.. [2] Devernay, F. (1995). A non-maxima suppression method for edge
       detection with sub-pixel accuracy. INRIA RR-2724.
.. [3] JCGM 100:2008, 3.2.3-3.2.4 (a recognised systematic effect is
       corrected, and the correction's uncertainty carried).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import special

from partinspect.vision.fitting import fit_line, information_matrices
from partinspect.vision.psd import covariance_factor

__all__ = ["PhaseRipple", "HARMONICS", "RIPPLE_P", "sampling_phase", "sampling_axis", "line_phase", "phase_ripple",
           "without_phase_ripple"]

HARMONICS = (1, 2)
"""The sine harmonics of the phase fitted: the odd error of a symmetric
profile's vertex is dominated by the first; the second takes up a profile
flattened at the top (a blur narrower than the pixel)."""

RIPPLE_P = 0.01
"""A ripple is removed when the Wald test of its coefficients against zero
(chi-square with ``len(HARMONICS)`` degrees of freedom, the coefficients'
sandwich covariance) rejects zero at this level: a clean line keeps its
points as found."""


@dataclass(frozen=True)
class PhaseRipple:
    """The phase ripple of one line's points.

    Attributes
    ----------
    regressors : ndarray, shape (N, k)
        ``sin(2 pi h phi)`` for h in ``HARMONICS`` (one set per sampling
        axis, zero at the other axis's points, where the points were found
        along both), made orthogonal to the line's offset and tilt under
        the fit's weights, px per unit coefficient.
    coefficients : ndarray, shape (k,)
        Fitted amplitudes, px.
    covariance : ndarray, shape (k, k)
        Their covariance, px^2 (sandwich, the points' correlated noise).
    p_value : float
        The Wald test's p-value of the coefficients against zero.
    """

    regressors: np.ndarray
    coefficients: np.ndarray
    covariance: np.ndarray
    p_value: float

    @property
    def displacement(self):
        """The ripple at each point along the line's normal, px, shape (N,)."""
        return self.regressors @ self.coefficients

    @property
    def significant(self):
        return self.p_value < RIPPLE_P

    @property
    def factor(self):
        """The removed ripple's error at each point per unit normal deviate, px, shape (N, k).

        ``factor @ z`` with ``z`` standard normal draws the correction's
        error across the line (the coefficients' covariance, rank k).
        """
        return self.regressors @ covariance_factor(self.covariance)


def sampling_phase(uv, pixel):
    """Sub-pixel phase of edge points along the axis each was found along.

    Parameters
    ----------
    uv : ndarray, shape (N, 2)
        Edge points, distorted px (``EdgePoints.xy``).
    pixel : ndarray, shape (N, 2)
        The pixel (row, column) each was found at (``EdgePoints.pixel``):
        the point differs from it along one axis only.

    Returns
    -------
    ndarray, shape (N,)
        The offset from the pixel centre along that axis, px, -1/2 to 1/2.
    """
    uv = np.asarray(uv, float)
    pixel = np.asarray(pixel, float)
    return (uv[:, 0] - pixel[:, 1]) + (uv[:, 1] - pixel[:, 0])


def sampling_axis(uv, pixel):
    """The image axis each edge point was found along: 0 for x, 1 for y, shape (N,)."""
    uv = np.asarray(uv, float)
    return (np.abs(uv[:, 1] - np.asarray(pixel, float)[:, 0]) > 0).astype(int)


def line_phase(uv, pixel, residuals, normal):
    """Sub-pixel phase at which the fitted line crosses each point's search axis.

    The ripple is a function of where the edge crosses the pixel, not of
    where the noisy point was found: a point's own phase is the edge's plus
    its noise, so harmonics of it regress the residuals on their own noise.
    Where the edge's phase hardly moves along the line (an image axis, 45
    degrees) that regression takes the noise up as a "ripple" and removes
    it, leaving points far straighter than their stated noise. The point
    moved along its search axis onto the fitted line gives the edge's phase.

    Parameters
    ----------
    uv : ndarray, shape (N, 2)
        Edge points, distorted px (``EdgePoints.xy``).
    pixel : ndarray, shape (N, 2)
        The pixel (row, column) each was found at.
    residuals : ndarray, shape (N,)
        Signed distances of the points from the fitted line along ``normal``,
        px (``LineFit.residuals``).
    normal : ndarray, shape (2,)
        The fitted line's unit normal.

    Returns
    -------
    ndarray, shape (N,)
        px. A move ``d`` along the search axis changes the residual by
        ``d`` times the normal's component on that axis, which the search
        along the gradient's dominant axis keeps at 1/sqrt(2) or more.

    References
    ----------
    .. [1] Fuller, W. A. (1987). Measurement Error Models. Wiley, 1.1 (a
           regressor observed with error biases the regression towards it).
    """
    axis = sampling_axis(uv, pixel)
    along = np.asarray(normal, float)[axis]
    return sampling_phase(uv, pixel) - np.asarray(residuals, float) / along


def phase_ripple(xy, normal, residuals, point_std, phase, corr_length, axis=None):
    """The phase ripple of a fitted line's points (see the module notes).

    Parameters
    ----------
    xy : ndarray, shape (N, 2)
        The line's points, ideal px, in order along it.
    normal : ndarray, shape (2,)
        The fitted line's unit normal.
    residuals : ndarray, shape (N,)
        Signed distances of the points from the fitted line, px.
    point_std : ndarray, shape (N,)
        Their standard uncertainties across the line, px (the fit's weights).
    phase : ndarray, shape (N,)
        Their sampling phases (:func:`sampling_phase`).
    corr_length : float
        Correlation length of the points' noise along the edge, px.
    axis : ndarray of int, shape (N,), optional
        The axis each point was found along (:func:`sampling_axis`). The
        displacement is along that axis, so its component across the line
        has the sign and size of the normal's component there: near 45
        degrees, where the axis changes from point to point, each axis has
        its own coefficients. None: one axis for all.

    Returns
    -------
    PhaseRipple or None
        None when the harmonics cannot be told from the line's offset and
        tilt (fewer points than parameters, or a phase that hardly moves).
    """
    xy = np.asarray(xy, float)
    s = np.asarray(point_std, float)
    n = len(xy)
    k = len(HARMONICS)
    if n < 3 + 2 * k:
        return None
    t = (xy - xy.mean(axis=0)) @ np.array([-normal[1], normal[0]])
    H = np.column_stack([np.ones(n), t])
    X = np.sin(2.0 * np.pi * np.outer(phase, HARMONICS))
    if axis is not None:
        axis = np.asarray(axis, int)
        X = np.column_stack([X * (axis == a)[:, None] for a in (0, 1) if np.sum(axis == a) >= 2 * k])
        k = X.shape[1]
        if k == 0:
            return None
    w = 1.0 / (s * s)
    # The regressors' part the line's offset and tilt cannot take up.
    Xp = X - H @ np.linalg.solve(H.T @ (w[:, None] * H), H.T @ (w[:, None] * X))
    S, M, _ = information_matrices(Xp, s, xy, corr_length)
    if np.linalg.cond(S) > 1e8:
        return None
    Sinv = np.linalg.inv(S)
    coef = Sinv @ (Xp.T @ (w * np.asarray(residuals, float)))
    cov = Sinv @ M @ Sinv
    wald = float(coef @ np.linalg.solve(cov, coef))
    return PhaseRipple(Xp, coef, cov, float(special.chdtrc(k, wald)))


def without_phase_ripple(feature, edges):
    """A line feature with its phase ripple removed, or the feature as it is where it shows none.

    Parameters
    ----------
    feature : ImageFeature
        A line (:class:`partinspect.vision.imagefeatures.ImageFeature`) with its fit.
    edges : EdgePoints
        The image's edge points its ``index`` refers to.

    Returns
    -------
    ImageFeature
        Where the ripple is significant (``RIPPLE_P``): its points (distorted
        and ideal) moved back across the line by the fitted ripple, its line
        fitted again (the same line up to rounding: the ripple removed is
        orthogonal to it), and ``phase_factor`` the correction's error
        factor (:attr:`PhaseRipple.factor`).
    """
    fit = feature.fit
    uv, pixel = edges.xy[feature.index], edges.pixel[feature.index]
    phase = line_phase(uv, pixel, fit.residuals, fit.params[:2])
    ripple = phase_ripple(feature.ideal.xy, fit.params[:2], fit.residuals, fit.point_std, phase, edges.sigma,
                          sampling_axis(uv, pixel))
    if ripple is None or not ripple.significant:
        return feature
    shift = ripple.displacement[:, None] * np.asarray(fit.params[:2], float)[None, :]
    ideal = replace(feature.ideal, xy=feature.ideal.xy - shift)
    fit = fit_line(ideal.xy, ideal.cov, corr_length=edges.sigma)
    return replace(feature, uv=feature.uv - shift, ideal=ideal, fit=fit, phase_factor=ripple.factor)
