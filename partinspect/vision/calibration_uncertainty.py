"""The calibration's uncertainty (its covariance, or its standard uncertainties) carried into the 3D features.

A stereo calibration may state standard uncertainties of its parameters
(``StereoCalibration.std``): the intrinsics and distortion of each camera
and the rotation and translation between them. A 3D feature depends on them
twice: its edge points are mapped to ideal pixels with the intrinsics and
distortion, and the two cameras built from all of them project its line or
circle. Its sensitivity to each parameter is found numerically, by central
differences at +-1 standard uncertainty: the edge points are mapped again
with the moved parameter, the cameras rebuilt, and one Gauss-Newton step of
the two-view fit (:mod:`partinspect.vision.fit3d`) taken from its solution,
which is the fit's first-order response. The parameters are moved along
the principal directions of their stated covariance
(:func:`uncertainty_directions`), each by its standard deviation, so that
the sum of the responses' outer products is the law of propagation of
uncertainty for correlated inputs [1]_ (a Monte Carlo of the same inputs,
:mod:`partinspect.vision.montecarlo`, checks it [2]_). A calibration that
states only per-parameter standard uncertainties is taken as uncorrelated;
that overstates what depends on the epipolar geometry, which a
calibration's correlated errors leave far better known.

Units: calibration parameters as OpenCV's (px for fx, fy, cx, cy; the
distortion coefficients unitless; rad for the rotation vector, mm for the
translation); feature parameters in the rig frame, mm, with unit vectors
for directions and normals.

References
----------
.. [1] JCGM 100:2008, Evaluation of measurement data -- Guide to the
       expression of uncertainty in measurement, sections 5.1.2 and 5.2.2.
.. [2] JCGM 101:2008, Evaluation of measurement data -- Supplement 1 to the
       GUM: propagation of distributions using a Monte Carlo method.
"""

from dataclasses import replace

import cv2
import numpy as np

from partinspect.vision.fit3d import minimal_residuals

__all__ = [
    "calibration_parameters",
    "full_covariance",
    "stated_covariance",
    "uncertainty_directions",
    "perturbed_calibration",
    "with_extrinsic_covariance",
    "calibration_responses",
    "residual_changes",
    "calibration_covariance",
    "budget_entry",
]

_GROUPS = ("intrinsics1", "intrinsics2", "extrinsics")


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
    for group in _GROUPS:
        std = np.asarray(calib.std.get(group, ()), float).ravel()
        for k, s in enumerate(std):
            if s > 0:
                out.append((group, k, float(s)))
    return out


def full_covariance(calib):
    """The covariance of all the calibration's parameters, shape (n, n), n = 14 + len(D1) + len(D2).

    Order: intrinsics1, intrinsics2, extrinsics (as :func:`calibration_parameters`);
    ``calib.cov``, or the squared standard uncertainties on the diagonal
    (zeros where none is stated).
    """
    if calib.cov is not None:
        return np.array(calib.cov, float)
    sizes = (4 + np.size(calib.D1), 4 + np.size(calib.D2), 6)
    var = [np.asarray(calib.std.get(g, np.zeros(n)), float).ravel() ** 2 for g, n in zip(_GROUPS, sizes)]
    return np.diag(np.concatenate(var))


def stated_covariance(calib):
    """The covariance the calibration states for its parameters with std > 0.

    Returns
    -------
    labels : list of (str, int)
        ``(group, index)`` as :func:`calibration_parameters`.
    cov : ndarray, shape (n, n)
        :func:`full_covariance` restricted to them.
    """
    sizes = (4 + np.size(calib.D1), 4 + np.size(calib.D2), 6)
    every = [(g, k) for g, n in zip(_GROUPS, sizes) for k in range(n)]
    C = full_covariance(calib)
    idx = [i for i in range(len(every)) if C[i, i] > 0]
    return [every[i] for i in idx], C[np.ix_(idx, idx)]


def with_extrinsic_covariance(calib, cov_rt):
    """The calibration with a covariance added to that of its (rotation vector, T).

    Parameters
    ----------
    calib : StereoCalibration
    cov_rt : ndarray, shape (6, 6)
        rad and mm, order (rx, ry, rz, tx, ty, tz).

    Returns
    -------
    StereoCalibration
        With ``cov`` (the stated one, or the stated standard uncertainties
        as a diagonal, plus ``cov_rt`` on the extrinsics' block) and ``std``
        its diagonal's square root.
    """
    from partinspect.vision.calibration import validate_calibration

    C = full_covariance(calib)
    C[-6:, -6:] += cov_rt
    return validate_calibration(replace(calib, std={}, cov=C))


def uncertainty_directions(calib, rtol=1e-12):
    """Parameter shifts whose outer products sum to the stated covariance.

    The covariance is scaled to a correlation matrix first (its parameters
    mix px, rad and mm), decomposed ``C = S V W V^T S``, and each principal
    direction returned scaled by its standard deviation, ``S v_j
    sqrt(w_j)``: moving the calibration along each in turn and adding the
    outer products of a result's responses is the law of propagation for
    correlated inputs (JCGM 100, 5.2.2), and ``sum_j z_j d_j`` with
    independent standard normal ``z_j`` is a draw from the covariance.
    Directions whose variance is below ``rtol`` of the largest carry
    nothing and are left out.

    Returns
    -------
    list of dict
        Each ``{(group, index): shift}``, as :func:`perturbed_calibration`
        takes it; empty when the calibration states no uncertainty.
    """
    labels, C = stated_covariance(calib)
    if not labels:
        return []
    if calib.cov is None:
        return [{lab: float(np.sqrt(c))} for lab, c in zip(labels, np.diag(C))]
    s = np.sqrt(np.diag(C))
    w, V = np.linalg.eigh(C / np.outer(s, s))
    keep = w > rtol * w.max()
    D = (s[:, None] * V[:, keep]) * np.sqrt(w[keep])
    return [dict(zip(labels, col)) for col in D.T]


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


def calibration_responses(fit, kind, views, calib):
    """First-order responses of a 3D feature's parameters to the calibration's uncertainty.

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
        With ``std``, and ``cov`` where it states one.

    Returns
    -------
    ndarray, shape (6, q) or (7, q)
        Column j: the change of (point, direction) or (center, normal,
        radius) when the calibration moves along the j-th of its q
        :func:`uncertainty_directions` (q = 0 when it states none). The
        feature's calibration covariance is ``G G^T``; two features measured
        with the same calibration share its error, and their
        cross-covariance is ``G_a G_b^T``.

    Notes
    -----
    Along each direction d_j of :func:`uncertainty_directions` the fit's
    minimal parameters respond, to first order, by one Gauss-Newton step
    from the solution: ``d theta = -(J^T J)^-1 J^T d r`` with ``d r`` the
    change of the weighted residuals when the calibration moves by d_j;
    central differences at +-d_j give the response ``g_j`` directly (a
    radius responds to some directions at second order only, which a
    one-sided difference would read as first), and
    ``sum_j g_j g_j^T = G C G^T`` is the law of propagation (JCGM 100,
    5.2.2).
    """
    changes = residual_changes(fit, kind, views, calib)
    if changes is None:
        return np.zeros((6 if kind == "line" else 7, 0))
    _, J, D, M = changes
    return M @ (-np.linalg.pinv(J) @ D)


def residual_changes(fit, kind, views, calib):
    """How a fit's weighted residuals move with the calibration, at its solution.

    Parameters as :func:`calibration_responses`.

    Returns
    -------
    (r0, J, D, M) or None
        ``r0`` (N,) the weighted residuals at the solution; ``J`` (N, p)
        their Jacobian in the fit's minimal parameters; ``D`` (N, q) their
        change along each of the q :func:`uncertainty_directions` (central
        differences, the points mapped again: a radius responds to some
        directions only at second order, which a one-sided difference would
        read as first); ``M`` as
        :func:`partinspect.vision.fit3d.minimal_residuals`. None when the
        calibration states no uncertainty.
    """
    directions = uncertainty_directions(calib)
    if not directions:
        return None
    res0, theta0, M = minimal_residuals(fit, kind, views(calib))
    h = 1e-6 * np.maximum(1.0, np.abs(theta0))
    J = np.stack([(res0(theta0 + e) - res0(theta0 - e)) / (2 * s) for e, s in zip(np.diag(h), h)], 1)
    cols = []
    for d in directions:
        r = []
        for sign in (1.0, -1.0):
            cal = perturbed_calibration(calib, {lab: sign * v for lab, v in d.items()})
            res, _, _ = minimal_residuals(fit, kind, views(cal, remap=True))
            r.append(res(theta0))
        cols.append(0.5 * (r[0] - r[1]))
    return res0(theta0), J, np.stack(cols, 1), M


def calibration_covariance(fit, kind, views, calib):
    """Covariance of a 3D feature's parameters due to the calibration's uncertainty.

    ``G G^T`` of :func:`calibration_responses` (same parameters); shape
    (6, 6) or (7, 7), zeros when the calibration states no uncertainty.
    """
    G = calibration_responses(fit, kind, views, calib)
    return G @ G.T


def budget_entry(calib):
    """report.json's ``uncertainty.calibration``: how the calibration's uncertainty enters the budget.

    Returns
    -------
    dict
        ``stated``: "covariance" (its parameters' full covariance, carried
        with the error all features share), "standard uncertainties" (taken
        as independent: every result that depends on the epipolar geometry
        is overstated) or "none" (the budget is incomplete: the
        calibration's error is in no stated uncertainty); ``parameters``:
        how many have a stated uncertainty; ``complete``: whether the
        budget holds the calibration as a calibration states it.
    """
    n = len(calibration_parameters(calib))
    stated = "none" if n == 0 else ("covariance" if calib.cov is not None else "standard uncertainties")
    return {"stated": stated, "parameters": n, "complete": stated == "covariance"}
