"""A line's displacement by a narrow band beside it, read from the grey profile across the line.

The shading reading of :func:`partinspect.vision.edges.background_gradients`
takes the background gradient 3-4 px off each edge point. A band beside
the edge (a fillet's or chamfer's flank seen near grazing incidence) whose
flank lies within about 2 px of the edge escapes it: the flank is inside
the step's own response there, and 3-4 px off the reading sees the band's
floor or far flank. Along a straight edge such a band runs with the edge,
so the grey profile across the line, averaged along it, shows it with the
noise of one point divided by the root of the line's length.

That profile is modelled as blurred steps (Canny's interaction of nearby
edges, [1]_): the edge, located from its unshaded side as much as from
the other, and the band as a second step of its own depth, place and
width (its near flank) with its return a width further out (its far
flank; out of reach for a face that stays shaded). The edge detector's
maximum of the smoothed gradient, computed on that model with and without
the band, gives the displacement of the line's points by the band
(:func:`band_displacement`).

Frames: distorted pixels as the points were found (OpenCV pixel frame);
the profile's coordinate runs along each point's edge normal, dark to
bright, zero at the point.

References
----------
.. [1] Canny, J. (1986). A computational approach to edge detection. IEEE
       PAMI 8(6), 679-698, section VI (the interaction of nearby edges).
.. [2] Golub, G., & Pereyra, V. (2003). Separable nonlinear least squares:
       the variable projection method and its applications. Inverse
       Problems 19(2), R1-R26.
"""

import numpy as np
from scipy.ndimage import map_coordinates
from scipy.optimize import least_squares
from scipy.special import ndtr

from partinspect.vision.rim_errors import RIM_DETECTOR_ERROR

__all__ = ["REACH", "BAND_Z", "across_profile", "two_step_fit", "band_displacement", "line_band_shift",
           "DETECTOR_FLOOR"]

REACH = 6.0
"""px either side of the edge the profile is read over: the band the
shading reading misses has its near flank within 2.5 edge widths of the
edge (about 3 px); its far flank must lie in the profile too, or the
model's band takes the face beyond it for its floor."""
STEP = 0.25
"""px between the profile's samples (bilinear, so the samples within one
pixel are correlated; the fit's residuals set its noise)."""
BAND_Z = 4.0
"""A band is taken as present when its depth is this many of its standard
errors from zero: beside faces of uniform grey none is, and a chance one
would put a Type B on a clean line."""
DETECTOR_FLOOR = RIM_DETECTOR_ERROR
"""px: a displacement the model gives below this is not counted. It is the
detector's own error beside flat shading
(:data:`partinspect.vision.rim_errors.RIM_DETECTOR_ERROR`): a step of
uniform faces is fitted by the two Gaussian-blurred steps to within a grey
level (the pixel's box and the bilinear samples are not Gaussian), which on
a long line is significant and gives 0.000-0.004 px."""
START_DISTANCES = (1.5, 3.0)
"""px: the band's near flank is sought from these starts on either side
(the fit has local minima: a band read as the edge's own shoulder)."""
MIN_POINTS = 12
"""Fewer points (the matcher's least line) give no reading."""


def across_profile(image, uv, normal, reach=REACH, step=STEP):
    """The grey profile across a straight edge, averaged along it.

    Parameters
    ----------
    image : ndarray, shape (H, W)
        The image as recorded, grey levels.
    uv : ndarray, shape (N, 2)
        The line's edge points, distorted px.
    normal : ndarray, shape (N, 2)
        Their unit edge normals, dark to bright.
    reach, step : float
        The profile's extent either side and its sampling, px.

    Returns
    -------
    t : ndarray, shape (M,)
        Offsets along the normal, px (0 at the points).
    grey : ndarray, shape (M,)
        The mean grey at each offset over the points.
    """
    t = np.arange(-reach, reach + 0.5 * step, step)
    p = uv[:, None, :] + t[None, :, None] * normal[:, None, :]
    # Bilinear, clamped at the borders (map_coordinates takes rows first);
    # computed in double whatever the image's type, which is not copied.
    grey = map_coordinates(np.asarray(image), [p[..., 1].ravel(), p[..., 0].ravel()], order=1, mode="nearest",
                           output=np.float64)
    return t, grey.reshape(len(uv), len(t)).mean(axis=0)


def _design(t, t0, s, d, s2, w):
    """Columns of the model: level, edge of unit height, band of unit depth (its two flanks).

    Shape (M, 3) for scalar parameters; parameters of shape (K, 1) give (K, M, 3).
    """
    u, e = t - t0, np.sign(d)
    band = ndtr(e * (u - d) / s2) - ndtr(e * (u - d - e * w) / s2)
    return np.stack(np.broadcast_arrays(1.0, ndtr(u / s), band), axis=-1)


def two_step_fit(t, grey):
    """Fit a blurred step and a band beside it to a profile.

    ``grey(t) = a + c Phi((t - t0) / s) + h B(t)`` with the band
    ``B = Phi(e (u - d) / s2) - Phi(e (u - d - e w) / s2)``, ``u = t - t0``,
    ``e = sign(d)``: the edge (height c, place t0, width s) and the band
    (depth h, its near flank at signed distance d from the edge, its far
    flank w further out, both of width s2). The linear parameters
    (a, c, h) are solved for at each trial of the others (variable
    projection, [2]_); the second step is sought on both sides of the edge,
    from 0.5 px out.

    Parameters
    ----------
    t, grey : ndarray, shape (M,)
        :func:`across_profile`.

    Returns
    -------
    dict
        ``t0, s, d, s2, w, a, c, h`` and ``h_std``, the standard error of h
        from the fit's residuals (model misfit included), grey levels;
        None when no fit converges.
    """
    if grey[-1] == grey[0]:
        return None  # no step across the profile: nothing to fit
    best = None
    for side in (1.0, -1.0):
        for d0 in START_DISTANCES:
            lo = [-1.0, 0.3, 0.5, 0.3, 0.5] if side > 0 else [-1.0, 0.3, -REACH, 0.3, 0.5]
            hi = [1.0, 2.0, REACH, 2.5, 4 * REACH] if side > 0 else [1.0, 2.0, -0.5, 2.5, 4 * REACH]
            r = least_squares(lambda q: _projected_residuals(t, grey, q[None])[0], [0.0, 0.8, side * d0, 0.8, 2.0],
                              jac=lambda q: _projected_jacobian(t, grey, q), bounds=(lo, hi), ftol=1e-6, xtol=1e-6)
            if best is None or r.cost < best.cost:
                best = r
    if best is None or not np.isfinite(best.cost):
        return None
    t0, s, d, s2, w = best.x
    A = _design(t, *best.x)
    lin = np.linalg.lstsq(A, grey, rcond=None)[0]
    # The standard error of h with the nonlinear parameters free too: the
    # full Jacobian at the solution, the residuals' variance.
    J = np.c_[A, _model_jacobian(t, best.x, lin)]
    dof = max(len(t) - J.shape[1], 1)
    var = 2.0 * best.cost / dof
    cov = np.linalg.pinv(J.T @ J) * var
    return dict(t0=t0, s=s, d=d, s2=s2, w=w, a=lin[0], c=lin[1], h=lin[2], h_std=float(np.sqrt(max(cov[2, 2], 0.0))))


def _projected_residuals(t, grey, Q):
    """Residuals of the model with its linear parameters solved for, at each row of ``Q`` (K, 5): (K, M)."""
    A = _design(t, *(Q[:, k, None] for k in range(5)))
    AtA = np.einsum("kmi,kmj->kij", A, A) + 1e-9 * np.eye(3)
    lin = np.linalg.solve(AtA, np.einsum("kmi,m->ki", A, grey)[..., None])[..., 0]
    return np.einsum("kmi,ki->km", A, lin) - grey


def _projected_jacobian(t, grey, q):
    """Derivatives of :func:`_projected_residuals` at ``q`` (5,): (M, 5), Golub and Pereyra's [2]_.

    ``dr = P dA lin - A (A^T A)^-1 dA^T r``, P the projector off A's
    columns, ``dA`` the design's derivative (:func:`_model_jacobian` of its
    edge and band columns).
    """
    A = _design(t, *q)
    AtA = A.T @ A + 1e-9 * np.eye(3)
    lin = np.linalg.solve(AtA, A.T @ grey)
    r = A @ lin - grey
    D = _model_jacobian(t, q, lin)
    dAtr = np.stack([np.zeros(5), _model_jacobian(t, q, (0.0, 1.0, 0.0)).T @ r,
                     _model_jacobian(t, q, (0.0, 0.0, 1.0)).T @ r])
    return D - A @ np.linalg.solve(AtA, A.T @ D + dAtr)


def _model_jacobian(t, q, lin):
    """Derivatives of the model ``_design(t, *q) @ lin`` in its nonlinear parameters ``q = (t0, s, d, s2, w)``: (M, 5).

    Analytic: each flank ``Phi(z)`` changes by ``phi(z) dz``; the edge
    ``c Phi(u / s)`` moves with t0 and s, the band's flanks
    ``h Phi(z1)`` and ``-h Phi(z2)`` (``z1 = e (u - d) / s2``,
    ``z2 = e (u - d - e w) / s2``) with t0, d, s2 and w; ``e = sign(d)`` is
    constant within the fit's bounds (``|d| >= 0.5``).
    """
    t0, s, d, s2, w = q
    _, c, h = lin
    u, e = t - t0, np.sign(d)
    ze, z1, z2 = u / s, e * (u - d) / s2, e * (u - d - e * w) / s2
    pe, p1, p2 = (np.exp(-0.5 * z * z) / np.sqrt(2 * np.pi) for z in (ze, z1, z2))
    shift = -h * e * (p1 - p2) / s2  # the band moved outwards, flanks together
    return np.stack([-c * pe / s + shift, -c * pe * ze / s, shift, -h * (z1 * p1 - z2 * p2) / s2, h * p2 / s2],
                    axis=1)


def band_displacement(c, h, d, s, s2, w=np.inf, sigma=1.0):
    """Where the edge detector finds a step with a band beside it, px from the step.

    The detector takes the maximum of the Gaussian-smoothed gradient
    across the edge. On the model of :func:`two_step_fit` that gradient is
    ``c N(x; 0, S) + e h (N(x; d, S2) - N(x; d + e w, S2))`` (up to a
    common factor) with ``S^2 = s^2 + sigma^2``, ``S2^2 = s2^2 + sigma^2``,
    ``e = sign(d)``; without the band its maximum lies at 0. The maximum nearest the edge is found on a fine grid and refined
    by a parabola.

    Parameters
    ----------
    c, h : float
        Heights of the edge and the second step, grey levels (h of either
        sign; c's sign is the edge's polarity).
    d : float
        Signed distance of the band's near flank from the edge, px.
    s, s2 : float
        The edge's and the band's blur widths in the image, px.
    w : float
        Distance of the band's far flank beyond its near one, px.
    sigma : float
        The edge filter's scale, px.

    Returns
    -------
    float
        The displacement along the profile's coordinate, px.
    """
    S, S2 = np.hypot(s, sigma), np.hypot(s2, sigma)
    x = np.arange(-1.5 * S, 1.5 * S, 0.005)
    far = d + np.sign(d) * w
    band = np.exp(-0.5 * ((x - d) / S2) ** 2) - np.exp(-0.5 * ((x - far) / S2) ** 2)
    g = np.sign(c) * (c * np.exp(-0.5 * (x / S) ** 2) / S + np.sign(d) * h * band / S2)
    k = int(np.clip(np.argmax(g), 1, len(x) - 2))
    a, b, e = g[k - 1], g[k], g[k + 1]
    den = a - 2 * b + e
    return float(x[k] + (0.5 * (a - e) / den * 0.005 if den < 0 else 0.0))


def line_band_shift(image, uv, normal, sigma=1.0, bound=None):
    """The displacement of a line's points by a band beside it, px, or 0 when the profile shows none.

    :func:`across_profile` of the line's points, :func:`two_step_fit`, and,
    when the band's depth is ``BAND_Z`` standard errors from zero,
    :func:`band_displacement` of its fitted model, counted from
    ``DETECTOR_FLOOR`` up. A line is not corrected by it: the model reads
    75-90 % of the displacement of the synthetic bands (docs/validation.md)
    and its sign rests on one fit, so its magnitude goes into the Type B
    standard uncertainty of the line's offset in this image
    (:func:`partinspect.vision.stereo.line_type_b`, JCGM 100 F.2.4.5).

    Parameters
    ----------
    image : ndarray, shape (H, W)
    uv, normal : ndarray, shape (N, 2)
        The line's points and edge normals, distorted px.
    sigma : float
        The edge filter's scale, px.
    bound : ndarray, shape (N,), optional
        The points' ``EdgePoints.background_bound``. Where its median is 0
        no shading was read beside the line, 3-4 px off it, and no band is
        sought: a band within the step's response has its floor or far
        flank there (the bound of the synthetic bands is 0.013-0.1 px,
        docs/validation.md), and the fit is spared on the lines between
        faces of uniform grey.

    Returns
    -------
    float
        px, signed along the normals (dark to bright); 0 without a band.
    """
    uv, normal = np.asarray(uv, float), np.asarray(normal, float)
    if len(uv) < MIN_POINTS or (bound is not None and not np.median(bound) > 0):
        return 0.0
    t, grey = across_profile(image, uv, normal)
    fit = two_step_fit(t, grey)
    if fit is None or abs(fit["h"]) <= BAND_Z * fit["h_std"]:
        return 0.0
    shift = band_displacement(fit["c"], fit["h"], fit["d"], fit["s"], fit["s2"], fit["w"], sigma)
    return shift if abs(shift) > DETECTOR_FLOOR else 0.0
