"""The rig's relative orientation re-estimated from the part's own circles: a bundle adjustment with the stated calibration as prior.

A stated calibration is one board session's estimate, and the rig may
have moved since. The part's circles measure it again: a 3D circle has 6
parameters and its two images, two ellipses, 10, so every circle seen by
both cameras leaves 4 conditions on the rig. Its unknowns here are the
relative orientation (the rotation vector of ``R`` and the direction of
``T``: 5 parameters) and, where the images determine them, the principal
points; each circle's centre, normal and radius are unknowns too, started
at their two-view fits. The residuals are the edge points' distances to
the projected circle (Sampson distances, :mod:`partinspect.vision.fit3d`)
over each point's standard uncertainty across the edge, as the stereo
chain states it. The stated calibration's covariance is the prior, so the
estimate is a maximum a posteriori one, and its posterior covariance
(a sandwich: the points' noise is correlated along the edge, and a rim's
systematic displacement with it) replaces the stated one in the
calibration the run measures with.

Three rules keep it metrology rather than curve fitting.

- The CAD model's nominal geometry is never a target: a part 0.1 mm
  oversize would otherwise "calibrate" the rig until it read nominal. The
  registration only says which measured circles are the part's (the
  association); their 3D parameters stay free.
- The baseline's length is not determined by images (a rig twice as wide
  sees a part twice as large alike): it keeps its stated value and
  uncertainty, and only the direction of ``T`` is refined.
- A parameter with a stated uncertainty is refined only where the images
  bring its standard uncertainty below ``DETERMINED`` of the prior's; near
  the image centre a principal point trades almost one for one with a turn
  of its camera, and the convergence angle is seen only through the
  circles' roundness. Otherwise it is held at its stated value, its
  uncertainty carried, and that is said.

When the run's calibration check found the rig drifted
(:mod:`partinspect.vision.epipolar_drift`), the stated rig is known to be
off by more than its uncertainty, along the turn the check measured. The
prior is then widened by that turn as a Type B component (its outer
product and its covariance, JCGM 100 4.3.7), independent of the
calibration's own errors, so that the images, not the stale calibration,
decide along it, while the stated covariance still holds the directions
the circles hardly see (the convergence angle trades with the baseline's
direction, and a principal point with its camera's turn). Where the
calibration states no uncertainty the prior is flat: the images alone.

Every other parameter with a stated uncertainty (focal lengths,
distortion, the baseline's length, principal points held) keeps its value,
but the images depend on it too: it is a "consider" parameter, its error
carried through the adjustment's response to it, so that the posterior is
the joint covariance of the refined parameters' errors and the held ones'
(:func:`_posterior`, :func:`_with_posterior`).

The correction of each parameter is reported with its posterior standard
uncertainty, the stated one, and its significance against the stated
calibration: under "the stated calibration is right", the correction
``d = s_hat - s_0`` has covariance ``V = G C G^T + C_n`` (``C`` the stated
covariance of the refined and held parameters, ``G`` the correction's
response to their errors, ``C_n`` the image noise's part of the
posterior); about ``S - P`` for a refined parameter's stated ``S`` and
posterior ``P``, and ``P`` where none is stated.

Units: rad and mm for the rig (degrees in reports), px for principal
points; frames as :mod:`partinspect.vision.calibration`.

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
.. [4] JCGM 100:2008 (GUM), 5.2.2; JCGM 102:2011, 6.3 (multivariate
       propagation).
"""

from dataclasses import dataclass, replace

import cv2
import numpy as np
from scipy.special import chdtrc

from partinspect.vision.calibration import validate_calibration
from partinspect.vision.calibration_uncertainty import full_covariance, perturbed_calibration
from partinspect.vision.fit3d import information_parts, minimal_residuals
from partinspect.vision.ideal import camera_matrices

__all__ = ["MIN_CIRCLES", "DETERMINED", "SIGNIFICANCE", "RefinementError", "RigRefinement", "CircleObservation",
           "circle_observations", "refine_rig", "rig_coordinates"]

MIN_CIRCLES = 3
"""Circles the adjustment needs: each leaves 4 conditions on the rig, and
with no stated prior 5 parameters are free; three keep the
relative orientation determined where two would leave it barely so."""

DETERMINED = 0.5
"""A parameter with a stated uncertainty is refined only where the images
bring its standard uncertainty below this fraction of the prior's (its
variance to a quarter: the images know three times what the calibration
did). A weaker reading is mostly the images' own systematic errors and the
held parameters' (a principal point trades with its camera's turn, the
convergence angle with the baseline's direction and the focal lengths),
and moving it would make the rig worse than stated (the convergence
angle sets the scale in depth: a diameter follows it)."""

SIGNIFICANCE = 3.0
"""A correction is called significant beyond this many standard
deviations of what the stated calibration lets it be (per parameter), or
at the matching chi-square level jointly."""

_STEPS = {"r": 1e-6, "t": 1e-4, "c": 1e-3}  # rad, mm, px: central-difference steps of the rig's parameters
_NAMES = ("rx", "ry", "rz", "tb1", "tb2", "cx1", "cy1", "cx2", "cy2")


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
    from partinspect.vision.stereo import edge_band, views_of

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
                    (K1 if k < 2 else K2)[k % 2, 2] += sign * _STEPS["c"]
                    moved.append(views_at(replace(calib, K1=K1, K2=K2), remap=True))
                for n in range(2):
                    dxy[n][:, :, k] = (moved[0][n].xy - moved[1][n].xy) / (2 * _STEPS["c"])
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


def _rig_at(calib, s, basis, length):
    """The calibration with the rig's parameters ``s`` (9, as :func:`rig_coordinates`' first rows)."""
    R = cv2.Rodrigues(np.asarray(s[:3], float).reshape(3, 1))[0]
    along = np.sqrt(max(length * length - s[3] ** 2 - s[4] ** 2, 0.0))
    T = s[3] * basis[0] + s[4] * basis[1] + along * basis[2]
    K1, K2 = np.array(calib.K1, float), np.array(calib.K2, float)
    K1[0, 2], K1[1, 2], K2[0, 2], K2[1, 2] = s[5:9]
    return replace(calib, R=R, T=T, K1=K1, K2=K2)


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
    steps = np.array([_STEPS[k] for k in "rrrttcccc"])
    cal = _rig_at(calib, s, basis, length)
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
                res_k, _ = _circle_residuals(obs, _rig_at(calib, sk, basis, length), sk, s0)
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


def _adjust(observations, calib, s0, start, thetas, free, info, basis, length, max_iter=30):
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


def _consider_jacobians(observations, cal, thetas, Zinv, consider, steps):
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


def _posterior(blocks, p, info, Jc, Cu):
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


@dataclass(frozen=True)
class RigRefinement:
    """The rig re-estimated from the part's circles.

    Attributes
    ----------
    calib : StereoCalibration
        The refined rig, its ``cov`` the posterior (full, OpenCV order): what
        the run measures with.
    names : tuple of str
        Refined parameters: "rx", "ry", "rz" (rotation vector of R, rad),
        "tb1", "tb2" (T along two directions normal to it, mm; the length
        is kept), and those of "cx1", "cy1", "cx2", "cy2" (px) the images
        determine.
    stated, refined : ndarray, shape (p,)
        Their values before and after.
    std : ndarray, shape (p,)
        Posterior standard uncertainties.
    prior_std : ndarray, shape (p,)
        The stated ones (0: none stated).
    widened : ndarray of bool, shape (p,)
        Whose prior was widened by the drift the calibration check corrected.
    z : ndarray, shape (p,)
        Correction over the standard deviation the stated calibration
        allows it (module notes).
    chi2 : float
        ``d^T V^+ d`` of the corrections jointly; ``dof`` its rank.
    dof : int
    fixed : dict
        Parameter name -> why it was kept at its stated value.
    circles : int
    baseline : float
        mm, kept.
    baseline_std : float
        mm, stated (0: none).
    rms : float
        RMS of the weighted residuals at the solution (about 1 when the
        points' stated uncertainties hold; correlated noise keeps it below).
    turn : float
        Angle of the refined ``R`` against the stated one, rad.
    """

    calib: object
    names: tuple
    stated: np.ndarray
    refined: np.ndarray
    std: np.ndarray
    prior_std: np.ndarray
    widened: np.ndarray
    z: np.ndarray
    chi2: float
    dof: int
    fixed: dict
    circles: int
    baseline: float
    baseline_std: float
    rms: float
    turn: float = 0.0

    @property
    def correction(self):
        return self.refined - self.stated

    @property
    def p_value(self):
        return float(chdtrc(self.dof, self.chi2)) if self.dof > 0 else 1.0

    @property
    def significant(self):
        return bool(self.dof > 0 and (self.p_value < float(chdtrc(1, SIGNIFICANCE**2))
                                      or np.any(np.abs(self.z) > SIGNIFICANCE)))

    def rotation_deg(self):
        """Angle of the refined rotation relative to the stated one, degrees."""
        return float(np.degrees(self.turn))

    def to_dict(self):
        """report.json's "rig_refinement" (rotation in degrees, T in mm, principal points in px)."""
        rows = []
        for k, name in enumerate(self.names):
            f = np.degrees(1.0) if name.startswith("r") else 1.0
            rows.append({
                "name": name, "unit": "deg" if name.startswith("r") else ("mm" if name.startswith("t") else "px"),
                "stated": round(float(self.stated[k] * f), 7), "refined": round(float(self.refined[k] * f), 7),
                "correction": round(float(self.correction[k] * f), 7),
                "standard_uncertainty": round(float(self.std[k] * f), 7),
                "prior_standard_uncertainty": round(float(self.prior_std[k] * f), 7) if self.prior_std[k] > 0 else None,
                "prior": ("none stated" if self.prior_std[k] == 0
                          else "stated, widened by the drift" if self.widened[k] else "stated"),
                "significance": round(float(self.z[k]), 3)})
        return {
            "method": ("bundle adjustment of the rig's relative orientation to the edge points of the registered "
                       "circles, each circle's centre, normal and radius free (the CAD model gives only which "
                       "circles are the part's); the stated calibration as prior (MAP); the baseline's length kept"),
            "circles": self.circles,
            "parameters": rows,
            "fixed": [{"name": k, "reason": v} for k, v in self.fixed.items()],
            "rotation_correction_deg": round(self.rotation_deg(), 6),
            "baseline_mm": round(self.baseline, 6),
            "baseline_standard_uncertainty_mm": round(self.baseline_std, 6),
            "chi_square": round(self.chi2, 3), "dof": self.dof, "p_value": round(self.p_value, 6),
            "significant": self.significant,
            "weighted_rms": round(self.rms, 4),
        }

    def summary(self):
        """One line for the terminal and the report."""
        word = "significant" if self.significant else "not significant"
        return (f"rig refined from {self.circles} circles ({', '.join(self.names)}): right camera turned "
                f"{self.rotation_deg():.5f} deg, {word} against the stated calibration "
                f"(chi-square {self.chi2:.1f} on {self.dof}); baseline kept at {self.baseline:.3f} mm"
                + (f"; held: {', '.join(self.fixed)}" if self.fixed else ""))


def refine_rig(calib, observations, start=None, drifted=False):
    """Re-estimate the rig's relative orientation and principal points, where the images determine them, from circles.

    Parameters
    ----------
    calib : StereoCalibration
        As stated: the prior (its ``cov``, or its standard uncertainties as
        independent; none stated: the images alone).
    observations : sequence of CircleObservation
        The part's circles (:func:`circle_observations`), measured with
        ``start`` (the views' ideal points depend on the intrinsics only).
    start : StereoCalibration, optional
        Where the adjustment starts; default ``calib``.
    drifted : bool
        ``start`` is the rig the calibration check corrected for a drift
        (its covariance holding the correction's): the prior is widened by
        that correction (module notes).

    Returns
    -------
    RigRefinement

    Raises
    ------
    RefinementError
        Fewer than ``MIN_CIRCLES`` circles, or a configuration that leaves
        the orientation undetermined.
    """
    if len(observations) < MIN_CIRCLES:
        raise RefinementError(f"{len(observations)} circle(s) measured; the rig's refinement needs {MIN_CIRCLES}")
    start = calib if start is None else start
    Z, basis = rig_coordinates(calib)
    C, Cp = _prior_covariances(calib, start, Z, basis, drifted)
    stated_var = np.diag(C)[:9]
    widened = np.diag(Cp)[:9] > stated_var * (1 + 1e-9)
    free = [k for k in range(9) if k < 5 or stated_var[k] > 0]
    fixed = {_NAMES[k]: "the calibration states no uncertainty for it" for k in range(5, 9) if k not in free}
    s0, s, length = _rig_vector(calib, basis), _rig_vector(start, basis), float(np.linalg.norm(calib.T))
    thetas = [np.r_[o.fit.center, 0.0, 0.0, o.fit.radius] for o in observations]
    setting = (observations, start, s0, basis, length, C, Cp, np.linalg.inv(Z))
    while True:
        s, thetas, blocks, fc, cov, noise, K = _refine_free(setting, s, thetas, free)
        p = len(free)
        post_std = np.sqrt(np.diag(cov)[:p])
        prior_std = np.sqrt(np.diag(Cp)[free])
        weak = [c for c in range(p) if prior_std[c] > 0 and post_std[c] > DETERMINED * prior_std[c]]
        if not weak:
            break
        for c in weak:
            k = free[c]
            fixed[_NAMES[k]] = (f"not determined by the images better than by the calibration (standard "
                                f"uncertainty {post_std[c] / prior_std[c]:.2f} of the "
                                f"{'widened' if widened[k] else 'stated'} one); held at its stated value, "
                                f"its uncertainty carried")
        if len(weak) == p:
            raise RefinementError("the images determine none of the rig's parameters better than the stated "
                                  "calibration does (to half its standard uncertainty)")
        held = [free[c] for c in weak]
        s[held] = s0[held]
        free = [k for k in free if k not in held]
    n_res = sum(len(b[0]) for b in blocks)
    z, chi2, dof = _significance(s[free] - s0[free], K[:p] + np.eye(p, len(fc)), C[np.ix_(fc, fc)], noise[:p, :p])
    refined = _rig_at(start, s, basis, length)
    return RigRefinement(
        _with_posterior(refined, setting[-1], Cp, fc, cov[:p, :p], K[:p]), tuple(_NAMES[k] for k in free),
        s0[free], s[free], post_std, np.sqrt(stated_var[free]), widened[free], z, chi2, dof, fixed,
        len(observations), length, float(np.sqrt(C[9, 9])),
        float(np.sqrt(sum(b[0] @ b[0] for b in blocks) / max(n_res, 1))),
        float(np.linalg.norm(cv2.Rodrigues(refined.R @ np.asarray(calib.R, float).T)[0])))


def _prior_covariances(calib, start, Z, basis, drifted):
    """The stated covariance in the rig's coordinates, and the prior's: widened by a drift's correction.

    The correction ``d`` (``start`` against ``calib``) and its covariance are
    added to the rig's block as a Type B independent of the calibration's
    own errors, only where the calibration states an uncertainty.
    """
    C = Z @ full_covariance(calib) @ Z.T
    Cp = C.copy()
    if drifted:
        stated = np.diag(C)[:9] > 0
        d = np.where(stated, _rig_vector(start, basis) - _rig_vector(calib, basis), 0.0)
        W = np.outer(d, d) + (Z @ full_covariance(start) @ Z.T - C)[:9, :9]
        Cp[:9, :9] += np.where(np.outer(stated, stated), W, 0.0)
    return C, Cp


def _refine_free(setting, s, thetas, free):
    """The adjustment over the ``free`` rig parameters, every other stated one held and considered.

    Returns the solution, the circles', the last linearisation's blocks,
    the order ``fc`` (free, then held) and :func:`_posterior`'s results.
    """
    observations, start, s0, basis, length, C, Cp, Zinv = setting
    info = _prior_information(Cp[:9, :9], free)
    s, thetas, blocks, _ = _adjust(observations, start, s0, s, thetas, free, info, basis, length)
    # Every other parameter with a stated uncertainty: held at its value, its error carried.
    consider = [j for j in range(len(C)) if j not in free and C[j, j] > 0]
    fc = free + consider
    Jc = _consider_jacobians(observations, _rig_at(start, s, basis, length), thetas, Zinv, consider,
                             np.sqrt(np.diag(C)[consider]))
    return (s, thetas, blocks, fc, *_posterior(blocks, len(free), info, Jc, Cp[np.ix_(fc, fc)]))


def _rig_vector(calib, basis):
    T = np.asarray(calib.T, float).ravel()
    return np.r_[cv2.Rodrigues(np.asarray(calib.R, float))[0].ravel(), basis[0] @ T, basis[1] @ T,
                 calib.K1[0, 2], calib.K1[1, 2], calib.K2[0, 2], calib.K2[1, 2]]


def _prior_information(C9, free):
    """The prior's information on the free parameters; none on those with no stated uncertainty."""
    keep = [c for c, k in enumerate(free) if C9[k, k] > 0]
    info = np.zeros((len(free), len(free)))
    if keep:
        idx = [free[c] for c in keep]
        info[np.ix_(keep, keep)] = np.linalg.pinv(C9[np.ix_(idx, idx)], rcond=1e-12, hermitian=True)
    return info


def _significance(d, G, C, noise):
    """Each correction's z and the joint chi-square against "the stated calibration is right".

    The correction ``d = s_hat - s_0`` is ``G u`` plus the image noise's
    part, ``G = K_s + [I, 0]`` (:func:`_posterior`), ``u`` the stated
    values' errors drawn from the stated covariance ``C`` (no drift's
    widening: that is what is tested).
    """
    V = G @ C @ G.T + noise
    z = d / np.sqrt(np.maximum(np.diag(V), 1e-300))
    w, U = np.linalg.eigh(0.5 * (V + V.T))
    keep = w > 1e-10 * w.max()
    chi2 = float(np.sum((U[:, keep].T @ d) ** 2 / w[keep]))
    return z, chi2, int(keep.sum())


def _with_posterior(refined, Zinv, C, fc, P, K):
    """The refined calibration with the joint covariance of all its parameters' errors.

    In the coordinates ``z = Z x``: the refined parameters' error has the
    covariance ``P`` and responds to the prior errors of ``fc`` (refined,
    then held) as ``K`` (:func:`_posterior`); every other parameter keeps
    its stated value, so its error is the stated one, ``C`` (a drift's
    widening included), and the two correlate as ``-K C_fc,o``.
    """
    n = C.shape[0]
    p = len(P)
    free = fc[:p]
    others = [i for i in range(n) if i not in free]
    post = np.zeros((n, n))
    post[np.ix_(free, free)] = P
    cross = -K @ C[np.ix_(fc, others)]
    post[np.ix_(free, others)] = cross
    post[np.ix_(others, free)] = cross.T
    post[np.ix_(others, others)] = C[np.ix_(others, others)]
    X = Zinv @ post @ Zinv.T
    return validate_calibration(replace(refined, std={}, cov=0.5 * (X + X.T)))
