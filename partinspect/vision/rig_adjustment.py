"""The bundle adjustment of a stereo rig's relative orientation to the edge points of circles it sees.

A 3D circle has 6 parameters and its two images, two ellipses, 10, so
every circle seen by both cameras leaves 4 conditions on the rig. The
unknowns here are the rig's parameters in :func:`rig_coordinates` (the
rotation vector of ``R``, ``T`` across its direction, the principal
points; any subset of them free) and each circle's centre, normal and
radius, started at its two-view fit. The residuals are the edge points'
distances to the projected circle (Sampson distances,
:mod:`partinspect.vision.fit3d`) over each point's standard uncertainty
across the edge, as the stereo chain states it; a prior's information on
the free rig parameters is added to the normal equations, so the
estimate is a maximum a posteriori one (:func:`adjust`).

Its covariance (:func:`posterior`) is a sandwich, since the points' noise
is correlated along the edge and a rim's systematic displacement with it,
plus the response to the errors of the prior's values and of the
parameters held at their stated values, which the images depend on too
("consider" parameters, :func:`consider_jacobians`).

Units: rad and mm for the rig, px for principal points; frames as
:mod:`partinspect.vision.calibration`.

References
----------
.. [1] Triggs, B., McLauchlan, P., Hartley, R., & Fitzgibbon, A. (2000).
       Bundle adjustment -- a modern synthesis. Vision Algorithms: Theory
       and Practice, LNCS 1883, 298-372 (sections 4 and 6: parametrisation,
       gauge, prior terms, covariance).
.. [2] Hartley, R., & Zisserman, A. (2004). Multiple View Geometry in
       Computer Vision, 2nd ed., sections 8.2 and 18.1.
.. [3] Quan, L. (1996). Conic reconstruction and correspondence from two
       views. IEEE PAMI 18(2), 151-160.
.. [4] JCGM 102:2011, 6.3 (multivariate propagation).
"""

from dataclasses import dataclass, replace

import cv2
import numpy as np

from partinspect.vision.calibration_uncertainty import perturbed_calibration
from partinspect.vision.fit3d import information_parts, minimal_residuals
from partinspect.vision.ideal import camera_matrices

__all__ = ["RefinementError", "CircleObservation", "circle_observations", "rig_coordinates", "rig_at", "rig_vector",
           "adjust", "consider_jacobians", "posterior"]

STEPS = {"r": 1e-6, "t": 1e-4, "c": 1e-3}
"""rad, mm, px: central-difference steps of the rig's parameters."""


class RefinementError(ValueError):
    """The images do not determine the rig (too few circles, or their configuration)."""


@dataclass(frozen=True)
class CircleObservation:
    """One measured circle or arc as the adjustment sees it.

    Attributes
    ----------
    views : list of View
        Its left and right edge points (ideal px) with their standard
        uncertainties, as the stereo chain fitted them.
    fit : Circle3D
        Its two-view fit: the start, and the basis of its tilts.
    dxy : list of ndarray, shape (N, 2, 4) or None
        Per view, the change of the ideal points with (cx1, cy1, cx2, cy2),
        px/px (ideal pixels depend on the principal point through the lens
        distortion); None without distortion.
    views_at : callable
        ``views_at(calib, remap=False)``: the views under another
        calibration (:func:`partinspect.vision.stereo.views_of`).
    """

    views: list
    fit: object
    dxy: list | None = None
    views_at: object = None


def circle_observations(stereo, indices, calib):
    """The :class:`CircleObservation` of measured circles of a :class:`~partinspect.vision.stereo.StereoResult`.

    Parameters
    ----------
    stereo : StereoResult
    indices : sequence of int
        Indices into ``stereo.features`` (circles and arcs), e.g. those the
        registration assigned to a CAD feature: that is all the CAD model
        contributes.
    calib : StereoCalibration
        The calibration they were measured with.

    Returns
    -------
    list of CircleObservation
    """
    from partinspect.vision.band_modes import edge_band
    from partinspect.vision.stereo import views_of

    out = []
    distorted = bool(np.any(calib.D1) or np.any(calib.D2))
    for i in indices:
        f = stereo.features[i]
        if f.kind == "line":
            continue
        fl, fr = stereo.left.features[f.left], stereo.right.features[f.right]
        corr_length = getattr(fl, "corr_length", None) or stereo.left.edges.sigma
        band = None if stereo.edge_break is None else edge_band(f.points, stereo.geometry, stereo.edge_break)
        views_at = views_of(fl, fr, corr_length, band)
        views = views_at(calib)
        dxy = None
        if distorted:
            dxy = [np.zeros((len(v.xy), 2, 4)) for v in views]
            for k in range(4):
                moved = []
                for sign in (1.0, -1.0):
                    K1, K2 = calib.K1.copy(), calib.K2.copy()
                    (K1 if k < 2 else K2)[k % 2, 2] += sign * STEPS["c"]
                    moved.append(views_at(replace(calib, K1=K1, K2=K2), remap=True))
                for n in range(2):
                    dxy[n][:, :, k] = (moved[0][n].xy - moved[1][n].xy) / (2 * STEPS["c"])
        out.append(CircleObservation(views, f.fit, dxy, views_at))
    return out


def rig_coordinates(calib):
    """The change of coordinates from the calibration's parameters to the rig's refinable ones.

    Parameters
    ----------
    calib : StereoCalibration

    Returns
    -------
    Z : ndarray, shape (n, n)
        Invertible; ``z = Z x`` for the parameters ``x`` in
        :func:`~partinspect.vision.calibration_uncertainty.full_covariance`'s
        order. Its first 9 rows: the rotation vector (3), ``T`` along two
        unit vectors normal to it (2), (cx1, cy1, cx2, cy2); then the
        baseline's length along ``T`` and every other parameter.
    basis : ndarray, shape (3, 3)
        Rows ``b1, b2, t_hat``: ``T`` in these coordinates is
        ``(z_3, z_4, length)``.
    """
    n1, n = 4 + np.size(calib.D1), 14 + np.size(calib.D1) + np.size(calib.D2)
    T = np.asarray(calib.T, float).ravel()
    t_hat = T / np.linalg.norm(T)
    b1 = np.cross(t_hat, [0.0, 1.0, 0.0])
    b1 /= np.linalg.norm(b1)
    basis = np.array([b1, np.cross(t_hat, b1), t_hat])
    eye = np.eye(n)
    along_T = np.zeros((3, n))
    along_T[:, n - 3:] = basis
    principal = [2, 3, n1 + 2, n1 + 3]
    rest = [i for i in range(n) if i not in set(principal) | set(range(n - 6, n))]
    Z = np.vstack([eye[n - 6:n - 3], along_T[:2], eye[principal], along_T[2:], eye[rest]])
    return Z, basis


def rig_at(calib, s, basis, length):
    """The calibration with the rig's parameters ``s`` (9, as :func:`rig_coordinates`' first rows)."""
    R = cv2.Rodrigues(np.asarray(s[:3], float).reshape(3, 1))[0]
    along = np.sqrt(max(length * length - s[3] ** 2 - s[4] ** 2, 0.0))
    T = s[3] * basis[0] + s[4] * basis[1] + along * basis[2]
    K1, K2 = np.array(calib.K1, float), np.array(calib.K2, float)
    K1[0, 2], K1[1, 2], K2[0, 2], K2[1, 2] = s[5:9]
    return replace(calib, R=R, T=T, K1=K1, K2=K2)


def rig_vector(calib, basis):
    """The rig's 9 parameters of :func:`rig_coordinates` (rotation vector, ``T`` along ``basis``' first two rows,
    principal points), shape (9,)."""
    T = np.asarray(calib.T, float).ravel()
    return np.r_[cv2.Rodrigues(np.asarray(calib.R, float))[0].ravel(), basis[0] @ T, basis[1] @ T,
                 calib.K1[0, 2], calib.K1[1, 2], calib.K2[0, 2], calib.K2[1, 2]]


def _circle_residuals(obs, calib, s, s0):
    """The weighted residuals of one circle's points under the rig ``s``, as a function of its minimal parameters, and its views."""
    P1, P2 = camera_matrices(calib)
    views = []
    for n, (v, P) in enumerate(zip(obs.views, (P1, P2))):
        xy = v.xy if obs.dxy is None else v.xy + obs.dxy[n] @ (np.asarray(s[5:9]) - s0[5:9])
        views.append(replace(v, P=P, xy=xy))
    res, _, _ = minimal_residuals(obs.fit, "arc", views)
    return res, views


def _blocks(observations, calib, s, s0, thetas, free, basis, length):
    """Residuals and Jacobian blocks of every circle: (r_i, J_i over the free rig parameters, J_i over its own 6)."""
    out = []
    steps = np.array([STEPS[k] for k in "rrrttcccc"])
    cal = rig_at(calib, s, basis, length)
    for obs, th in zip(observations, thetas):
        res, views = _circle_residuals(obs, cal, s, s0)
        r = res(th)
        h = 1e-6 * np.maximum(1.0, np.abs(th))
        rows = res.batch(np.concatenate([th + np.diag(h), th - np.diag(h)]))
        Jt = ((rows[:6] - rows[6:]) / (2 * h)[:, None]).T
        Js = np.empty((len(r), len(free)))
        for c, k in enumerate(free):
            side = []
            for sign in (1.0, -1.0):
                sk = np.array(s, float)
                sk[k] += sign * steps[k]
                res_k, _ = _circle_residuals(obs, rig_at(calib, sk, basis, length), sk, s0)
                side.append(res_k(th))
            Js[:, c] = (side[0] - side[1]) / (2 * steps[k])
        out.append((r, Js, Jt, views))
    return out


def _normal_equations(blocks, p, info, ds):
    """Dense normal matrix and gradient over (rig's free parameters, every circle's 6), with the prior."""
    m = p + 6 * len(blocks)
    H, g = np.zeros((m, m)), np.zeros(m)
    H[:p, :p] += info
    g[:p] += info @ ds
    for i, (r, Js, Jt, _) in enumerate(blocks):
        c = slice(p + 6 * i, p + 6 * i + 6)
        H[:p, :p] += Js.T @ Js
        H[:p, c] = Js.T @ Jt
        H[c, :p] = H[:p, c].T
        H[c, c] = Jt.T @ Jt
        g[:p] += Js.T @ r
        g[c] = Jt.T @ r
    return H, g


def _cost(blocks, info, ds):
    return float(sum(r @ r for r, *_ in blocks) + ds @ info @ ds)


def adjust(observations, calib, s0, start, thetas, free, info, basis, length, max_iter=30):
    """Levenberg-Marquardt on the joint normal equations; the solution and its last linearisation."""
    s = np.array(start, float)
    thetas = [np.array(t, float) for t in thetas]
    p = len(free)
    lam = 1e-6
    blocks = _blocks(observations, calib, s, s0, thetas, free, basis, length)
    cost = _cost(blocks, info, s[free] - s0[free])
    for _ in range(max_iter):
        H, g = _normal_equations(blocks, p, info, s[free] - s0[free])
        while True:
            step = np.linalg.solve(H + lam * np.diag(np.diag(H)), -g)
            s_new = s.copy()
            s_new[free] += step[:p]
            t_new = [t + step[p + 6 * i: p + 6 * i + 6] for i, t in enumerate(thetas)]
            b_new = _blocks(observations, calib, s_new, s0, t_new, free, basis, length)
            c_new = _cost(b_new, info, s_new[free] - s0[free])
            if c_new <= cost or lam > 1e8:
                break
            lam *= 10
        if c_new > cost:
            break
        done = cost - c_new <= 1e-10 * max(cost, 1e-300)
        s, thetas, blocks, cost, lam = s_new, t_new, b_new, c_new, max(lam / 10, 1e-9)
        if done:
            break
    return s, thetas, blocks, cost


def consider_jacobians(observations, cal, thetas, Zinv, consider, steps):
    """Per circle, the derivatives (N_i, q) of its weighted residuals along the fixed parameters that carry a stated uncertainty.

    Central differences at +-1 standard uncertainty of each (as
    :func:`~partinspect.vision.calibration_uncertainty.residual_changes`),
    the edge points mapped to ideal pixels again by the moved calibration.
    """
    sizes = (4 + np.size(cal.D1), 4 + np.size(cal.D2), 6)
    labels = [(g, k) for g, n in zip(("intrinsics1", "intrinsics2", "extrinsics"), sizes) for k in range(n)]
    out = []
    for obs, th in zip(observations, thetas):
        cols = []
        for j, h in zip(consider, steps):
            side = []
            for sign in (1.0, -1.0):
                dx = sign * h * Zinv[:, j]
                moved = perturbed_calibration(cal, {lab: v for lab, v in zip(labels, dx) if v != 0})
                res, _, _ = minimal_residuals(obs.fit, "arc", obs.views_at(moved, remap=True))
                side.append(res(th))
            cols.append((side[0] - side[1]) / (2 * h))
        n = sum(len(v.xy) for v in obs.views)
        out.append(np.stack(cols, 1) if cols else np.zeros((n, 0)))
    return out


def posterior(blocks, p, info, Jc, Cu):
    """Covariance of the estimate's error, its image-noise part, and its response to the prior's errors.

    The estimate solves ``H dx = -J^T e - L u_s + J^T J_c u_c`` to first
    order: ``e`` the points' errors, ``u_s`` the stated values' errors of
    the refined parameters (weighted by the prior's information ``L``) and
    ``u_c`` those of the parameters held at their stated values, which the
    images also depend on (``J_c``: a "consider" covariance). So the error
    is ``H^-1 (-J^T e) + K u`` with ``K = H^-1 [-L, J^T J_c]``, and its
    covariance ``H^-1 M H^-1 + K C_u K^T`` (``M`` the points' sandwich
    middle: noise correlated along the edge, and a rim's systematic part).

    Returns
    -------
    cov : ndarray, shape (m, m)
        Over (refined rig parameters, every circle's 6).
    noise : ndarray, shape (m, m)
        Its image-noise part.
    K : ndarray, shape (m, p + q)
        Response of the estimate to the prior errors ``u = (u_s, u_c)``.
    """
    H, _ = _normal_equations(blocks, p, info, np.zeros(p))
    m, q = H.shape[0], Jc[0].shape[1] if Jc else 0
    M, A = np.zeros((m, m)), np.zeros((m, p + q))
    A[:p, :p] = -info
    for i, (_, Js, Jt, views) in enumerate(blocks):
        idx = np.r_[np.arange(p), p + 6 * i + np.arange(6)]
        Jx = np.hstack([Js, Jt])
        _, Mr, Mb = information_parts(views, Jx)
        M[np.ix_(idx, idx)] += Mr + Mb
        A[idx, p:] += Jx.T @ Jc[i]
    d = np.sqrt(np.diag(H))
    if not np.all(d > 0) or np.linalg.cond(H / np.outer(d, d)) > 1e12:  # scaled: the parameters mix rad, mm, px
        raise RefinementError("the circles do not determine the rig's orientation (singular normal matrix)")
    Hinv = np.linalg.inv(H)
    noise = Hinv @ M @ Hinv
    K = Hinv @ A
    cov = noise + K @ Cu @ K.T
    return 0.5 * (cov + cov.T), 0.5 * (noise + noise.T), K
