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
tangencies are seen), they correct the rig, and their covariance is added
to the calibration's (Type B), so what the correction leaves uncertain is
carried into every 3D result.

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

from dataclasses import dataclass, field as dataclass_field, replace

import numpy as np

from partinspect.vision.calibration_uncertainty import full_covariance, with_extrinsic_covariance
from partinspect.vision.matching import epipolar_geometry
from partinspect.vision.psd import covariance_factor
from partinspect.vision.rim_errors import EDGE_BIAS_FLOOR

__all__ = ["TANGENT_REACH", "MIN_SIGNIFICANCE", "DriftEstimate", "tangent_offsets", "tangency_residuals",
           "estimate_drift", "drift_axes", "rotated_right_camera", "fit_drift", "predicted_residual_std",
           "MAX_DRIFT", "OUTLIER_Z", "CalibrationCheck", "check_calibration", "consistent_tangencies", "matched_arcs",
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
"""The roll is fitted only from this many tangencies on: with fewer, a
slope across the image is read from the rims' own scatter."""

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


def _observed(points, params, phase):
    if points is None or len(points) == 0:
        return False
    tp = _ellipse_points(params, np.array([phase]))[0]
    return bool(np.min(np.linalg.norm(np.asarray(points, float) - tp, axis=1)) <= TANGENT_REACH)


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
        px^2: the two fits' and, for each image, the rims' Type B edge
        displacement (:data:`partinspect.vision.rim_errors.EDGE_BIAS_FLOOR`), and
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
            # displacement the fits do not carry (EDGE_BIAS_FLOOR).
            v = (_offset_variance(band_left, fl.fit.params, fl.fit.cov, tl[k])
                 + _offset_variance(band_right, fr.fit.params, fr.fit.cov, tr[k]) + 2 * EDGE_BIAS_FLOOR**2)
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


def estimate_drift(residuals, variances, along=None, at=None):
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
        px. Without it, or with fewer than ``MIN_ROLL_TANGENCIES`` kept, or
        with the tangencies at one place, the field is a constant: the
        weighted mean.
    at : array_like, shape (m,), optional
        The part's edge points' place along the lines (:func:`along_lines`),
        px; default the tangencies'.

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
    linear = s_all is not None and keep.sum() >= MIN_ROLL_TANGENCIES and np.ptp(s_all[keep]) > _MIN_REACH
    coef, cov, left = _field_fit(r_all[keep], v_all[keep], s_all[keep] if linear else None)
    if linear:
        again = keep.copy()
        again[keep] = consistent_tangencies(left, v_all[keep])
        if not again.all() and again.sum() >= MIN_ROLL_TANGENCIES:
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
                         int((~keep).sum()), float(coef[1]), spread, coef, cov * enlarge**2)


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


def fit_drift(calib, pairs, tangencies=None, h=1e-5):
    """The turns of the right camera (:func:`drift_axes`) that bring the tangency residuals to zero.

    Weighted least squares on the residuals' central-difference Jacobian;
    only the turn about the baseline when fewer than
    ``MIN_ROLL_TANGENCIES`` tangencies are seen. The covariance is the
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
    axes = drift_axes(calib)[: 2 if len(r) >= MIN_ROLL_TANGENCIES else 1]
    J = np.empty((len(r), len(axes)))
    for k, axis in enumerate(axes):
        side = []
        for sign in (1.0, -1.0):
            moved = epipolar_geometry(rotated_right_camera(calib, sign * h * axis))
            side.append(tangency_residuals(moved, pairs, select, geo.ref_left)[0])
        J[:, k] = (side[0] - side[1]) / (2 * h)
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


def _weighted_fit(J, r, w):
    """Normal matrix, step and what is left of ``r`` after ``min sum w (r + J theta)^2``."""
    A = (J * w[:, None]).T @ J
    theta = -np.linalg.solve(A, J.T @ (w * r))
    return A, theta, r + J @ theta


def predicted_residual_std(calib, pairs, tangencies=None, along=None, at=None):
    """Standard deviation of the estimated residual (:func:`estimate_drift`) that the calibration's stated uncertainties allow, px.

    The calibration is moved along each principal direction of its stated
    covariance in turn (first order; independent parameters where it
    states only standard uncertainties), and the residual estimated as the
    check estimates it (the same tangencies, places and edge points); 0
    when it states none. ``tangencies`` as :func:`fit_drift`'s; ``along``,
    ``at`` as :func:`estimate_drift`'s.
    """
    from partinspect.vision.calibration_uncertainty import perturbed_calibration, uncertainty_directions

    geo = epipolar_geometry(calib)
    r, v, select = tangencies if tangencies is not None else tangency_residuals(geo, pairs)
    base = estimate_drift(r, v, along, at).shift
    total = 0.0
    for d in uncertainty_directions(calib):
        moved = perturbed_calibration(calib, d)
        r, v, _ = tangency_residuals(epipolar_geometry(moved), pairs, select, geo.ref_left)
        total += (estimate_drift(r, v, along, at).shift - base) ** 2
    return float(np.sqrt(total))


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
        uncertainty allows), "drifted" (beyond it; corrected, the
        correction's uncertainty carried), "invalid" (beyond ``MAX_DRIFT``:
        recalibrate) or "not checked" (no circle's tangencies seen in both
        images).
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
    """

    verdict: str
    drift: DriftEstimate
    predicted: float
    correction: np.ndarray
    correction_cov: np.ndarray
    birge_after: float
    calib: object

    @property
    def corrected(self):
        return bool(np.any(self.correction))

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
    predicted = predicted_residual_std(calib, pairs, tangencies, along, at)
    # Beyond the matcher's reach on the whole (a roll may put a few tangents further).
    if abs(drift.shift) > MAX_DRIFT or np.percentile(np.abs(drift.residuals), 75) > MAX_DRIFT:
        return CalibrationCheck("invalid", drift, predicted, *none, 1.0, calib)
    rotation, cov, birge = fit_drift(calib, pairs, tangencies)
    # Significant: some turn exceeds MIN_SIGNIFICANCE of its standard uncertainty.
    w, V = np.linalg.eigh(cov)
    z = np.abs(V.T @ rotation) / np.sqrt(np.where(w > 0, w, np.inf))
    if not np.any(z > MIN_SIGNIFICANCE):
        return CalibrationCheck("consistent", drift, predicted, *none, 1.0, calib)
    verdict = "consistent" if _within_stated(calib, rotation, cov, drift, predicted) else "drifted"
    return CalibrationCheck(verdict, drift, predicted, rotation, cov, birge, rotated_right_camera(calib, rotation, cov))


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
