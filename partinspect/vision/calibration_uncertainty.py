"""The calibration's standard uncertainties carried into the 3D features.

A stereo calibration may state standard uncertainties of its parameters
(``StereoCalibration.std``): the intrinsics and distortion of each camera
and the rotation and translation between them. A 3D feature depends on them
twice: its edge points are mapped to ideal pixels with the intrinsics and
distortion, and the two cameras built from all of them project its line or
circle. Its sensitivity to each parameter is found numerically, by central
differences at +-1 standard uncertainty: the edge points are mapped again
with the moved parameter, the cameras rebuilt, and one Gauss-Newton step of
the two-view fit (:mod:`partinspect.vision.fit3d`) taken from its solution,
which is the fit's first-order response. With the parameters taken as
uncorrelated, the covariance is the sum of the responses' outer products,
the law of propagation of uncertainty [1]_ (a Monte Carlo of the same
inputs, :mod:`partinspect.vision.montecarlo`, checks it [2]_).

Units: calibration parameters as OpenCV's (px for fx, fy, cx, cy; the
distortion coefficients unitless; rad for the rotation vector, mm for the
translation); feature parameters in the rig frame, mm, with unit vectors
for directions and normals.

References
----------
.. [1] JCGM 100:2008, Evaluation of measurement data -- Guide to the
       expression of uncertainty in measurement, section 5.1.2.
.. [2] JCGM 101:2008, Evaluation of measurement data -- Supplement 1 to the
       GUM: propagation of distributions using a Monte Carlo method.
"""

from dataclasses import replace

import cv2
import numpy as np

from partinspect.vision.fit3d import minimal_residuals

__all__ = ["calibration_parameters", "perturbed_calibration", "calibration_covariance"]


def calibration_parameters(calib):
    """Names, values and standard uncertainties of the calibration parameters with std > 0.

    Returns
    -------
    list of (str, int, float)
        ``(group, index, std)``: group "intrinsics1", "intrinsics2" or
        "extrinsics", index in OpenCV's order (fx, fy, cx, cy, D...; rx, ry,
        rz, tx, ty, tz).
    """
    out = []
    for group in ("intrinsics1", "intrinsics2", "extrinsics"):
        std = np.asarray(calib.std.get(group, ()), float).ravel()
        for k, s in enumerate(std):
            if s > 0:
                out.append((group, k, float(s)))
    return out


def perturbed_calibration(calib, deltas):
    """A copy of ``calib`` with parameters shifted: ``deltas`` maps (group, index) -> shift.

    Groups and indices as :func:`calibration_parameters`; the rotation is
    shifted in its Rodrigues vector (rad), the translation in mm.
    """
    K1, D1, K2, D2 = (np.array(a, float) for a in (calib.K1, calib.D1, calib.K2, calib.D2))
    R, T = np.array(calib.R, float), np.array(calib.T, float).ravel()
    rvec = cv2.Rodrigues(R)[0].ravel()
    for (group, k), d in deltas.items():
        if group == "extrinsics":
            if k < 3:
                rvec[k] += d
            else:
                T[k - 3] += d
            continue
        K, D = (K1, D1) if group == "intrinsics1" else (K2, D2)
        if k < 4:
            K[[0, 1, 0, 1][k], [0, 1, 2, 2][k]] += d
        else:
            D[k - 4] += d
    R = cv2.Rodrigues(rvec)[0]
    return replace(calib, K1=K1, D1=D1, K2=K2, D2=D2, R=R, T=T)


def calibration_covariance(fit, kind, views, calib):
    """Covariance of a 3D feature's parameters due to the calibration's uncertainty.

    Parameters
    ----------
    fit : Line3D or Circle3D
        The fit with the nominal calibration.
    kind : str
        "line" or "arc".
    views : callable
        ``views(calib)``: the fit's Views (:class:`partinspect.vision.fit3d.View`)
        under a calibration; ``views(calib, remap=True)`` with the edge
        points mapped to ideal pixels again by it (for a pair of image
        features, :func:`partinspect.vision.stereo.feature_views` with the
        two features and their correlation length bound).
    calib : StereoCalibration
        With ``std``.

    Returns
    -------
    ndarray, shape (6, 6) or (7, 7)
        Of (point, direction) or (center, normal, radius); zeros when the
        calibration has no standard uncertainties.

    Notes
    -----
    For each parameter p_k with standard uncertainty u_k the fit's
    minimal parameters respond, to first order, by one Gauss-Newton step
    from the solution: ``d theta = -(J^T J)^-1 J^T d r`` with ``d r`` the
    change of the weighted residuals when p_k moves; central differences at
    +-u_k give ``c_k u_k`` directly, and ``sum_k (c_k u_k)(c_k u_k)^T`` is
    the law of propagation for uncorrelated inputs (JCGM 100, 5.1.2).
    """
    params = calibration_parameters(calib)
    views0 = views(calib)
    res0, theta0, M = minimal_residuals(fit, kind, views0)
    n = M.shape[0]
    if not params:
        return np.zeros((n, n))
    h = 1e-6 * np.maximum(1.0, np.abs(theta0))
    J = np.stack([(res0(theta0 + e) - res0(theta0 - e)) / (2 * s) for e, s in zip(np.diag(h), h)], 1)
    pinv = np.linalg.pinv(J)
    cols = []
    for group, k, s in params:
        r = []
        for sign in (1.0, -1.0):
            cal = perturbed_calibration(calib, {(group, k): sign * s})
            res, _, _ = minimal_residuals(fit, kind, views(cal, remap=True))
            r.append(res(theta0))
        cols.append(-pinv @ (0.5 * (r[0] - r[1])))
    G = M @ np.stack(cols, 1)
    return G @ G.T
