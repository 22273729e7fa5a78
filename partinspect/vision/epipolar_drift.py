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

The weighted mean of the residuals estimates the drift across the epipolar
lines; its standard uncertainty is the weighted mean's, enlarged by the
Birge ratio where the residuals scatter more than their fits say (the
drift is then not one shift across the image). It is compared with what
the stated calibration's own standard uncertainties let the residual be.
The drift that shifts every epipolar line alike is a rotation of the
right camera about the baseline: that rotation, fitted to the residuals,
corrects the rig, and its uncertainty is added to the calibration's
(Type B, about the baseline), so what the correction leaves uncertain is
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

from dataclasses import dataclass, replace

import numpy as np

from partinspect.vision.matching import epipolar_geometry
from partinspect.vision.psd import covariance_factor

__all__ = ["TANGENT_REACH", "MIN_SIGNIFICANCE", "DriftEstimate", "tangent_offsets", "tangency_residuals",
           "estimate_drift", "rotated_about_baseline", "residual_per_radian", "predicted_residual_std",
           "MAX_DRIFT", "CalibrationCheck", "check_calibration", "matched_arcs"]

TANGENT_REACH = 2.0
"""px: a tangency is read only where the feature's own edge points come
this close to the fitted ellipse's tangent point; elsewhere the tangent
is the fit's extrapolation, not an observation."""

MIN_SIGNIFICANCE = 2.0
"""The rig is corrected when the estimated drift exceeds this many of its
standard uncertainties (a coverage factor of 2): a smaller one is not
told apart from zero by this pair."""

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
        Right minus left band offset of each tangency, px, and its variance
        from the two fits, px^2.
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
            v = (_offset_variance(band_left, fl.fit.params, fl.fit.cov, tl[k])
                 + _offset_variance(band_right, fr.fit.params, fr.fit.cov, tr[k]))
            if np.isfinite(v) and v > 0:
                res.append(orr[k] - ol[k])
                var.append(v)
                used.append((i, k))
    return np.array(res), np.array(var), used


@dataclass(frozen=True)
class DriftEstimate:
    """The pair's epipolar drift from the stated calibration.

    Attributes
    ----------
    shift : float
        Weighted mean epipolar residual, px (0 when none was measured).
    u : float
        Its standard uncertainty, px (inf when none was measured).
    n : int
        Tangencies it rests on.
    birge : float
        sqrt(chi-square / (n - 1)) of the residuals about the mean (1 when
        n < 2): above 1, they scatter more than their fits say.
    residuals : ndarray, shape (n,)
        px.
    """

    shift: float
    u: float
    n: int
    birge: float
    residuals: np.ndarray

    @property
    def significant(self):
        """Whether the drift is told apart from zero (``MIN_SIGNIFICANCE`` standard uncertainties)."""
        return self.n > 0 and abs(self.shift) > MIN_SIGNIFICANCE * self.u


def estimate_drift(residuals, variances):
    """Weighted mean of the tangency residuals with its uncertainty (Birge-enlarged).

    Parameters
    ----------
    residuals, variances : array_like, shape (n,)
        As :func:`tangency_residuals` returns.

    Returns
    -------
    DriftEstimate
    """
    r, v = np.asarray(residuals, float), np.asarray(variances, float)
    if len(r) == 0:
        return DriftEstimate(0.0, float("inf"), 0, 1.0, r)
    w = 1.0 / v
    mean = float(np.sum(w * r) / np.sum(w))
    u = float(np.sqrt(1.0 / np.sum(w)))
    birge = float(np.sqrt(np.sum(w * (r - mean) ** 2) / (len(r) - 1))) if len(r) > 1 else 1.0
    return DriftEstimate(mean, u * max(1.0, birge), len(r), birge, r)


def rotated_about_baseline(calib, angle, angle_std=0.0):
    """The calibration with the right camera turned about the baseline.

    Parameters
    ----------
    calib : StereoCalibration
    angle : float
        rad, right-handed about the baseline direction ``T / |T|`` in the
        right camera's frame: it turns every epipolar plane about the
        baseline alike, so it moves the epipolar lines across themselves and
        leaves ``T`` as it is.
    angle_std : float
        Standard uncertainty of ``angle``, rad: added in quadrature to the
        rotation's standard uncertainties along the baseline's components
        (the calibration states independent per-parameter uncertainties).

    Returns
    -------
    StereoCalibration
    """
    import cv2

    T = np.asarray(calib.T, float).ravel()
    axis = T / np.linalg.norm(T)
    Q = cv2.Rodrigues(axis * float(angle))[0]
    std = dict(calib.std)
    if angle_std > 0:
        ext = np.zeros(6) if "extrinsics" not in std else np.array(std["extrinsics"], float).ravel().copy()
        ext[:3] = np.sqrt(ext[:3] ** 2 + (axis * angle_std) ** 2)
        std["extrinsics"] = ext
    return replace(calib, R=Q @ np.asarray(calib.R, float), std=std)


def residual_per_radian(calib, pairs, h=1e-5):
    """d(mean tangency residual)/d(rotation about the baseline), px/rad, by a central difference."""
    geo = epipolar_geometry(calib)
    _, _, select = tangency_residuals(geo, pairs)
    means = []
    for sign in (1.0, -1.0):
        moved = epipolar_geometry(rotated_about_baseline(calib, sign * h))
        r, v, _ = tangency_residuals(moved, pairs, select, geo.ref_left)
        means.append(estimate_drift(r, v).shift)
    return (means[0] - means[1]) / (2 * h)


def predicted_residual_std(calib, pairs):
    """Standard deviation of the mean tangency residual that the calibration's stated uncertainties allow, px.

    Each parameter with a stated standard uncertainty is moved by it in
    turn (first order, parameters independent as stated); 0 when the
    calibration states none.
    """
    from partinspect.vision.calibration_uncertainty import calibration_parameters, perturbed_calibration

    geo = epipolar_geometry(calib)
    r, v, select = tangency_residuals(geo, pairs)
    base = estimate_drift(r, v).shift
    total = 0.0
    for group, k, s in calibration_parameters(calib):
        moved = perturbed_calibration(calib, {(group, k): s})
        r, v, _ = tangency_residuals(epipolar_geometry(moved), pairs, select, geo.ref_left)
        total += (estimate_drift(r, v).shift - base) ** 2
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
    correction : float
        Rotation of the right camera about the baseline applied, rad (0:
        none).
    correction_std : float
        Its standard uncertainty, rad, added to the calibration's.
    calib : StereoCalibration
        The calibration to measure with (corrected where the drift was
        significant).
    """

    verdict: str
    drift: DriftEstimate
    predicted: float
    correction: float
    correction_std: float
    calib: object

    def to_dict(self):
        """report.json's "calibration_check" (px and degrees)."""
        d = self.drift
        measured = d.n > 0
        bound = float(np.hypot(self.predicted, d.u)) if measured else None
        return {
            "verdict": self.verdict,
            "method": "epipolar tangency of matched circles (right minus left band offset)",
            "tangencies": d.n,
            "epipolar_residual_px": round(d.shift, 4) if measured else None,
            "standard_uncertainty_px": round(d.u, 4) if measured else None,
            "birge_ratio": round(d.birge, 3) if measured else None,
            "predicted_std_px": round(self.predicted, 4),
            "ratio_to_allowed": round(abs(d.shift) / bound, 3) if measured and bound > 0 else None,
            "correction_deg": round(float(np.degrees(self.correction)), 6),
            "correction_std_deg": round(float(np.degrees(self.correction_std)), 6),
        }

    def summary(self):
        """One line for the terminal and the report."""
        d = self.drift
        if d.n == 0:
            return "calibration not checked: no circle's epipolar tangencies seen in both images"
        text = (f"calibration {self.verdict}: epipolar residual {d.shift:+.3f} px (u {d.u:.3f} px, "
                f"{d.n} tangencies; stated calibration allows {self.predicted:.3f} px)")
        if self.correction:
            text += (f"; right camera turned {np.degrees(self.correction):+.5f} deg about the baseline "
                     f"(u {np.degrees(self.correction_std):.5f} deg, carried)")
        return text


def check_calibration(calib, pairs):
    """Check the stated calibration against matched ellipse pairs, and correct a significant drift.

    Parameters
    ----------
    calib : StereoCalibration
        As stated.
    pairs : sequence of (ImageFeature, ImageFeature)
        Matched arcs of the pair, measured with ``calib``.

    Returns
    -------
    CalibrationCheck
    """
    geo = epipolar_geometry(calib)
    r, v, _ = tangency_residuals(geo, pairs)
    drift = estimate_drift(r, v)
    if drift.n == 0:
        return CalibrationCheck("not checked", drift, 0.0, 0.0, 0.0, calib)
    predicted = predicted_residual_std(calib, pairs)
    if abs(drift.shift) > MAX_DRIFT:
        return CalibrationCheck("invalid", drift, predicted, 0.0, 0.0, calib)
    allowed = MIN_SIGNIFICANCE * float(np.hypot(predicted, drift.u))
    verdict = "consistent" if abs(drift.shift) <= allowed else "drifted"
    if not drift.significant:
        return CalibrationCheck(verdict, drift, predicted, 0.0, 0.0, calib)
    slope = residual_per_radian(calib, pairs)
    angle, angle_std = -drift.shift / slope, drift.u / abs(slope)
    return CalibrationCheck(verdict, drift, predicted, angle, angle_std,
                            rotated_about_baseline(calib, angle, angle_std))


def matched_arcs(stereo):
    """(left, right) image features of every matched pair of arcs of a :class:`StereoResult`."""
    L, R = stereo.left.features, stereo.right.features
    return [(L[m.left], R[m.right]) for m in stereo.matching.matches
            if L[m.left].kind != "line" and R[m.right].kind != "line"]
