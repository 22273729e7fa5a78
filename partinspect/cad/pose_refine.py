"""Weighted least-squares refinement of the part's pose, with its covariance.

Minimised over the six pose parameters (Gauss-Newton): the chi-square
``r^T r`` of the matched datum features' residuals, each whitened by the
feature's own covariance, so that poorly known depth pulls the fit little:

- circle: the centre offset (mm), whitened by the centre's 3x3
  covariance, and the normal in its tangent plane, by its 2x2 covariance;
- line: the offset ``(a, b)`` (mm) and slope ``(alpha, beta)`` of the CAD
  line in the plane normal to the measured line at its reference point,
  whitened by their 4x4 covariance.

Radii carry no pose information. Pose: ``T_hat = T_true @ D(xi)``,
``D(xi) = [[Rot(w), v], [0, 1]]``, ``xi = (w, v)``: a rotation vector (rad)
and a translation (mm) in the part frame. Its covariance is ``(J^T J)^-1``
with ``J`` the whitened Jacobian, i.e. ``(J^T Sigma^-1 J)^-1`` [1]_ (plus
the calibration's part, below), first order. The chi-square is reported,
so that a model mismatch is seen; when it is beyond what its degrees of
freedom allow by chance (``MISFIT_P``), the features scatter about the
model more than their covariances say, and the pose's covariance from
them, ``(J^T J)^-1``, is multiplied by ``chi2 / dof``, the Birge ratio
squared [3]_ (the GUM's Type A practice of taking the spread from the
residuals [2]_): a pose fitted to features that disagree beyond their
stated covariances is not known as well as those covariances alone say.
Within chance it is left as it is, so the misfit's own sampling spread
does not move an honest registration's uncertainty.
Without named datums, features whose residuals are beyond chance
(``OUTLIER_P``) are left out, worst first, at most a quarter of them (a
robust best fit).

The stereo calibration's error is one error shared by every feature
(:attr:`partinspect.vision.feature3d.Feature3D.calibration_response`, ``G``,
a feature's response to the calibration's q principal directions of
uncertainty). Most of it moves every feature alike, as a rigid motion
would, and the pose is meant to take that up: the part frame is the one
the datum features establish, as measured. So each feature is weighted
by its own covariance less that shared part, and the shared part is
carried, not weighted: the whitened residuals' covariance is
``I + U U^T`` with ``U`` the stacked ``-S M^T G``, and the pose's
covariance is the sandwich ``A + H H^T``, ``A = (J^T J)^-1``,
``H = -A J^T U`` [2]_. The chi-square and each feature's outlier test
are taken against the residuals' covariance so formed (what the pose
cannot take up of the calibration's error, ``V = (I - J A J^T) U``, added
to the unit covariance), so that a calibration's shared error does not
read as a misfit.

Neglected correlations: inside one circle fit (between centre and normal
in the whitening; the radius carries no pose information), and between a
line's point and direction (zero at the data centroid, where the fitter
puts the point).

References
----------
.. [1] Hartley, R., & Zisserman, A. (2004). Multiple View Geometry in
       Computer Vision, 2nd ed., section 5.2 (covariance by
       back-propagation, ``(J^T Sigma^-1 J)^-1``).
.. [2] JCGM 100:2008 (GUM), section 5.2: correlated input quantities;
       section 4.2: Type A evaluation from the observed scatter.
.. [3] Birge, R. T. (1932). The calculation of errors by the method of
       least squares. Phys. Rev. 40, 207-227; as applied by CODATA:
       Mohr, P. J., Newell, D. B., Taylor, B. N. (2016). CODATA
       recommended values of the fundamental physical constants: 2014.
       Rev. Mod. Phys. 88, 035009, appendix E.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from partinspect.cad.pose_search import RegistrationError, axis_cov, match, unit
from partinspect.frames import plane_basis

__all__ = [
    "calibration_response",
    "decorrelator",
    "calibration_left",
    "refine_pose",
    "solve_pose",
    "pose_error",
    "pose_matrix",
    "misfit_scale",
    "OUTLIER_P",
    "MISFIT_P",
    "COST_TOL",
]

_MAX_ITER = 30
OUTLIER_P = 1e-9
"""Without named datums, a matched feature whose own chi-square at the
refined pose has a chance below this (for its 4 or 5 whitened residuals:
beyond 46 or 51) is left out of the pose fit, worst first, at most a
quarter of the features, and reported (``Registration.outliers``). It is
still assigned and measured against the pose the others give. Such a
feature (one edge paired with a different edge in the other image, or a
hole moved on the part) would otherwise pull the pose and with it every
other feature."""
MISFIT_P = 1e-3
"""A registration's chi-square whose chance on its degrees of freedom is
below this is a misfit beyond chance, and the pose covariance carries it
(:func:`misfit_scale`). The same level as the fusion's view test
(:data:`partinspect.tolerances.fusion.VIEW_P`): a view whose features
misfit its own pose this much would be refused there if its pose's
covariance ignored it."""
COST_TOL = 1e-10
"""The pose refinement has converged when a Gauss-Newton step would lower
the chi-square by less than this fraction of it (``|J step|^2``; the
residuals are whitened, so the step then moves the fit by a negligible
part of a standard deviation), or the step itself is below 1e-11 rad and
1e-9 mm. The relative test is what ends a fit whose chi-square is large:
its steps stop shrinking at the rounding of the residuals, above those
absolute limits."""



def _whitener(C):
    """S with S C S^T = I (inverse Cholesky), robust to a near-singular C."""
    C = 0.5 * (np.asarray(C, float) + np.asarray(C, float).T)
    w, V = np.linalg.eigh(C)
    floor = max(w.max(), 1e-30) * 1e-12
    w = np.maximum(w, floor)
    return (V / np.sqrt(w)).T, V * np.sqrt(w)  # S, L with L L^T = C, S = L^-1


def pose_matrix(R, t):
    """The 4x4 homogeneous transform ``[[R, t], [0, 1]]``."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def _delta(xi):
    """``D(xi) = [[Rot(w), v], [0, 1]]`` of ``xi = (w [rad], v [mm])``."""
    return pose_matrix(Rotation.from_rotvec(xi[:3]).as_matrix(), xi[3:])


def pose_error(T_est, T_true):
    """The error ``xi`` with ``T_est = T_true @ D(xi)``: rotation vector (rad), translation (mm), part frame.

    Parameters
    ----------
    T_est, T_true : ndarray, shape (4, 4)

    Returns
    -------
    ndarray, shape (6,)
    """
    D = np.linalg.inv(T_true) @ T_est
    return np.r_[Rotation.from_matrix(D[:3, :3]).as_rotvec(), D[:3, 3]]



# ---------------------------------------------------------------------------
# residual model and Gauss-Newton


def calibration_response(kind, rec):
    """A record's responses to the calibration's principal directions, shape (7, q) or (6, q).

    ``calibration_response`` of a :class:`partinspect.vision.feature3d.Feature3D`;
    q = 0 for a record without one.
    """
    G = getattr(rec, "calibration_response", None)
    return np.zeros((7 if kind == "circle" else 6, 0)) if G is None else np.asarray(G, float)


def decorrelator(U):
    """``x -> (I + U U^T)^-1/2 x`` for x of shape (n,) or (n, k).

    With ``U^T U = Q diag(l) Q^T``, ``(I + U U^T)^-1/2 = I + U Q diag(c) Q^T U^T``,
    ``c = (1/sqrt(1 + l) - 1) / l`` (-1/2 at l = 0), computed without
    forming the n x n matrix.
    """
    if U.shape[1] == 0:
        return lambda x: x
    lam, Q = np.linalg.eigh(U.T @ U)
    lam = np.clip(lam, 0.0, None)
    with np.errstate(divide="ignore", invalid="ignore"):
        c = np.where(lam > 1e-300, (1.0 / np.sqrt(1.0 + lam) - 1.0) / lam, -0.5)
    W = U @ (Q * c) @ Q.T
    return lambda x: x + W @ (U.T @ x)


class _Problem:
    """Whitened residuals of matched features as a function of a pose."""

    def __init__(self, circles, lines, circ_match, line_match, cad):
        self.items = []  # (kind, index, n_rows, M, L, G)
        blocks = []  # (rows of -S M^T G) per feature, in row order
        cc, cn, cS, cE, cSn, cm, nm = [], [], [], [], [], [], []
        for i, k in sorted(circ_match.items()):
            rec = circles[i]
            G = calibration_response("circle", rec)
            S, L = _whitener(np.asarray(rec.covariance, float) - G[:3] @ G[:3].T)
            n = unit(rec.normal)
            E = plane_basis(n)
            Sn, Ln = _whitener(E.T @ (axis_cov(rec) - G[3:6] @ G[3:6].T) @ E)
            cc.append(cad.centers[k])
            cn.append(cad.normals[k])
            cS.append(S)
            cE.append(E)
            cSn.append(Sn)
            cm.append(np.asarray(rec.center, float))
            nm.append(n)
            M = np.zeros((7, 5))
            M[:3, :3] = np.eye(3)
            M[3:6, 3:5] = E
            Lb, Sb = np.zeros((5, 5)), np.zeros((5, 5))
            Lb[:3, :3], Lb[3:, 3:] = L, Ln
            Sb[:3, :3], Sb[3:, 3:] = S, Sn
            self.items.append(("circle", i, 5, M, Lb, G))
            blocks.append(-Sb @ M.T @ G)
        lp, ld, lS, lE, pm, dm = [], [], [], [], [], []
        for j, l in sorted(line_match.items()):
            rec = lines[j]
            G = calibration_response("line", rec)
            d = unit(rec.direction)
            E = plane_basis(d)
            C4 = np.zeros((4, 4))
            C4[:2, :2] = E.T @ (np.asarray(rec.covariance, float) - G[:3] @ G[:3].T) @ E
            C4[2:, 2:] = E.T @ (axis_cov(rec) - G[3:6] @ G[3:6].T) @ E
            S, L = _whitener(C4)
            lp.append(cad.starts[l])
            ld.append(cad.dirs[l])
            lS.append(S)
            lE.append(E)
            pm.append(np.asarray(rec.point, float))
            dm.append(d)
            M = np.zeros((6, 4))
            M[:3, :2] = E
            M[3:6, 2:] = E
            self.items.append(("line", j, 4, M, L, G))
            blocks.append(-S @ M.T @ G)
        arr = lambda x, s: np.array(x, float).reshape(s)  # noqa: E731
        self.cc, self.cn, self.cS = arr(cc, (-1, 3)), arr(cn, (-1, 3)), arr(cS, (-1, 3, 3))
        self.cE, self.cSn, self.cm, self.nm = arr(cE, (-1, 3, 2)), arr(cSn, (-1, 2, 2)), arr(cm, (-1, 3)), arr(nm, (-1, 3))
        self.lp, self.ld, self.lS, self.lE = arr(lp, (-1, 3)), arr(ld, (-1, 3)), arr(lS, (-1, 4, 4)), arr(lE, (-1, 3, 2))
        self.pm, self.dm = arr(pm, (-1, 3)), arr(dm, (-1, 3))
        self.n_res = 5 * len(self.cc) + 4 * len(self.lp)
        self.csign = np.ones(len(self.cc))
        self.lsign = np.ones(len(self.lp))
        q = max((b.shape[1] for b in blocks), default=0)
        self.U = np.vstack([np.pad(b, ((0, 0), (0, q - b.shape[1]))) for b in blocks]) if blocks else np.zeros((0, 0))

    def fix_signs(self, T):
        R = T[:3, :3]
        self.csign = np.where(np.einsum("ni,ni->n", self.cn @ R.T, self.nm) < 0, -1.0, 1.0)
        self.lsign = np.where(np.einsum("ni,ni->n", self.ld @ R.T, self.dm) < 0, -1.0, 1.0)

    def residuals(self, T, raw=False):
        R, t = T[:3, :3], T[:3, 3]
        out = []
        if len(self.cc):
            dc = self.cc @ R.T + t - self.cm
            nt = np.einsum("nij,ni->nj", self.cE, self.csign[:, None] * (self.cn @ R.T))
            if raw:
                out.append(np.linalg.norm(dc, axis=1))
            else:
                out.append(np.concatenate([np.einsum("nij,nj->ni", self.cS, dc), np.einsum("nij,nj->ni", self.cSn, nt)], 1))
        if len(self.lp):
            P = self.lp @ R.T + t
            D = self.lsign[:, None] * (self.ld @ R.T)
            den = np.einsum("ni,ni->n", D, self.dm)
            s = np.einsum("ni,ni->n", self.pm - P, self.dm) / den
            X = P + s[:, None] * D - self.pm
            ab = np.einsum("nij,ni->nj", self.lE, X)
            al = np.einsum("nij,ni->nj", self.lE, D) / den[:, None]
            if raw:
                out.append(np.linalg.norm(ab, axis=1))
            else:
                out.append(np.einsum("nij,nj->ni", self.lS, np.concatenate([ab, al], 1)))
        if raw:
            return np.concatenate(out) if out else np.zeros(0)
        # rows ordered circles then lines, each feature's block contiguous
        return np.concatenate([o.ravel() for o in out]) if out else np.zeros(0)

    def jacobian(self, T, h=1e-7):
        cols = []
        for k in range(6):
            e = np.zeros(6)
            e[k] = h
            cols.append((self.residuals(T @ _delta(e)) - self.residuals(T @ _delta(-e))) / (2 * h))
        return np.stack(cols, 1)


def refine_pose(T0, problem):
    """Gauss-Newton on the right-perturbation ``T @ D(xi)``; returns (T, J, r, converged)."""
    T = np.array(T0, float)
    problem.fix_signs(T)
    r = problem.residuals(T)
    cost = r @ r
    converged = False
    for _ in range(_MAX_ITER):
        J = problem.jacobian(T)
        try:
            step = np.linalg.lstsq(J, -r, rcond=None)[0]
        except np.linalg.LinAlgError:
            break
        # Predicted decrease of the cost, before any halving of the step.
        negligible = float(np.sum((J @ step) ** 2)) <= COST_TOL * max(cost, 1.0)
        Tn = T @ _delta(step)
        rn = problem.residuals(Tn)
        cn = rn @ rn
        if cn > cost * (1 + 1e-12) + 1e-18:
            # a Gauss-Newton step that increases the cost: halve it
            for _ in range(20):
                step *= 0.5
                Tn = T @ _delta(step)
                rn = problem.residuals(Tn)
                cn = rn @ rn
                if cn <= cost:
                    break
            else:
                converged = negligible or np.linalg.norm(step) < 1e-9
                break
        T, r = Tn, rn
        small = negligible or (np.linalg.norm(step[:3]) < 1e-11 and np.linalg.norm(step[3:]) < 1e-9)
        cost = cn
        if small:
            converged = True
            break
    J = problem.jacobian(T)
    return T, J, problem.residuals(T), converged


def _constraint_check(J):
    """Raise when the datum features leave some pose direction free."""
    if J.shape[0] < 6:
        raise RegistrationError(
            f"alignment is ambiguous: the datum features give {J.shape[0]} constraints, the pose needs 6"
        )
    # Scale rotations by a part-sized lever (100 mm) so the test compares like with like.
    Js = J * np.r_[np.full(3, 1e-2), np.ones(3)]
    s = np.linalg.svd(Js, compute_uv=False)
    if s[-1] < 1e-8 * s[0]:
        raise RegistrationError(
            "alignment is ambiguous: the datum features leave the pose undetermined in some direction "
            "(e.g. all lines parallel, or one circle alone)"
        )



# ---------------------------------------------------------------------------
# match and refine


def _refine(T, circles, lines, meas, cad, datum_set, left_out):
    """Match, refine on the datums (less those keyed (kind, measured index) in ``left_out``), re-match, refine again."""
    for _ in range(3):
        circ, lin, _ = match(meas, cad, T[:3, :3], T[:3, 3])
        fc = {i: k for i, k in circ.items()
              if (datum_set is None or cad.round_ids[k] in datum_set) and ("circle", i) not in left_out}
        fl = {j: l for j, l in lin.items()
              if (datum_set is None or cad.line_ids[l] in datum_set) and ("line", j) not in left_out}
        problem = _Problem(circles, lines, fc, fl, cad)
        if problem.n_res < 6:
            raise RegistrationError(
                f"alignment is ambiguous: the matched datum features give {problem.n_res} constraints, the pose needs 6"
            )
        T_new, J, r, converged = refine_pose(T, problem)
        if not converged:
            raise RegistrationError("alignment is ambiguous: the pose refinement did not converge")
        moved = np.linalg.norm(T_new[:3, 3] - T[:3, 3]) + 100 * Rotation.from_matrix(T_new[:3, :3].T @ T[:3, :3]).magnitude()
        T = T_new
        if moved < 1e-6:
            break
    _constraint_check(J)
    return T, circ, lin, fc, fl, problem, J, r


def misfit_scale(chi2, dof, p=MISFIT_P):
    """The factor the pose covariance's feature part is multiplied by: ``chi2 / dof`` beyond chance, else 1.

    Parameters
    ----------
    chi2 : float
        The registration's chi-square, against the whitened residuals'
        covariance (:func:`calibration_left`).
    dof : int
        Its degrees of freedom (residuals less the pose's 6).
    p : float
        Chance below which the chi-square is a misfit (``MISFIT_P``).

    Returns
    -------
    float
        ``chi2 / dof`` (the Birge ratio squared) when the chi-square's
        upper tail probability is below ``p``; 1 otherwise, and with no
        degrees of freedom (nothing to judge the fit by).

    Notes
    -----
    Birge's ratio ``sqrt(chi2 / dof)`` scales a least-squares estimate's
    standard uncertainties when the data scatter beyond their stated
    uncertainties by a common factor; the test keeps it from moving a fit
    whose chi-square is within chance, where ``chi2 / dof`` scatters about
    1 by ``sqrt(2 / dof)``.
    """
    from scipy.special import chdtrc

    if dof < 1 or not np.isfinite(chi2) or chdtrc(dof, chi2) >= p:
        return 1.0
    return max(1.0, float(chi2) / dof)


def calibration_left(J, U):
    """``V = (I - J (J^T J)^-1 J^T) U``: the calibration's shared error in the whitened residuals that the pose cannot take up."""
    if U.shape[1] == 0:
        return U
    return U - J @ np.linalg.solve(J.T @ J, J.T @ U)


def _worst(problem, r, V):
    """(chance, kind, measured index, chi-square, residuals) of the feature with the least likely residuals.

    A feature's residuals are judged against their covariance ``I + V_f V_f^T``
    (:func:`calibration_left`).
    """
    # chdtrc is what scipy.stats.chi2.sf calls, without scipy.stats' import time.
    from scipy.special import chdtrc

    worst, start = None, 0
    for kind, index, n, *_ in problem.items:
        rf, Vf = r[start:start + n], V[start:start + n]
        c2 = float(rf @ np.linalg.solve(np.eye(n) + Vf @ Vf.T, rf))
        start += n
        p = chdtrc(n, c2)
        if worst is None or p < worst[0]:
            worst = (p, kind, index, c2, n)
    return worst


def solve_pose(T, circles, lines, meas, cad, datum_set, exclude_outliers=False):
    """Match, refine on the datums, re-match with the refined pose, refine again.

    With ``exclude_outliers`` (no named datums), a feature inconsistent with
    the others (``OUTLIER_P``) is then left out and the pose refined again,
    worst first, while the rest still fix the pose.

    Parameters
    ----------
    T : ndarray, shape (4, 4)
        Starting ``part_to_camera``.
    circles, lines : sequence
        The measured records (rig frame).
    meas : partinspect.cad.pose_search.MeasuredArrays
    cad : partinspect.cad.pose_search.CadArrays
    datum_set : set of str or None
        CAD ids that may drive the fit; None: every matched feature.
    exclude_outliers : bool

    Returns
    -------
    dict
        ``T`` (refined pose), ``cov`` (6x6 pose covariance, the calibration's
        part included, the features' part times ``cov_scale``,
        :func:`misfit_scale`), ``J`` (whitened Jacobian), ``JA`` (``J (J^T J)^-1``:
        the pose's sensitivity to the whitened residuals is ``-JA^T``),
        ``U`` (the whitened residuals' calibration part, rows of J by q),
        ``rows`` ((kind, index) -> (rows of J, M, L)), ``chi2`` (against the
        residuals' covariance, :func:`calibration_left`),
        ``dof``, ``rms`` (mm), ``circ`` / ``lin`` (measured index -> CAD
        index, under the final pose), ``score``, ``datums`` (CAD ids),
        ``outliers`` (CAD id -> (chi-square, residuals)).

    Raises
    ------
    RegistrationError
        Fewer than 6 constraints, no convergence, or a pose direction
        the datums leave free.
    """
    left_out = {}
    T, circ, lin, fc, fl, problem, J, r = _refine(T, circles, lines, meas, cad, datum_set, left_out)
    limit = (len(fc) + len(fl)) // 4
    while exclude_outliers and len(left_out) < limit:
        p, kind, index, c2, n = _worst(problem, r, calibration_left(J, problem.U))  # needs 6 residuals: there is one
        if p >= OUTLIER_P:
            break
        trial = {**left_out, (kind, index): (c2, n)}
        try:
            refined = _refine(T, circles, lines, meas, cad, datum_set, trial)
        except RegistrationError:
            break  # the others alone leave the pose undetermined: keep the feature
        left_out = trial
        T, circ, lin, fc, fl, problem, J, r = refined
    circ2, lin2, _ = match(meas, cad, T[:3, :3], T[:3, 3])
    if (circ2, lin2) != (circ, lin):
        circ, lin = circ2, lin2  # final assignment under the final pose
    A = np.linalg.inv(J.T @ J)
    A = 0.5 * (A + A.T)
    H = -A @ (J.T @ problem.U)
    V = calibration_left(J, problem.U)
    chi2 = float(np.sum(decorrelator(V)(r) ** 2))
    dof = int(r.size - 6)
    # The calibration's part leaves no residual to judge it by: only the features' own part is scaled.
    scale = misfit_scale(chi2, dof)
    cov = scale * A + H @ H.T
    rows, start = {}, 0
    for kind, index, n, M, L, _ in problem.items:
        rows[(kind, index)] = (slice(start, start + n), M, L)
        start += n
    raw = problem.residuals(T, raw=True)
    ids = tuple(sorted({cad.round_ids[k] for k in fc.values()} | {cad.line_ids[l] for l in fl.values()}))
    return {
        "T": T,
        "cov": cov,
        "J": J,
        "JA": J @ A,
        "U": problem.U,
        "rows": rows,
        "chi2": chi2,
        "dof": dof,
        "cov_scale": scale,
        "rms": float(np.sqrt(np.mean(raw**2))) if raw.size else 0.0,
        "circ": circ,
        "lin": lin,
        "score": len(circ) + len(lin),
        "datums": ids,
        "outliers": {(cad.round_ids[circ[i]] if kind == "circle" else cad.line_ids[lin[i]]): (round(c2, 6), n)
                     for (kind, i), (c2, n) in left_out.items()
                     if i in (circ if kind == "circle" else lin)},
    }
