"""The rig's relative orientation re-estimated from the part's own circles: a bundle adjustment with the stated calibration as prior.

A stated calibration is one board session's estimate, and the rig may
have moved since. The part's circles measure it again, by the bundle
adjustment of :mod:`partinspect.vision.rig_adjustment` (each circle's
centre, normal and radius free) with the stated calibration's covariance
as its prior: the relative orientation (the rotation vector of ``R`` and
the direction of ``T``: 5 parameters) and, where the images determine
them, the principal points. Its posterior covariance replaces the stated
one in the calibration the run measures with; the reports state it
through :mod:`partinspect.vision.rig_report`.

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
  circles' roundness. Otherwise it is held at its stated value (after a
  drift, as the check corrected it: the check's turn about the baseline
  moves the rotation's x component, which trades with ``T``'s vertical
  direction, so resetting it would pull that back), its uncertainty
  carried, and that is said.

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
(:func:`partinspect.vision.rig_adjustment.posterior`, :func:`_with_posterior`).

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
from partinspect.vision.calibration_uncertainty import full_covariance
from partinspect.vision.rig_adjustment import (CircleObservation, RefinementError, adjust, circle_observations,
                                               consider_jacobians, posterior, rig_at, rig_coordinates, rig_vector)
from partinspect.vision.rig_report import refinement_entry, refinement_summary

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

_NAMES = ("rx", "ry", "rz", "tb1", "tb2", "cx1", "cy1", "cx2", "cy2")


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
        """report.json's "rig_refinement" (:func:`partinspect.vision.rig_report.refinement_entry`)."""
        return refinement_entry(self)

    def summary(self):
        """One line for the terminal and the report (:func:`partinspect.vision.rig_report.refinement_summary`)."""
        return refinement_summary(self)


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
    C, Cp, Ce = _prior_covariances(calib, start, Z, basis, drifted)
    stated_var = np.diag(C)[:9]
    widened = np.diag(Cp)[:9] > stated_var * (1 + 1e-9)
    free = [k for k in range(9) if k < 5 or stated_var[k] > 0]
    fixed = {_NAMES[k]: "the calibration states no uncertainty for it" for k in range(5, 9) if k not in free}
    s0, s, length = rig_vector(calib, basis), rig_vector(start, basis), float(np.linalg.norm(calib.T))
    s_start = s.copy()
    thetas = [np.r_[o.fit.center, 0.0, 0.0, o.fit.radius] for o in observations]
    setting = (observations, start, s0, basis, length, C, Cp, Ce, np.linalg.inv(Z))
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
                                f"{'widened' if widened[k] else 'stated'} one); held at its "
                                f"{'corrected' if drifted else 'stated'} value, its uncertainty carried")
        if len(weak) == p:
            raise RefinementError("the images determine none of the rig's parameters better than the stated "
                                  "calibration does (to half its standard uncertainty)")
        held = [free[c] for c in weak]
        # At the start's value: after a drift, the check's correction of it, which the widened prior carries.
        s[held] = s_start[held]
        free = [k for k in free if k not in held]
    n_res = sum(len(b[0]) for b in blocks)
    z, chi2, dof = _significance(s[free] - s0[free], K[:p] + np.eye(p, len(fc)), C[np.ix_(fc, fc)], noise[:p, :p])
    refined = rig_at(start, s, basis, length)
    return RigRefinement(
        _with_posterior(refined, setting[-1], Ce, fc, cov[:p, :p], K[:p]), tuple(_NAMES[k] for k in free),
        s0[free], s[free], post_std, np.sqrt(stated_var[free]), widened[free], z, chi2, dof, fixed,
        len(observations), length, float(np.sqrt(C[9, 9])),
        float(np.sqrt(sum(b[0] @ b[0] for b in blocks) / max(n_res, 1))),
        float(np.linalg.norm(cv2.Rodrigues(refined.R @ np.asarray(calib.R, float).T)[0])))


def _prior_covariances(calib, start, Z, basis, drifted):
    """The stated covariance in the rig's coordinates, the prior's, and that of the start's errors.

    The prior (centred on the stated values): the correction ``d``
    (``start`` against ``calib``) and its covariance are added to the rig's
    block as a Type B independent of the calibration's own errors, only
    where the calibration states an uncertainty. The start's values (what
    a held parameter keeps): the correction's covariance only, since the
    correction itself is applied to them. Without a drift all three agree
    but for the first's use as the null hypothesis.
    """
    C = Z @ full_covariance(calib) @ Z.T
    Cp, Ce = C.copy(), C.copy()
    if drifted:
        stated = np.diag(C)[:9] > 0
        both = np.outer(stated, stated)
        d = np.where(stated, rig_vector(start, basis) - rig_vector(calib, basis), 0.0)
        W = (Z @ full_covariance(start) @ Z.T - C)[:9, :9]
        Ce[:9, :9] += np.where(both, W, 0.0)
        Cp[:9, :9] += np.where(both, W + np.outer(d, d), 0.0)
    return C, Cp, Ce


def _refine_free(setting, s, thetas, free):
    """The adjustment over the ``free`` rig parameters, every other stated one held and considered.

    Returns the solution, the circles', the last linearisation's blocks,
    the order ``fc`` (free, then held) and :func:`~partinspect.vision.rig_adjustment.posterior`'s results.
    """
    observations, start, s0, basis, length, C, Cp, Ce, Zinv = setting
    info = _prior_information(Cp[:9, :9], free)
    s, thetas, blocks, _ = adjust(observations, start, s0, s, thetas, free, info, basis, length)
    # Every other parameter with a stated uncertainty: held at its value, its error carried.
    consider = [j for j in range(len(C)) if j not in free and C[j, j] > 0]
    fc = free + consider
    Jc = consider_jacobians(observations, rig_at(start, s, basis, length), thetas, Zinv, consider,
                             np.sqrt(np.diag(C)[consider]))
    # The prior's errors of the refined parameters (weighted by its information), the start's of the held ones.
    Cu = Ce[np.ix_(fc, fc)]
    Cu[: len(free), : len(free)] = Cp[np.ix_(free, free)]
    return (s, thetas, blocks, fc, *posterior(blocks, len(free), info, Jc, Cu))


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
    part, ``G = K_s + [I, 0]`` (:func:`~partinspect.vision.rig_adjustment.posterior`), ``u`` the stated
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
    then held) as ``K`` (:func:`~partinspect.vision.rig_adjustment.posterior`); every other parameter keeps
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
