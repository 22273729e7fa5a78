"""How far the image pair's epipolar geometry is from the stated calibration's, and its correction.

A stereo rig drifts after calibration (temperature, a knock, a refocus),
and then a point's partner no longer lies on its epipolar line. The image
pair itself measures this: the image of a circle is tangent to two
epipolar lines in each image, and for a matched pair the tangent lines
must be the same epipolar lines in both images (epipolar tangency [1]_,
[2]_). The difference of their band offsets (the signed distance across
the epipolar lines, :class:`~partinspect.vision.matching.EpipolarGeometry`)
is an epipolar residual of the stated calibration, in pixels, with an
uncertainty from the two ellipse fits.

A shift of the epipolar lines moves every tangency's residual alike, a
roll of the right camera in proportion to its place along the lines. The
residuals are therefore fitted as a field over the image, a constant plus
a term linear along the epipolar lines, and the residual is stated where
the part's edges are (the field's median over their points), with the
standard uncertainty the fit's covariance gives there, enlarged by the
Birge ratio where the residuals scatter about the field more than their
fits say; the field's spread over the edges is stated beside it. It is
compared with what the stated calibration's own covariance lets that
estimate be.
Two turns of the right camera about its centre move the epipolar lines
across themselves: about the baseline, alike everywhere, and about its
optical axis, in proportion to the distance along them. Fitted to the
residuals (weighted least squares; the second only where six or more
tangencies are seen, or three where their scatter about a constant asks
for it), they correct the rig, and their covariance is added
to the calibration's (Type B), so what the correction leaves uncertain is
carried into every 3D result.

The verdict follows the residuals' scatter about the field as well: one
beyond what their variances and the stated calibration allow
(:func:`field_scatter`) is not "consistent". Where even then too few
tangencies are seen to fit the roll, the roll that scatter asks for is
carried as a Type B uncertainty of the rig (:func:`unexplained_roll`), or
the run refused where it exceeds what a run carries.

Pixels are ideal (undistorted) pixel coordinates; angles in radians.

References
----------
.. [1] Porrill, J., & Pollard, S. (1991). Curve matching and stereo
       calibration. Image and Vision Computing 9(1), 45-50.
.. [2] Hartley, R., & Zisserman, A. (2004). Multiple View Geometry in
       Computer Vision, 2nd ed., sections 9.2 and 11.1 (epipolar lines,
       the fundamental matrix).
.. [3] JCGM 100:2008 (GUM), 4.2 (Type A) and 4.3 (Type B evaluation).
"""

import math
from dataclasses import dataclass, field as dataclass_field, replace

import numpy as np
from scipy.special import chdtrc  # what scipy.stats.chi2.sf evaluates, without scipy.stats' import time

from partinspect.vision.calibration_uncertainty import full_covariance, with_extrinsic_covariance
from partinspect.vision.matching import epipolar_geometry
from partinspect.vision.psd import covariance_factor
from partinspect.vision.rim_errors import BACKGROUND_CORRECTION, EDGE_BIAS_FLOOR, RIM_BOUND_READING

__all__ = ["TANGENT_REACH", "MIN_SIGNIFICANCE", "MIN_ROLL_TANGENCIES", "MIN_ROLL_DEMANDED", "SCATTER_P", "OUTLIER_Z",
           "MAX_DRIFT", "DriftEstimate", "tangent_offsets", "tangency_residuals", "estimate_drift", "drift_axes",
           "rotated_right_camera", "fit_drift", "predicted_residual_std", "stated_moves", "field_scatter",
           "unexplained_roll", "CalibrationCheck", "check_calibration", "consistent_tangencies", "matched_arcs",
           "matched_edge_points", "tangency_along", "along_lines"]

TANGENT_REACH = 2.0
"""px: a tangency is read only where the feature's own edge points come
this close to the fitted ellipse's tangent point; elsewhere the tangent
is the fit's extrapolation, not an observation."""

MIN_SIGNIFICANCE = 3.0
"""The rig is corrected when the estimated turn exceeds this many of its
standard uncertainties. Not 2: the rims' tangents carry small systematic
displacements of their own (shading beside a hole's wall), and a
correction made at the 5 % chance level would move an exact rig in one
run of twenty; 3 leaves that to 0.3 %, and a drift that loses features
(0.05 px and more) stands well above it."""

MIN_ROLL_TANGENCIES = 6
"""The roll is fitted from this many tangencies on: with fewer, a slope
across the image would be read from the rims' own scatter. With fewer but
at least ``MIN_ROLL_DEMANDED``, it is fitted where the tangencies' scatter
about a constant rejects the constant (:data:`SCATTER_P`): the scatter
then is the roll's, not the rims'."""

MIN_ROLL_DEMANDED = 3
"""Tangencies a demanded roll is fitted from: a constant and a slope, and
one degree of freedom left to judge the fit by (its Birge ratio)."""

SCATTER_P = math.erfc(MIN_SIGNIFICANCE / math.sqrt(2.0))
"""0.0027: the tangencies scatter about the fitted field beyond what their
variances and the stated calibration allow when the upper tail of its
chi-square (:func:`field_scatter`) is below this, the two-sided tail of a
normal distribution beyond ``MIN_SIGNIFICANCE`` standard deviations: the
level at which a turn is corrected."""

OUTLIER_Z = 3.0
"""A tangency whose residual lies further than this many robust standard
deviations (1.4826 MAD, combined with its own) from the others is left
out: a rim's tangent point beside an occluding edge or a shading step
reads a tangent that is not the circle's."""

_PHASES = 1440


def _ellipse_points(params, t):
    xc, yc, a, b, th = (float(v) for v in params)
    c, s = np.cos(th), np.sin(th)
    x, y = a * np.cos(t), b * np.sin(t)
    return np.c_[xc + c * x - s * y, yc + s * x + c * y]


def tangent_offsets(band, params):
    """The two extreme band offsets of an ellipse and the phases where they lie.

    Parameters
    ----------
    band : callable
        ``band(points (N, 2)) -> (N,)``: band offsets in one image, px.
    params : array_like, shape (5,)
        Ellipse (xc, yc, a, b, theta), ideal px and rad.

    Returns
    -------
    offsets : ndarray, shape (2,)
        Lowest and highest band offset, px.
    phases : ndarray, shape (2,)
        Their phases on the ellipse, rad (refined by a parabola through the
        three samples about each extreme).
    """
    t = np.linspace(0.0, 2 * np.pi, _PHASES, endpoint=False)
    f = band(_ellipse_points(params, t))
    out, phases = [], []
    for k, sign in ((int(np.argmin(f)), 1.0), (int(np.argmax(f)), -1.0)):
        fm, f0, fp = f[k - 1], f[k], f[(k + 1) % _PHASES]
        den = fm - 2 * f0 + fp
        shift = 0.5 * (fm - fp) / den if sign * den > 0 else 0.0
        tk = t[k] + shift * (t[1] - t[0])
        phases.append(tk)
        out.append(float(band(_ellipse_points(params, np.array([tk])))[0]))
    return np.array(out), np.array(phases)


def _offset_variance(band, params, cov, phase):
    """Variance of a tangent's band offset from the fit's covariance.

    At an extreme the offset does not change with the phase, so its
    gradient in the ellipse parameters is taken at the tangent point's
    fixed phase (envelope theorem).
    """
    p = np.asarray(params, float)
    g = np.empty(5)
    for k in range(5):
        h = 1e-6 * max(1.0, abs(p[k]))
        dp = np.zeros(5)
        dp[k] = h
        hi = band(_ellipse_points(p + dp, np.array([phase])))[0]
        lo = band(_ellipse_points(p - dp, np.array([phase])))[0]
        g[k] = (hi - lo) / (2 * h)
    C = np.where(np.isfinite(cov), cov, 0.0)  # a circle's free axis angle moves no tangent
    return float(np.sum((g @ covariance_factor(C)) ** 2))


def _nearest(points, params, phase):
    """(index, distance px) of the point nearest the ellipse's point at ``phase``; (None, inf) without points."""
    if points is None or len(points) == 0:
        return None, np.inf
    d = np.linalg.norm(np.asarray(points, float) - _ellipse_points(params, np.array([phase]))[0], axis=1)
    i = int(np.argmin(d))
    return i, float(d[i])


def _observed(points, params, phase):
    return _nearest(points, params, phase)[1] <= TANGENT_REACH


def tangency_residuals(geo, pairs, select=None, ref_left=None):
    """Epipolar residuals of matched ellipse pairs at their tangent epipolar lines.

    Parameters
    ----------
    geo : EpipolarGeometry
        Of the stated calibration.
    pairs : sequence of (ImageFeature, ImageFeature)
        Matched left and right arcs, each with ``fit.params``, ``fit.cov``
        (ideal px) and ``ideal.xy``.
    select : sequence of (int, int), optional
        (pair, tangency 0 lowest / 1 highest) to read, as a previous call
        returned them, so that residuals under a changed geometry compare
        like with like; default every tangency seen in both images.
    ref_left : ndarray, shape (2,), optional
        The ``ref_left`` of the geometry the residuals are compared with:
        band offsets are signed by it. The sense along the epipolar lines
        is a convention of each geometry, and a rig whose epipoles lie far
        outside the images can flip it under the smallest change.

    Returns
    -------
    residuals, variances : ndarray, shape (n,)
        Right minus left band offset of each tangency, px, and its variance,
        px^2: the two fits' and, for each image, the rim's Type B edge
        displacement at the tangent point (:func:`_shading_variance`), and
        the rim's own disagreement between its two tangencies
        (:func:`_with_rim_disagreement`).
    select : list of (int, int)
        Which tangencies they are.
    """
    sign = -1.0 if ref_left is not None and float(np.dot(geo.ref_left, ref_left)) < 0 else 1.0

    def band_left(x):
        return sign * geo.band_left(x)

    def band_right(y):
        return sign * geo.band_right(y)

    res, var, used = [], [], []
    for i, (fl, fr) in enumerate(pairs):
        if fl.fit.cov is None or fr.fit.cov is None:
            continue
        ol, tl = tangent_offsets(band_left, fl.fit.params)
        orr, tr = tangent_offsets(band_right, fr.fit.params)
        for k in range(2):
            if select is not None:
                if (i, k) not in select:
                    continue
            elif not (_observed(fl.ideal.xy, fl.fit.params, tl[k]) and _observed(fr.ideal.xy, fr.fit.params, tr[k])):
                continue
            # The fits' noise, and in each image the rim's Type B edge
            # displacement there, which the fits do not carry.
            v = (_offset_variance(band_left, fl.fit.params, fl.fit.cov, tl[k])
                 + _offset_variance(band_right, fr.fit.params, fr.fit.cov, tr[k])
                 + _shading_variance(fl, tl[k]) + _shading_variance(fr, tr[k]))
            if np.isfinite(v) and v > 0:
                res.append(orr[k] - ol[k])
                var.append(v)
                used.append((i, k))
    return np.array(res), _with_rim_disagreement(np.array(var), np.array(res), used), used


def tangency_along(geo, pairs, select):
    """Where the tangencies lie along the epipolar lines in the left image, px.

    Parameters
    ----------
    geo : EpipolarGeometry
    pairs : sequence of (ImageFeature, ImageFeature)
    select : sequence of (int, int)
        (pair, tangency) as :func:`tangency_residuals` returned them.

    Returns
    -------
    ndarray, shape (n,)
        Each left tangent point's distance along the epipolar lines from the
        left principal point (:func:`along_lines`), px.
    """
    out = []
    for i, k in select:
        params = pairs[i][0].fit.params
        _, phases = tangent_offsets(geo.band_left, params)
        out.append(_ellipse_points(params, phases[k:k + 1])[0])
    return along_lines(geo, np.reshape(out, (-1, 2)))


def along_lines(geo, points):
    """Left ideal points' (N, 2) coordinate along the epipolar lines, px (N,).

    The distance from the left principal point along ``geo.ref_left``: a
    turn of the right camera about its optical axis moves the epipolar
    lines across themselves in proportion to it.
    """
    return (np.asarray(points, float).reshape(-1, 2) - geo.center) @ geo.ref_left


def _shading_variance(f, phase):
    """Type B variance of a tangent's band offset from the shading beside the rim there, px^2.

    The tangents are read from the ellipse fitted to the points as found,
    before the shading correction the 3D fit makes
    (:mod:`partinspect.vision.rim_errors`), so the tangent point keeps the
    whole displacement that correction would remove: at most
    ``BACKGROUND_CORRECTION`` times the shading bound of the points there,
    read as a rectangular half-width (``RIM_BOUND_READING``, GUM 4.3.7).
    The ellipse's normal at a tangent point lies across the epipolar line,
    so the offset moves by the whole displacement; the bound is the
    nearest point's. ``EDGE_BIAS_FLOOR`` in quadrature is the detector's
    own error; a rim without shading readings carries that alone.
    """
    bound = getattr(f, "background_bound", None)
    floor2 = EDGE_BIAS_FLOOR * EDGE_BIAS_FLOOR
    if bound is None or f.ideal.xy is None or len(f.ideal.xy) != len(bound):
        return floor2
    b = float(bound[_nearest(f.ideal.xy, f.fit.params, phase)[0]])
    return (BACKGROUND_CORRECTION * RIM_BOUND_READING * b) ** 2 + floor2


def _with_rim_disagreement(var, res, used):
    """Variances with each rim's own Type B: what its two tangencies disagree by beyond their noise.

    A drift moves a rim's two tangencies alike (a shift exactly, a roll all
    but alike: they lie at about one distance from the principal point), so
    their difference shows the rim's own error, which the fits do not carry
    (a shading the background correction missed, a rim partly hidden). With
    an independent systematic ``b`` of variance ``s^2`` on each,
    ``E[(r_0 - r_1)^2] = v_0 + v_1 + 2 s^2``: ``s^2`` is estimated from that
    one difference, zero where it is within the noise, and added to both.
    """
    at = {key: n for n, key in enumerate(used)}
    out = var.copy()
    for (i, k), n in at.items():
        m = at.get((i, 1 - k))
        if m is not None:
            out[n] += max(0.0, 0.5 * ((res[n] - res[m]) ** 2 - var[n] - var[m]))
    return out


@dataclass(frozen=True)
class DriftEstimate:
    """The pair's epipolar drift from the stated calibration.

    Attributes
    ----------
    shift : float
        The epipolar residual at the part's edges, px (0 when none was
        measured): the median over the edge points of the residual field
        fitted to the tangencies (:func:`estimate_drift`).
    u : float
        Its standard uncertainty, px (inf when none was measured).
    n : int
        Tangencies it rests on.
    birge : float
        sqrt(chi-square / dof) of the residuals about the fitted field (1
        when nothing is left to judge): above 1, they scatter more than their
        fits say.
    residuals : ndarray, shape (n,)
        px, every tangency read (the ones left out too).
    outliers : int
        Tangencies left out (:data:`OUTLIER_Z`).
    slope : float
        The field's change along the epipolar lines, px per px (0: a
        constant field was fitted).
    spread : float
        Standard deviation of the fitted field over the part's edge points,
        px: how much the residual varies across the image.
    field : ndarray, shape (2,)
        The field ``r(s) = a + b s``: ``a`` at the left principal point, px,
        and ``b``, px per px (``s`` the place along the epipolar lines,
        :func:`along_lines`).
    field_cov : ndarray, shape (2, 2)
        Its covariance (Birge-enlarged).
    kept : ndarray of bool, shape (len(residuals),)
        Which residuals the field rests on.
    """

    shift: float
    u: float
    n: int
    birge: float
    residuals: np.ndarray
    outliers: int = 0
    slope: float = 0.0
    spread: float = 0.0
    field: np.ndarray = dataclass_field(default_factory=lambda: np.zeros(2))
    field_cov: np.ndarray = dataclass_field(default_factory=lambda: np.zeros((2, 2)))
    kept: np.ndarray = None


def estimate_drift(residuals, variances, along=None, at=None, min_roll=MIN_ROLL_TANGENCIES):
    """The epipolar residual at the part's edges: a field fitted to the tangencies, with its uncertainty.

    A shift of the epipolar lines moves every tangency alike; a turn of the
    right camera about its optical axis (a roll) moves them in proportion to
    their place along the lines, so that the residual changes sign across
    the image and the tangencies' mean says little of what the part's edges
    see. The residual is therefore fitted as a field, ``r(s) = a + b s``
    with ``s`` the place along the epipolar lines (weighted least squares,
    the tangencies' variances as weights), and stated at the median of the
    part's edge points, ``a + b median(s)`` (the median of a linear field
    is the field at the median place), with the standard uncertainty that
    the fit's covariance gives there, enlarged by the Birge ratio where the
    tangencies scatter about the field more than their fits say. A
    tangency that disagrees with the others (:func:`consistent_tangencies`)
    is left out, judged again about the fitted field.

    Parameters
    ----------
    residuals, variances : array_like, shape (n,)
        As :func:`tangency_residuals` returns, px and px^2.
    along : array_like, shape (n,), optional
        The tangencies' place along the epipolar lines (:func:`tangency_along`),
        px. Without it, or with fewer than ``min_roll`` kept, or
        with the tangencies at one place, the field is a constant: the
        weighted mean.
    at : array_like, shape (m,), optional
        The part's edge points' place along the lines (:func:`along_lines`),
        px; default the tangencies'.
    min_roll : int
        Tangencies a slope is fitted from (:data:`MIN_ROLL_TANGENCIES`).

    Returns
    -------
    DriftEstimate
    """
    r_all, v_all = np.asarray(residuals, float), np.asarray(variances, float)
    if len(r_all) == 0:
        return DriftEstimate(0.0, float("inf"), 0, 1.0, r_all)
    keep = consistent_tangencies(r_all, v_all)
    s_all = None if along is None else np.asarray(along, float)
    at = (s_all if at is None else np.asarray(at, float)) if s_all is not None else None
    linear = s_all is not None and keep.sum() >= min_roll and np.ptp(s_all[keep]) > _MIN_REACH
    coef, cov, left = _field_fit(r_all[keep], v_all[keep], s_all[keep] if linear else None)
    if linear:
        again = keep.copy()
        again[keep] = consistent_tangencies(left, v_all[keep])
        if not again.all() and again.sum() >= min_roll:
            keep = again
            coef, cov, left = _field_fit(r_all[keep], v_all[keep], s_all[keep])
    x = np.array([1.0, float(np.median(at))]) if linear else np.array([1.0])
    value, u2 = float(x @ coef), float(x @ cov @ x)
    spread = abs(coef[1]) * float(np.std(at)) if linear else 0.0
    if not linear:
        coef, cov = np.r_[coef, 0.0], np.diag([cov[0, 0], 0.0])
    dof = int(keep.sum()) - (2 if linear else 1)
    birge = float(np.sqrt(np.sum(left**2 / v_all[keep]) / dof)) if dof > 0 else 1.0
    enlarge = max(1.0, birge)
    return DriftEstimate(value, float(np.sqrt(u2)) * enlarge, int(keep.sum()), birge, r_all,
                         int((~keep).sum()), float(coef[1]), spread, coef, cov * enlarge**2, keep)


_MIN_REACH = 50.0
"""px: the tangencies must spread this far along the epipolar lines for a
slope to be fitted; closer, it would be read from the rims' own scatter."""


def _field_fit(r, v, s=None):
    """Weighted least squares ``r = a + b s`` (``r = a`` without ``s``): coefficients, covariance, what is left."""
    A = np.ones((len(r), 1)) if s is None else np.c_[np.ones(len(s)), s]
    w = 1.0 / v
    cov = np.linalg.inv((A * w[:, None]).T @ A)
    coef = cov @ (A.T @ (w * r))
    return coef, cov, r - A @ coef


def consistent_tangencies(deviations, variances):
    """Which tangencies agree with the others, boolean (n,); all of them when fewer than four.

    A deviation (a residual, or what a fit leaves of it) is kept within
    ``OUTLIER_Z`` times its robust standard deviation about the median:
    1.4826 times the median absolute deviation, in quadrature with its own
    standard uncertainty.
    """
    d, v = np.asarray(deviations, float), np.asarray(variances, float)
    if len(d) < 4:
        return np.ones(len(d), bool)
    off = np.abs(d - np.median(d))
    return off <= OUTLIER_Z * np.hypot(1.4826 * np.median(off), np.sqrt(v))


def drift_axes(calib):
    """Axes of the two turns of the right camera that move the epipolar lines across themselves.

    Returns
    -------
    ndarray, shape (2, 3)
        Unit axes in the right camera's frame: the baseline ``T / |T|`` (every
        epipolar plane turns about it alike), and the optical axis made
        orthogonal to it (a roll: the lines move in proportion to the distance
        along them).
    """
    T = np.asarray(calib.T, float).ravel()
    b = T / np.linalg.norm(T)
    z = np.array([0.0, 0.0, 1.0]) - b[2] * b
    return np.array([b, z / np.linalg.norm(z)])


def rotated_right_camera(calib, rotation, rotation_cov=None):
    """The calibration with the right camera turned about its centre.

    Parameters
    ----------
    calib : StereoCalibration
    rotation : array_like, shape (3,)
        Rotation vector, rad, in the right camera's frame: ``X_right`` becomes
        ``Q X_right``, so ``R`` becomes ``Q R`` and ``T`` becomes ``Q T``.
    rotation_cov : array_like, shape (3, 3), optional
        Its covariance, rad^2: carried to the rotation vector of ``R`` and to
        ``T`` to first order (``d rvec / d w`` numerically, ``d T = w x T``)
        and added to the calibration's stated covariance.

    Returns
    -------
    StereoCalibration
    """
    import cv2

    Q = cv2.Rodrigues(np.asarray(rotation, float).reshape(3, 1))[0]
    T = np.asarray(calib.T, float).ravel()
    turned = replace(calib, R=Q @ np.asarray(calib.R, float), T=Q @ T)
    if rotation_cov is None:
        return turned
    J = np.zeros((6, 3))
    r0 = cv2.Rodrigues(turned.R)[0].ravel()
    for k in range(3):
        e = np.zeros(3)
        e[k] = 1e-7
        J[:3, k] = (cv2.Rodrigues(cv2.Rodrigues(e)[0] @ turned.R)[0].ravel() - r0) / 1e-7
    J[3:] = np.array([[0.0, T[2], -T[1]], [-T[2], 0.0, T[0]], [T[1], -T[0], 0.0]])  # w x T = J w
    w, V = np.linalg.eigh(np.asarray(rotation_cov, float))
    F = J @ (V * np.sqrt(np.clip(w, 0.0, None)))  # a factor keeps the sum's diagonal non-negative
    return with_extrinsic_covariance(turned, F @ F.T)


def fit_drift(calib, pairs, tangencies=None, h=1e-5, min_roll=MIN_ROLL_TANGENCIES):
    """The turns of the right camera (:func:`drift_axes`) that bring the tangency residuals to zero.

    Weighted least squares on the residuals' central-difference Jacobian;
    only the turn about the baseline when fewer than ``min_roll``
    tangencies are seen. The covariance is the
    fit's, enlarged by the squared Birge ratio of what the turns leave where
    that exceeds 1. ``tangencies``: :func:`tangency_residuals` under
    ``calib``, if already read.

    Returns
    -------
    rotation : ndarray, shape (3,)
        Rotation vector, rad, right camera's frame.
    cov : ndarray, shape (3, 3)
        Its covariance, rad^2.
    birge : float
        Of the residuals after the turns (1 when nothing is left to judge).
    """
    geo = epipolar_geometry(calib)
    r, v, select = tangencies if tangencies is not None else tangency_residuals(geo, pairs)
    keep = consistent_tangencies(r, v)
    r, v, select = r[keep], v[keep], [s for s, k in zip(select, keep) if k]
    axes = drift_axes(calib)[: 2 if len(r) >= min_roll else 1]
    J = _turn_jacobian(calib, pairs, select, axes, h)
    w = 1.0 / v
    A, theta, left = _weighted_fit(J, r, w)
    again = consistent_tangencies(left, v)  # a roll spreads the residuals: judged after the turns too
    if not again.all() and again.sum() > len(axes):
        J, r, w = J[again], r[again], w[again]
        A, theta, left = _weighted_fit(J, r, w)
    dof = len(r) - len(axes)
    birge = float(np.sqrt(np.sum(w * left**2) / dof)) if dof > 0 else 1.0
    cov_theta = np.linalg.inv(A) * max(1.0, birge) ** 2
    return theta @ axes, axes.T @ cov_theta @ axes, birge


def _turn_jacobian(calib, pairs, select, axes, h=1e-5):
    """d residual / d turn of the right camera about each of ``axes`` (k, 3), px per rad, shape (n, k); central differences."""
    geo = epipolar_geometry(calib)
    J = np.empty((len(select), len(axes)))
    for k, axis in enumerate(axes):
        side = []
        for sign in (1.0, -1.0):
            moved = epipolar_geometry(rotated_right_camera(calib, sign * h * axis))
            side.append(tangency_residuals(moved, pairs, select, geo.ref_left)[0])
        J[:, k] = (side[0] - side[1]) / (2 * h)
    return J


def _weighted_fit(J, r, w):
    """Normal matrix, step and what is left of ``r`` after ``min sum w (r + J theta)^2``."""
    A = (J * w[:, None]).T @ J
    theta = -np.linalg.solve(A, J.T @ (w * r))
    return A, theta, r + J @ theta


def stated_moves(calib, pairs, select):
    """The tangencies read under the calibration moved along each principal direction of its stated covariance.

    Returns
    -------
    list of (residuals, variances)
        One per direction of
        :func:`~partinspect.vision.calibration_uncertainty.uncertainty_directions`
        (first order: a draw from the stated covariance moves the residuals
        by ``sum_j z_j (r_j - r)``), the same tangencies ``select`` signed
        by ``calib``'s geometry; empty when it states none.
    """
    from partinspect.vision.calibration_uncertainty import perturbed_calibration, uncertainty_directions

    ref = epipolar_geometry(calib).ref_left
    moves = []
    for d in uncertainty_directions(calib):
        r, v, _ = tangency_residuals(epipolar_geometry(perturbed_calibration(calib, d)), pairs, select, ref)
        moves.append((r, v))
    return moves


def predicted_residual_std(calib, pairs, tangencies=None, along=None, at=None, moves=None,
                           min_roll=MIN_ROLL_TANGENCIES):
    """Standard deviation of the estimated residual (:func:`estimate_drift`) that the calibration's stated uncertainties allow, px.

    The calibration is moved along each principal direction of its stated
    covariance in turn (first order; independent parameters where it
    states only standard uncertainties), and the residual estimated as the
    check estimates it (the same tangencies, places and edge points); 0
    when it states none. ``tangencies`` as :func:`fit_drift`'s; ``along``,
    ``at``, ``min_roll`` as :func:`estimate_drift`'s; ``moves``
    :func:`stated_moves`, if already read.
    """
    geo = epipolar_geometry(calib)
    r, v, select = tangencies if tangencies is not None else tangency_residuals(geo, pairs)
    base = estimate_drift(r, v, along, at, min_roll).shift
    moves = stated_moves(calib, pairs, select) if moves is None else moves
    return float(np.sqrt(sum((estimate_drift(rm, vm, along, at, min_roll).shift - base) ** 2 for rm, vm in moves)))


def field_scatter(residuals, variances, responses, design):
    """Chi-square of the tangencies about a fitted field, the stated calibration's own uncertainty allowed.

    A calibration within its stated covariance bends the epipolar lines a
    little differently across the image; the residuals may scatter by that
    much without the rig having drifted. Their covariance is therefore
    ``C = diag(variances) + D D^T`` (``D``: their first-order responses to the
    calibration along each principal direction of its stated covariance,
    :func:`stated_moves`), the field ``design @ c`` is fitted by generalised
    least squares, and what is left is judged by

        Q = r^T P r,  P = C^-1 - C^-1 A (A^T C^-1 A)^-1 A^T C^-1,

    chi-square distributed on ``n - k`` degrees of freedom were ``C`` right
    (``A`` the design, ``k`` its columns).

    Parameters
    ----------
    residuals, variances : array_like, shape (n,)
        px, px^2.
    responses : array_like, shape (n, q)
        ``D``, px; q may be 0.
    design : array_like, shape (n, k)
        The field's columns: ones, and the place along the lines for a slope.

    Returns
    -------
    Q : float
    dof : int
    P : ndarray, shape (n, n)
        The projector above, px^-2: ``x^T P x`` is what a further field ``x``
        over the tangencies adds to ``Q``'s expectation.
    """
    r, A = np.asarray(residuals, float), np.reshape(np.asarray(design, float), (len(residuals), -1))
    D = np.reshape(np.asarray(responses, float), (len(r), -1))
    Ci = np.linalg.inv(np.diag(np.asarray(variances, float)) + D @ D.T)
    CiA = Ci @ A
    P = Ci - CiA @ np.linalg.solve(A.T @ CiA, CiA.T)
    return float(r @ P @ r), len(r) - A.shape[1], P


def unexplained_roll(calib, pairs, select, Q, dof, P, h=1e-5):
    """The roll of the right camera that a constant field's excess scatter asks for, rad (its standard uncertainty).

    With fewer than ``MIN_ROLL_DEMANDED`` tangencies, or with all of them
    at one place along the lines, no roll is fitted (:func:`fit_drift`) and
    the field is a constant. If the tangencies then
    scatter about it beyond what their variances and the stated
    calibration allow (:func:`field_scatter`, :data:`SCATTER_P`), the
    residual varies across the image by more than the rims' errors explain,
    and a constant correction would leave that variation in every 3D
    result. Of the two turns of the right camera (:func:`drift_axes`) only
    the one about its optical axis moves the epipolar lines differently
    across the image; the excess is ascribed to it. A roll ``theta`` moves
    the residuals by ``theta J`` (``J`` their response, px per rad) and adds
    ``theta^2 J^T P J`` to ``Q``'s expectation ``dof``, so the
    method-of-moments estimate [4]_ is

        theta^2 = (Q - dof) / (J^T P J).

    Its sign is not determined, so the roll is not applied but carried as
    a Type B standard uncertainty (GUM 4.3) of the rig's rotation about that
    axis; the rims' own errors in the excess make it larger, not smaller.

    Parameters
    ----------
    calib : StereoCalibration
    pairs : sequence of (ImageFeature, ImageFeature)
    select : sequence of (int, int)
        The tangencies ``Q`` was read from (:func:`tangency_residuals`).
    Q, dof, P
        As :func:`field_scatter` returns them for a constant field.

    Returns
    -------
    float
        rad; 0 when ``Q`` does not exceed ``dof``, inf when no roll moves
        the tangencies apart (all at one place along the lines).

    References
    ----------
    .. [4] DerSimonian, R., & Laird, N. (1986). Meta-analysis in clinical
           trials. Controlled Clinical Trials 7(3), 177-188 (the moment
           estimate of an excess variance from Cochran's Q).
    """
    if Q <= dof:
        return 0.0
    J = _turn_jacobian(calib, pairs, select, drift_axes(calib)[1:], h)[:, 0]
    reach = float(J @ P @ J)
    return float(np.sqrt((Q - dof) / reach)) if reach > 0 else float("inf")


MAX_DRIFT = 3.0
"""px: the largest drift a run corrects. The matcher pairs features whose
epipolar bands overlap within its band tolerance (3 px); beyond it the
pairs themselves are in doubt, and the rig needs recalibrating."""


@dataclass(frozen=True)
class CalibrationCheck:
    """The stated calibration checked against this image pair.

    Attributes
    ----------
    verdict : str
        "consistent" (the drift lies within what the calibration's stated
        uncertainty allows, and so does the residuals' scatter about the
        field), "drifted" (beyond it; corrected, the correction's
        uncertainty carried, and where no roll could be fitted the roll the
        scatter asks for carried as Type B), "invalid" (beyond
        ``MAX_DRIFT``: recalibrate) or "not checked" (no circle's
        tangencies seen in both images).
    drift : DriftEstimate
        Before any correction.
    predicted : float
        Standard deviation of the drift the stated uncertainties allow, px.
    correction : ndarray, shape (3,)
        Rotation vector of the right camera's turn applied, rad, right
        camera's frame (zeros: none).
    correction_cov : ndarray, shape (3, 3)
        Its covariance, rad^2, added to the calibration's.
    birge_after : float
        Birge ratio of the residuals the correction leaves (1 without one).
    calib : StereoCalibration
        The calibration to measure with (corrected where the drift was
        significant).
    roll_type_b : float
        Standard uncertainty of the roll carried without a correction
        (:func:`unexplained_roll`), rad; 0 when none.
    scatter_p : float
        Upper tail of the chi-square of the tangencies about the fitted
        field, the stated calibration's uncertainty allowed
        (:func:`field_scatter`); 1 when nothing is left to judge.
    """

    verdict: str
    drift: DriftEstimate
    predicted: float
    correction: np.ndarray
    correction_cov: np.ndarray
    birge_after: float
    calib: object
    roll_type_b: float = 0.0
    scatter_p: float = 1.0

    @property
    def corrected(self):
        return bool(np.any(self.correction))

    @property
    def half_width(self):
        """Half the image's width, px: a roll of ``theta`` rad moves the epipolar lines at its sides by ``theta`` times it."""
        return 0.5 * float(self.calib.image_size[0])

    def refusal(self):
        """The one line an "invalid" check ends the run with."""
        d = self.drift
        if not np.isfinite(self.roll_type_b) or self.roll_type_b * self.half_width > MAX_DRIFT:
            return (f"the calibration does not fit these images: their epipolar residuals scatter beyond their "
                    f"uncertainty (Birge ratio {d.birge:.1f} on {d.n} tangencies, p {self.scatter_p:.1g}) by a roll of "
                    f"{self.roll_type_b * self.half_width:.1f} px at the image's sides, more than a run carries "
                    f"({MAX_DRIFT:g} px); recalibrate the rig")
        return (f"the calibration does not fit these images: their epipolar lines are {d.shift:+.2f} px off "
                f"(u {d.u:.2f} px), more than a run corrects; recalibrate the rig")

    def to_dict(self):
        """report.json's "calibration_check" (px and degrees)."""
        d = self.drift
        measured = d.n > 0
        bound = float(np.hypot(self.predicted, d.u)) if measured else None
        return {
            "verdict": self.verdict,
            "method": ("epipolar tangency of matched circles (right minus left band offset), fitted as a field "
                       "(constant + linear along the epipolar lines) and stated at the median of the part's edges"
                       if d.slope else "epipolar tangency of matched circles (right minus left band offset), "
                       "weighted mean"),
            "tangencies": d.n,
            "tangencies_left_out": d.outliers,
            "epipolar_residual_px": round(d.shift, 4) if measured else None,
            "standard_uncertainty_px": round(d.u, 4) if measured else None,
            "birge_ratio": round(d.birge, 3) if measured else None,
            "scatter_p_value": float(f"{self.scatter_p:.3g}") if measured else None,
            "roll_type_b_std_deg": round(float(np.degrees(self.roll_type_b)), 6),
            "roll_type_b_px_at_side": round(self.roll_type_b * self.half_width, 4),
            "residual_slope_px_per_1000px": round(1000 * d.slope, 4) if measured else None,
            "residual_slope_standard_uncertainty_px_per_1000px": (round(1000 * float(np.sqrt(d.field_cov[1, 1])), 4)
                                                                  if measured else None),
            "residual_at_principal_point_px": round(float(d.field[0]), 4) if measured else None,
            "residual_at_principal_point_standard_uncertainty_px": (round(float(np.sqrt(d.field_cov[0, 0])), 4)
                                                                    if measured else None),
            "residual_spread_px": round(d.spread, 4) if measured else None,
            "predicted_std_px": round(self.predicted, 4),
            "ratio_to_allowed": round(abs(d.shift) / bound, 3) if measured and bound > 0 else None,
            "correction_deg": round(float(np.degrees(np.linalg.norm(self.correction))), 6),
            "correction_std_deg": round(float(np.degrees(np.sqrt(np.trace(self.correction_cov)))), 6),
            "correction_rotation_vector_deg": [round(float(v), 6) for v in np.degrees(self.correction)],
            "birge_ratio_after": round(self.birge_after, 3),
        }

    def summary(self):
        """One line for the terminal and the report."""
        d = self.drift
        if d.n == 0:
            return "calibration not checked: no circle's epipolar tangencies seen in both images"
        text = (f"calibration {self.verdict}: epipolar residual {d.shift:+.3f} px (u {d.u:.3f} px, "
                f"{d.n} tangencies; stated calibration allows {self.predicted:.3f} px)")
        if d.spread:
            text += f", varying by {d.spread:.3f} px (SD) over the part's edges"
        if self.corrected:
            text += (f"; right camera turned {np.degrees(np.linalg.norm(self.correction)):.5f} deg "
                     f"(u {np.degrees(np.sqrt(np.trace(self.correction_cov))):.5f} deg, carried)")
        if self.roll_type_b:
            text += (f"; the tangencies scatter beyond their uncertainty (Birge ratio {d.birge:.2f}, p {self.scatter_p:.1g}) "
                     f"with too few to fit a roll: a roll of u {np.degrees(self.roll_type_b):.5f} deg "
                     f"({self.roll_type_b * self.half_width:.2f} px at the image's sides) carried as Type B")
        return text


def _within_stated(calib, rotation, cov, drift, predicted):
    """Whether a drift lies within what the calibration's stated uncertainty allows.

    The mean epipolar residual is compared with ``MIN_SIGNIFICANCE`` times
    its standard uncertainty combined with the one the stated calibration
    predicts (:func:`predicted_residual_std`: its full covariance where it
    states one); and the turn along each of :func:`drift_axes` with
    ``MIN_SIGNIFICANCE`` times its own standard uncertainty combined with
    the stated rotation's along that axis (a roll leaves the mean residual
    unchanged). Nothing stated: nothing but the measurement's own
    uncertainty is allowed.
    """
    if abs(drift.shift) > MIN_SIGNIFICANCE * np.hypot(predicted, drift.u):
        return False
    stated = full_covariance(calib)[-6:-3, -6:-3]  # the rotation vector's
    for axis in drift_axes(calib):
        allowed = np.sqrt(max(axis @ stated @ axis, 0.0) + max(axis @ cov @ axis, 0.0))
        if abs(axis @ rotation) > MIN_SIGNIFICANCE * allowed:
            return False
    return True


def check_calibration(calib, pairs, edges=None):
    """Check the stated calibration against matched ellipse pairs, and correct a significant drift.

    A scatter about a constant field beyond what the tangencies' variances
    and the stated calibration allow (:data:`SCATTER_P`) asks for the slope:
    it and the roll are fitted from ``MIN_ROLL_DEMANDED`` tangencies on. A
    scatter about the fitted field beyond it makes the rig "drifted"
    whatever the turns' significance: the fitted turns are applied with
    their covariance, and without a fitted slope the roll the scatter asks
    for is carried too (:func:`unexplained_roll`), so that every 3D result
    and the arc-pair test see it; "invalid" where that roll moves the
    image's sides by more than ``MAX_DRIFT``.

    Parameters
    ----------
    calib : StereoCalibration
        As stated.
    pairs : sequence of (ImageFeature, ImageFeature)
        Matched arcs of the pair, measured with ``calib``.
    edges : array_like, shape (N, 2), optional
        The part's matched edge points in the left image, ideal px
        (:func:`matched_edge_points`): where the residual is stated (its
        median over them); default the arcs' own.

    Returns
    -------
    CalibrationCheck
    """
    geo = epipolar_geometry(calib)
    tangencies = tangency_residuals(geo, pairs)
    if edges is None:
        edges = np.concatenate([np.reshape(fl.ideal.xy, (-1, 2)) for fl, _ in pairs]) if pairs else np.zeros((0, 2))
    along = tangency_along(geo, pairs, tangencies[2])
    at = along_lines(geo, edges) if len(edges) else None
    drift = estimate_drift(*tangencies[:2], along, at)
    none = np.zeros(3), np.zeros((3, 3))
    if drift.n == 0:
        return CalibrationCheck("not checked", drift, 0.0, *none, 1.0, calib)
    moves = stated_moves(calib, pairs, tangencies[2])
    min_roll = MIN_ROLL_TANGENCIES
    Q, dof, P, p = _scatter(drift, tangencies, along, moves)
    if p < SCATTER_P and not drift.field_cov[1, 1] > 0:
        # The scatter rejects a constant: the slope it asks for is fitted from as few as MIN_ROLL_DEMANDED.
        sloped = estimate_drift(*tangencies[:2], along, at, MIN_ROLL_DEMANDED)
        if sloped.field_cov[1, 1] > 0:
            min_roll, drift = MIN_ROLL_DEMANDED, sloped
            Q, dof, P, p = _scatter(drift, tangencies, along, moves)
    predicted = predicted_residual_std(calib, pairs, tangencies, along, at, moves, min_roll)
    # Beyond the matcher's reach on the whole (a roll may put a few tangents further).
    if abs(drift.shift) > MAX_DRIFT or np.percentile(np.abs(drift.residuals), 75) > MAX_DRIFT:
        return CalibrationCheck("invalid", drift, predicted, *none, 1.0, calib)
    rotation, cov, birge = fit_drift(calib, pairs, tangencies, min_roll=min_roll)
    if p < SCATTER_P:
        # The field does not explain the residuals: not consistent, whatever the turns' significance. The turns
        # are carried with their Birge-enlarged covariance; without a fitted slope, the roll the scatter asks for too.
        select = [t for t, keep in zip(tangencies[2], drift.kept) if keep]
        roll = 0.0 if drift.field_cov[1, 1] > 0 else unexplained_roll(calib, pairs, select, Q, dof, P)
        axis = drift_axes(calib)[1]
        check = CalibrationCheck("drifted", drift, predicted, rotation, cov, birge, calib, roll, p)
        if not np.isfinite(roll) or roll * check.half_width > MAX_DRIFT:
            return replace(check, verdict="invalid", correction=none[0], correction_cov=none[1], birge_after=1.0)
        cov = cov + roll**2 * np.outer(axis, axis)
        return replace(check, correction_cov=cov, calib=rotated_right_camera(calib, rotation, cov))
    # Significant: some turn exceeds MIN_SIGNIFICANCE of its standard uncertainty.
    w, V = np.linalg.eigh(cov)
    z = np.abs(V.T @ rotation) / np.sqrt(np.where(w > 0, w, np.inf))
    if not np.any(z > MIN_SIGNIFICANCE):
        return CalibrationCheck("consistent", drift, predicted, *none, 1.0, calib, scatter_p=p)
    verdict = "consistent" if _within_stated(calib, rotation, cov, drift, predicted) else "drifted"
    return CalibrationCheck(verdict, drift, predicted, rotation, cov, birge, rotated_right_camera(calib, rotation, cov),
                            scatter_p=p)


def _scatter(drift, tangencies, along, moves):
    """:func:`field_scatter` of the tangencies ``drift`` kept about its field: (Q, dof, P, upper tail of Q)."""
    r, v, _ = tangencies
    k = drift.kept
    design = np.c_[np.ones(k.sum()), along[k]] if drift.field_cov[1, 1] > 0 else np.ones((k.sum(), 1))
    D = np.stack([rm[k] - r[k] for rm, _ in moves], 1) if moves else np.zeros((k.sum(), 0))
    Q, dof, P = field_scatter(r[k], v[k], D, design)
    return Q, dof, P, (float(chdtrc(dof, Q)) if dof > 0 else 1.0)


def matched_edge_points(stereo):
    """The left ideal edge points (N, 2), px, of every matched pair of a :class:`StereoResult`, lines and arcs."""
    L = stereo.left.features
    points = [np.reshape(L[m.left].ideal.xy, (-1, 2)) for m in stereo.matching.matches]
    return np.concatenate(points) if points else np.zeros((0, 2))


def matched_arcs(stereo):
    """(left, right) image features of every matched pair of arcs of a :class:`StereoResult`."""
    L, R = stereo.left.features, stereo.right.features
    return [(L[m.left], R[m.right]) for m in stereo.matching.matches
            if L[m.left].kind != "line" and R[m.right].kind != "line"]
