"""Geometric fits of lines, circles and ellipses to edge points, with covariance.

Every fit minimises the sum of squared *orthogonal* distances of the points
to the curve, each weighted by the inverse variance of its point along the
normal (``n^T cov_i n``), which is the maximum-likelihood fit for Gaussian
point errors along the normal (paper, section 3). Near the optimum every fit
is a linear regression of the normal errors e_i on rows h_i = d(distance_i)
/ d(params), which gives one common uncertainty evaluation:

    cov(params) = S^-1 (H^T W R W H) S^-1,   S = H^T W H,  W = diag(1 / s_i^2)

where R is the covariance of the normal errors. For independent errors
(R = W^-1) this is S^-1, Kanatani's KCR lower bound evaluated at the
estimate; edge points from one edge share image noise through the filter
(see :func:`partinspect.vision.edges.edge_error_correlation`), and passing
``corr_length`` accounts for it (errors correlated as exp(-d^2 / (4 l^2))
over the distance d between points), without which the standard
uncertainties are understated.

Parameter covariances are standard-uncertainty covariances (GUM); the 95 %
intervals use the coverage factor k = 1.96 of the normal distribution.

References
----------
.. [1] Paper of this project, sections 3.1 and 3.2.
.. [2] Gander, W., Golub, G. H., Strebel, R. (1994). Least-squares fitting of
       circles and ellipses. BIT 34, 558-578.
.. [3] Kanatani, K. (1996). Statistical Optimization for Geometric
       Computation. Elsevier (the KCR lower bound).
.. [4] Chernov, N., Lesort, C. (2004). Statistical efficiency of curve
       fitting algorithms. Computational Statistics & Data Analysis 47,
       713-728.
.. [5] Halir, R., Flusser, J. (1998). Numerically stable direct least
       squares fitting of ellipses. WSCG (start values, via OpenCV's
       ``fitEllipseDirect``).
.. [6] Satterthwaite, F. E. (1946). An approximate distribution of estimates
       of variance components. Biometrics Bulletin 2(6), 110-114.
.. [7] Transtrum, M. K., Sethna, J. P. (2012). Improvements to the
       Levenberg-Marquardt algorithm for nonlinear least-squares
       minimization. arXiv:1201.5885 (geodesic acceleration).
.. [8] Madsen, K., Nielsen, H. B., Tingleff, O. (2004). Methods for
       non-linear least squares problems, 2nd ed. IMM, DTU, section 3.2
       (the damping update from the gain ratio).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np
from scipy import special

__all__ = [
    "LineFit",
    "CircleFit",
    "EllipseFit",
    "fit_line",
    "fit_circle",
    "fit_ellipse",
    "ellipse_points",
    "ellipse_curvature",
    "line_kcr_bound",
    "ellipse_kcr_bound",
    "COVERAGE_95",
    "EllipseJob",
    "fit_ellipses",
    "line_with_covariance",
    "ellipse_with_covariance",
    "ellipse_geometry",
    "foot_phases",
    "direct_residuals",
    "std_along",
    "trace_r2",
    "as_points",
    "axis_bound",
]

COVERAGE_95 = 1.959963984540054  # coverage factor k for a 95 % interval, normal distribution


@dataclass(frozen=True)
class Consistency:
    """Chi-square test of the residuals against the points' own variances.

    Attributes
    ----------
    chi2 : float
        Sum of squared normalised residuals, sum (r_i / s_i)^2.
    dof : float
        Effective degrees of freedom of chi2 (Satterthwaite [6]_ when the
        errors are correlated; n - p otherwise).
    scale : float
        chi2 is distributed as scale * chi-square(dof).
    p_value : float
        Probability of a chi2 at least this large if the model and the point
        variances are right.
    noise_ratio : float
        sqrt(chi2 / E[chi2]): the residual spread relative to the expected
        noise (1 when consistent).
    """

    chi2: float
    dof: float
    scale: float
    p_value: float
    noise_ratio: float


@dataclass(frozen=True)
class LineFit:
    """Line A x + B y + C = 0 (paper, eq. 1).

    Attributes
    ----------
    params : ndarray, shape (3,)
        (A, B, C) with A^2 + B^2 = 1, C in px. Gauge: Hesse normal form,
        C <= 0, i.e. (A, B) points from the pixel-frame origin towards the
        line and -C is its distance from the origin.
    cov : ndarray, shape (3, 3)
        Covariance of (A, B, C), rank 2 (units 1, 1, px; px^2 for C): the
        first-order image of the 2x2 covariance of (alpha, C) with
        (A, B) = (cos alpha, sin alpha), so it lies in the tangent space of
        the constraint A^2 + B^2 = 1.
    cov_angle_offset : ndarray, shape (2, 2)
        Covariance of (alpha, C), rad^2, rad px, px^2.
    ci95 : ndarray, shape (3, 2)
        Lower and upper 95 % bounds of A, B, C (k = 1.96).
    residuals : ndarray, shape (N,)
        Signed orthogonal distances A x + B y + C of the points, px.
    point_std : ndarray, shape (N,)
        Standard uncertainty of each point along the line normal, px.
    consistency : Consistency
    centroid : ndarray, shape (2,)
        Weighted centroid, a point on the line, px.
    """

    params: np.ndarray
    cov: np.ndarray
    cov_angle_offset: np.ndarray
    ci95: np.ndarray
    residuals: np.ndarray
    point_std: np.ndarray
    consistency: Consistency
    centroid: np.ndarray

    @property
    def normal(self):
        return self.params[:2]

    @property
    def direction(self):
        return np.array([-self.params[1], self.params[0]])


@dataclass(frozen=True)
class CircleFit:
    """Circle of centre (xc, yc) and radius r, px.

    Attributes
    ----------
    params : ndarray, shape (3,)
        (xc, yc, r), px.
    cov : ndarray, shape (3, 3)
        Covariance, px^2.
    ci95 : ndarray, shape (3, 2)
    residuals : ndarray, shape (N,)
        Signed distances |p - c| - r (positive outside), px.
    point_std : ndarray, shape (N,)
    consistency : Consistency
    converged : bool
    iterations : int
    """

    params: np.ndarray
    cov: np.ndarray
    ci95: np.ndarray
    residuals: np.ndarray
    point_std: np.ndarray
    consistency: Consistency
    converged: bool
    iterations: int

    @property
    def center(self):
        return self.params[:2]

    @property
    def radius(self):
        return float(self.params[2])


@dataclass(frozen=True)
class EllipseFit:
    """Ellipse x(phi) = c + Q(theta) (a cos phi, b sin phi), px.

    Attributes
    ----------
    params : ndarray, shape (5,)
        (xc, yc, a, b, theta): centre px, semi-axes px with a >= b, angle of
        the a axis from the x axis, rad, in (-pi/2, pi/2].
    cov : ndarray, shape (5, 5)
        Covariance of params (px^2, px rad, rad^2). For a circle (a = b)
        theta is undetermined: its variance is then inf and its
        covariances 0.
    ci95 : ndarray, shape (5, 2)
        Lower and upper 95 % bounds (k = 1.96).
    residuals : ndarray, shape (N,)
        Signed orthogonal distances to the ellipse (positive outside), px.
    phases : ndarray, shape (N,)
        Parameter phi of each point's foot point, rad.
    point_std : ndarray, shape (N,)
    consistency : Consistency
    converged : bool
    iterations : int
    """

    params: np.ndarray
    cov: np.ndarray
    ci95: np.ndarray
    residuals: np.ndarray
    phases: np.ndarray
    point_std: np.ndarray
    consistency: Consistency
    converged: bool
    iterations: int

    @property
    def center(self):
        return self.params[:2]

    @property
    def axes(self):
        return self.params[2:4]

    @property
    def angle(self):
        return float(self.params[4])


# ---------------------------------------------------------------- shared

def std_along(cov, normals):
    """Standard uncertainty of each point along the given unit normals, px.

    Parameters
    ----------
    cov : ndarray, shape (N, 2, 2) or (N,), or None
        Point covariances, px^2, or each point's variance along its normal
        already (returned as its square root whatever ``normals``).
    normals : ndarray, shape (N, 2) or (2,)
        Unit normals, one per point or one for all.

    Returns
    -------
    ndarray, shape (N,) or None
        ``sqrt(n^T cov n)``, px: the fits weigh each point by the inverse of
        its square, since only the error across the curve moves a point off
        it. None for ``cov`` None.
    """
    if cov is None:
        return None
    cov = np.asarray(cov, float)
    if cov.ndim == 1:  # already a variance along the normal
        return np.sqrt(cov)
    # Written out: einsum on (N, 2, 2) blocks is several times slower, and
    # this runs at every iteration of the ellipse fit.
    nx, ny = normals[..., 0], normals[..., 1]
    var = nx * nx * cov[:, 0, 0] + nx * ny * (cov[:, 0, 1] + cov[:, 1, 0]) + ny * ny * cov[:, 1, 1]
    return np.sqrt(var)


def information_matrices(h, s, xy, corr_length):
    """The two matrices of the sandwich covariance of a weighted regression.

    For residuals ``r_i / s_i`` with Jacobian rows ``h_i / s_i`` and errors
    correlated along the curve as ``exp(-d^2 / (4 corr_length^2))``, the
    covariance of the estimate is ``S^-1 M S^-1``. R is banded: it pairs
    point i with i + k (cyclically, k = 1 .. N // 2; the distance is
    Euclidean, so the ends of an open curve come out uncorrelated and those
    of a closed one correlated) up to the first offset k whose correlations
    all fall below 1e-4.

    Parameters
    ----------
    h : ndarray, shape (N, p)
        d(signed distance_i) / d(params), rows ordered along the curve.
    s : ndarray, shape (N,)
        Standard uncertainty of each point along the normal, px.
    xy : ndarray, shape (N, 2)
        The points, px, to measure distances along the curve.
    corr_length : float or None
        Correlation length of the point errors, px (the edge filter's
        sigma); None for independent errors.

    Returns
    -------
    S : ndarray, shape (p, p)
        ``H^T H`` of the weighted rows (the information if independent).
    M : ndarray, shape (p, p)
        ``H^T R H`` with R the error correlation matrix.
    trR2 : float
        sum_ij rho_ij^2, for the effective degrees of freedom.
    """
    from partinspect.vision._kernels import band_sums

    hw = h / s[:, None]
    S = hw.T @ hw
    M = S.copy()
    trR2 = float(len(h))
    if corr_length and len(h) >= 2:
        # sum_k sum_i rho_ki hw_i^T hw_(i+k) over the band.
        C, rho2 = band_sums(np.ascontiguousarray(xy, float), float(corr_length), np.ascontiguousarray(hw))
        M += C + C.T
        trR2 += 2.0 * rho2
    return S, M, trR2


def trace_r2(xy, corr_length):
    """``tr(R^2) = sum_ij rho_ij^2`` of points' errors correlated along a curve.

    The ``trR2`` of :func:`information_matrices` alone (the same band
    sums), for the Satterthwaite degrees of freedom of a residual test
    without the covariance [6]_.

    Parameters
    ----------
    xy : ndarray, shape (N, 2)
        The points, px, ordered along the curve.
    corr_length : float or None
        Correlation length of their errors, px (``rho_ij = exp(-d_ij^2 /
        (4 corr_length^2))``); None or 0 for independent errors.

    Returns
    -------
    float
        N for independent errors, more for correlated ones.
    """
    from partinspect.vision._kernels import band_sums

    if not corr_length or len(xy) < 2:
        return float(len(xy))
    _, rho2 = band_sums(np.ascontiguousarray(xy, float), float(corr_length), np.zeros((len(xy), 0)))
    return float(len(xy)) + 2.0 * rho2


def _uncertainty(h, s, xy, corr_length):
    """Sandwich covariance ``S^-1 M S^-1`` (see :func:`information_matrices`).

    Returns
    -------
    cov : ndarray, shape (p, p)
    sinv : ndarray, shape (p, p)
        S^-1, the covariance if the errors were independent.
    trR2 : float
    """
    S, M, trR2 = information_matrices(h, s, xy, corr_length)
    sinv = _pinv_sym(S, 1e-13)
    return sinv @ M @ sinv, sinv, trR2


def _pinv_sym(S, rcond):
    """Pseudo-inverse of a small symmetric matrix: ``np.linalg.pinv(S, rcond,
    hermitian=True)`` without its per-call overhead (the fits call it many
    thousand times on 2x2 to 5x5 matrices)."""
    ev, V = np.linalg.eigh(S)
    big = np.abs(ev) > rcond * np.abs(ev).max()
    inv = np.where(big, 1.0 / np.where(big, ev, 1.0), 0.0)
    return (V * inv) @ V.T


def _consistency(r, s, n_params, trR2):
    n = len(r)
    q = float(((r / s) ** 2).sum())
    dof_raw = max(n - n_params, 1)
    # Satterthwaite: chi2 ~ c chi-square(nu) with c = tr(R^2)/tr(R),
    # nu = tr(R)^2 / tr(R^2); the fit removes n_params of tr(R).
    trR = float(dof_raw)
    trR2 = max(trR2 * dof_raw / n, 1e-12)
    scale = trR2 / trR
    nu = trR * trR / trR2
    # scipy.special.chdtrc is what stats.chi2.sf evaluates, without the
    # distribution machinery's per-call overhead.
    p = float(special.chdtrc(nu, q / scale))
    return Consistency(q, nu, scale, p, float(np.sqrt(q / trR)))


def _ci(params, cov):
    u = np.sqrt(np.maximum(np.diag(cov), 0.0))
    return np.column_stack([params - COVERAGE_95 * u, params + COVERAGE_95 * u])


def as_points(xy, min_points):
    """Points as a float array of shape (N, 2), N >= ``min_points``.

    Raises
    ------
    ValueError
        For another shape or fewer points: what a fit of that model cannot
        be made from (3 for a line or circle, 6 for an ellipse), said
        before any arithmetic.
    """
    xy = np.asarray(xy, float)
    if xy.ndim != 2 or xy.shape[1] != 2:
        raise ValueError(f"points must have shape (N, 2), got {xy.shape}")
    if len(xy) < min_points:
        raise ValueError(f"need at least {min_points} points, got {len(xy)}")
    return xy


# ---------------------------------------------------------------- line

def _line_tls(xy, w):
    c = (w @ xy) / w.sum()
    dx, dy = xy[:, 0] - c[0], xy[:, 1] - c[1]
    # Smallest right singular vector of the weighted, centred points: the
    # minor axis of their 2x2 scatter matrix, in closed form (an SVD of the
    # (N, 2) matrix costs more in overhead than in arithmetic).
    wx = w * dx
    sxx, syy, sxy = float(wx @ dx), float(w @ (dy * dy)), float(wx @ dy)
    t = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)  # major axis angle
    n = np.array([-np.sin(t), np.cos(t)])
    return n, c


def _line_normal_std(cov):
    """std(normal): :func:`std_along` of every point along one common
    normal, with the covariance parts taken out once (the line fit asks
    three times)."""
    cov = np.asarray(cov, float)
    if cov.ndim == 1:  # already a variance along the normal
        s = np.sqrt(cov)
        return lambda nrm: s
    c00, c01, c11 = cov[:, 0, 0], cov[:, 0, 1] + cov[:, 1, 0], cov[:, 1, 1]

    def std(nrm):
        nx, ny = nrm
        return np.sqrt(nx * nx * c00 + nx * ny * c01 + ny * ny * c11)

    return std


def fit_line(xy, cov=None, *, corr_length=None, with_cov=True):
    """Orthogonal (total least squares) line fit by SVD, with covariance.

    Parameters
    ----------
    xy : array_like, shape (N, 2)
        Points, px, ordered along the line when ``corr_length`` is given.
    cov : array_like, shape (N, 2, 2) or (N,), optional
        Covariance of each point, px^2 (or its variance along the normal).
        Weights are the inverse variances along the fitted normal. Without
        it, all points weigh the same and their common standard uncertainty
        is estimated from the residuals (N - 2 degrees of freedom).
    corr_length : float, optional
        Correlation length of the point errors along the line, px (the edge
        filter's sigma for points from ``edge_points``).
    with_cov : bool
        Without it, ``cov``, ``cov_angle_offset`` and ``ci95`` are None and
        the rest is the same: a test of a piece needs only its consistency,
        and most pieces tested are not kept (:func:`line_with_covariance`
        adds them later, the same as computed here).

    Returns
    -------
    LineFit

    Notes
    -----
    Minimises sum_i w_i (A x_i + B y_i + C)^2 / (A^2 + B^2) (paper, eq. 2):
    the normal (A, B) is the right singular vector of the smallest singular
    value of the weighted centred points, C = -(A, B) . centroid [1]_.
    With weights from the covariances, two passes are made (the normal
    variances depend on the normal).
    """
    xy = as_points(xy, 3)
    n_pts = len(xy)
    w = np.ones(n_pts)
    nrm, c = _line_tls(xy, w)
    if cov is not None:
        std = _line_normal_std(cov)
        for _ in range(2):
            s = std(nrm)
            w = 1.0 / (s * s)
            nrm, c = _line_tls(xy, w)
        s = std(nrm)
    C = -float(nrm @ c)
    if C > 0:
        nrm, C = -nrm, -C
    r = xy @ nrm + C
    if cov is None:
        s = np.full(n_pts, np.sqrt((r * r).sum() / max(n_pts - 2, 1)))
        s = np.maximum(s, 1e-12)
    params = np.array([nrm[0], nrm[1], C])
    if not with_cov:
        return LineFit(params, None, None, None, r, s, _consistency(r, s, 2, trace_r2(xy, corr_length)), c)
    cov3, cov2, trR2 = _line_cov(params, s, xy, corr_length)
    return LineFit(params, cov3, cov2, _ci(params, cov3), r, s, _consistency(r, s, 2, trR2), c)


def _line_cov(params, s, xy, corr_length):
    """Covariances of (A, B, C) and (alpha, C) of a line fit, and trR2."""
    alpha = float(np.arctan2(params[1], params[0]))
    # d r_i / d(alpha, C) with (A, B) = (cos alpha, sin alpha).
    h = np.column_stack([-np.sin(alpha) * xy[:, 0] + np.cos(alpha) * xy[:, 1], np.ones(len(xy))])
    cov2, _, trR2 = _uncertainty(h, s, xy, corr_length)
    G = np.array([[-np.sin(alpha), 0.0], [np.cos(alpha), 0.0], [0.0, 1.0]])
    return G @ cov2 @ G.T, cov2, trR2


def line_with_covariance(fit, xy, corr_length):
    """A LineFit made by ``fit_line(..., with_cov=False)`` with its covariances and intervals added.

    Parameters
    ----------
    fit : LineFit
        Returned as it is when it has its covariances already.
    xy : array_like, shape (N, 2)
        The points it was fitted to, px.
    corr_length : float or None
        As :func:`fit_line`'s.

    Returns
    -------
    LineFit
        From the same weights (``fit.point_std``), so the same as
        ``fit_line(..., with_cov=True)`` computes them: a caller that tests
        many candidate lines and keeps few pays for the covariances of the
        kept ones only.
    """
    if fit.cov is not None:
        return fit
    cov3, cov2, _ = _line_cov(fit.params, fit.point_std, np.asarray(xy, float), corr_length)
    return replace(fit, cov=cov3, cov_angle_offset=cov2, ci95=_ci(fit.params, cov3))


def line_kcr_bound(xy_true, normal, normal_std, corr_length=None):
    """Lower bound on the covariance of (alpha, C) for points on a line.

    The KCR bound [3]_ [4]_ (H^T R^-1 H)^-1 for normal errors with standard
    deviations ``normal_std`` and, with ``corr_length``, correlation
    exp(-d^2 / (4 l^2)) between points at distance d (then the Cramer-Rao
    bound for those correlated Gaussian errors).

    Parameters
    ----------
    xy_true : ndarray, shape (N, 2)
        True positions of the points on the line, px.
    normal : ndarray, shape (2,)
        True unit normal.
    normal_std : float or ndarray, shape (N,)
    """
    xy_true = np.asarray(xy_true, float)
    alpha = np.arctan2(normal[1], normal[0])
    h = np.column_stack([-np.sin(alpha) * xy_true[:, 0] + np.cos(alpha) * xy_true[:, 1],
                         np.ones(len(xy_true))])
    return _crb(h, np.broadcast_to(np.asarray(normal_std, float), (len(h),)), xy_true, corr_length)


def _crb(h, s, xy, corr_length):
    if corr_length:
        d = np.linalg.norm(xy[:, None, :] - xy[None, :, :], axis=2)
        R = np.exp(-(d * d) / (4 * corr_length ** 2)) * np.outer(s, s)
        X = np.linalg.solve(R, h)
        return np.linalg.inv(h.T @ X)
    hw = h / s[:, None]
    return np.linalg.inv(hw.T @ hw)


# ---------------------------------------------------------------- circle

def _kasa(xy):
    """Algebraic circle fit (Kasa), the start of the geometric fit."""
    x, y = xy[:, 0], xy[:, 1]
    A = np.column_stack([x, y, np.ones(len(x))])
    sol, *_ = np.linalg.lstsq(A, x * x + y * y, rcond=None)
    xc, yc = sol[0] / 2, sol[1] / 2
    return np.array([xc, yc, np.sqrt(max(sol[2] + xc * xc + yc * yc, 1e-12))])


def fit_circle(xy, cov=None, *, corr_length=None, blur=None, max_iter=50, tol=1e-10):
    """Geometric circle fit (Gauss-Newton on orthogonal distances) [2]_.

    Parameters
    ----------
    xy : array_like, shape (N, 2)
        Points, px (ordered along the circle when ``corr_length`` is given).
    cov : array_like, shape (N, 2, 2) or (N,), optional
        Point covariances, px^2, as in :func:`fit_line`.
    corr_length : float, optional
        Correlation length of the point errors, px.
    blur : float, optional
        Width of the edge profile, px: the fitted radius is increased by
        blur^2 / (2 r), the smoothing bias of a curved edge (see
        :func:`fit_ellipse`).

    Returns
    -------
    CircleFit
    """
    xy = as_points(xy, 3)
    if blur:
        c0 = _kasa(xy)
        d = xy - c0[:2]
        xy = xy + (0.5 * blur * blur / c0[2]) * d / np.linalg.norm(d, axis=1)[:, None]
    p = _kasa(xy)
    converged = False
    it = 0
    for it in range(1, max_iter + 1):
        d = xy - p[:2]
        rho = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-12)
        u = d / rho[:, None]
        r = rho - p[2]
        s = std_along(cov, u) if cov is not None else np.ones(len(xy))
        h = np.column_stack([-u, -np.ones(len(xy))])
        hw, rw = h / s[:, None], r / s
        step, *_ = np.linalg.lstsq(hw, -rw, rcond=None)
        p = p + step
        if np.abs(step).max() < tol * max(1.0, p[2]):
            converged = True
            break
    d = xy - p[:2]
    rho = np.hypot(d[:, 0], d[:, 1])
    u = d / rho[:, None]
    r = rho - p[2]
    h = np.column_stack([-u, -np.ones(len(xy))])
    if cov is not None:
        s = std_along(cov, u)
    else:
        s = np.full(len(xy), max(np.sqrt((r * r).sum() / max(len(xy) - 3, 1)), 1e-12))
    covp, _, trR2 = _uncertainty(h, s, xy, corr_length)
    return CircleFit(p, covp, _ci(p, covp), r, s, _consistency(r, s, 3, trR2), converged, it)


# ---------------------------------------------------------------- ellipse

def ellipse_curvature(params, phi):
    """Curvature of the ellipse (xc, yc, a, b, theta) at phases phi, 1/px, shape (N,).

    kappa = a b / (a^2 sin^2 phi + b^2 cos^2 phi)^(3/2), the curvature of
    the parametric curve (a cos phi, b sin phi).
    """
    _, _, a, b, _ = params
    sp, cp = np.sin(phi), np.cos(phi)
    return a * b / (a * a * sp * sp + b * b * cp * cp) ** 1.5


def ellipse_points(params, phi):
    """Points (N, 2) of the ellipse (xc, yc, a, b, theta) at phases phi."""
    xc, yc, a, b, th = params
    c, s = np.cos(th), np.sin(th)
    phi = np.ravel(phi)  # a scalar phase gives one point
    u, v = a * np.cos(phi), b * np.sin(phi)
    out = np.empty((len(u), 2))
    out[:, 0] = xc + c * u - s * v
    out[:, 1] = yc + s * u + c * v
    return out


def _ellipse_start(xy):
    """Direct algebraic fit (Fitzgibbon / Halir-Flusser, via OpenCV) [5]_."""
    (cx, cy), (w, h), ang = cv2.fitEllipseDirect(xy.astype(np.float32).reshape(-1, 1, 2))
    if not (np.isfinite([cx, cy, w, h, ang]).all() and w > 0 and h > 0):
        p = _kasa(xy)
        return np.array([p[0], p[1], p[2], p[2] * 0.999, 0.0])
    # OpenCV: full axis lengths; ang (degrees) rotates the first (width) axis.
    return _canonical(np.array([cx, cy, w / 2.0, h / 2.0, np.deg2rad(ang)]))


def _canonical(p):
    """a >= b and theta in (-pi/2, pi/2]."""
    p = np.array(p, float)
    if p[3] > p[2]:
        p[2], p[3] = p[3], p[2]
        p[4] += np.pi / 2
    p[4] = (p[4] + np.pi / 2) % np.pi - np.pi / 2
    if p[4] <= -np.pi / 2:
        p[4] += np.pi
    return p


def foot_phases(xy, params, phi=None, iters=6):
    """Phases of the orthogonal foot points of points on an ellipse.

    Newton's method on each point (compiled:
    :func:`partinspect.vision._kernels.foot_phases`): the foot point is
    where the ellipse's normal passes through the point, which is what the
    orthogonal distance of every ellipse fit is measured to [2]_.

    Parameters
    ----------
    xy : array_like, shape (N, 2)
        Points, px.
    params : array_like, shape (5,)
        (xc, yc, a, b, theta) as :class:`EllipseFit`.
    phi : array_like, shape (N,), optional
        Start phases, rad; default the points' angles scaled to the ellipse.
    iters : int
        Newton steps at most; a point stops earlier once its phase moves by
        less than 1e-13 rad (Newton converges quadratically, so the next
        step would change nothing beyond rounding).

    Returns
    -------
    ndarray, shape (N,)
        Phases, rad.
    """
    from partinspect.vision._kernels import foot_phases as compiled

    xy = np.ascontiguousarray(xy, float)
    start = phi is None
    phi = np.empty(len(xy)) if start else np.array(phi, float)
    return compiled(xy, np.asarray(params, float), phi, int(iters), start)


def ellipse_geometry(xy, params, phi):
    """Residuals (m,), outward unit normals (m, 2) and rows h_i (m, 5) at the
    foot points (compiled: :func:`partinspect.vision._kernels.ellipse_geometry`).

    ``xy`` are the points (px), ``params`` the ellipse (xc, yc, a, b,
    theta) and ``phi`` the points' foot phases (:func:`foot_phases`, rad);
    the residuals are signed orthogonal distances, px, positive outside.

    The outward normal in the ellipse frame is l = (b cos phi, a sin phi)
    normalised, in the image n = Q(theta) l. Row h_i = d(signed distance_i)
    / d(params) = -n . d(x(phi)) / d(params): the phase derivative drops out
    because dx/dphi is tangent (Schur complement of the block-diagonal phase
    part, [2]_ section 4). With dx/d(a, b, theta) = Q (cos phi, 0),
    Q (0, sin phi), Q (-b sin phi, a cos phi), the products reduce to the
    ellipse frame: h = (-n_x, -n_y, -l_x cos phi, -l_y sin phi,
    b sin phi l_x - a cos phi l_y).
    """
    from partinspect.vision._kernels import ellipse_geometry as compiled

    return compiled(np.ascontiguousarray(xy, float), np.asarray(params, float), np.ascontiguousarray(phi, float))


# An "ellipse" far larger than its points is no ellipse they show: the
# fits of the 2D chain (segmentation, features) stop before their
# semi-major axis exceeds this many times the points' extent (see
# _lm_ellipses); such a piece's best conic is a parabola or a hyperbola.
MAX_AXIS_SPANS = 50.0


def axis_bound(xy):
    """The largest semi-major axis of a plausible ellipse through points xy, px.

    ``MAX_AXIS_SPANS`` times the points' extent (at least 1 px): beyond it
    the points show no ellipse but a flatter conic, and a fit of the 2D
    chain that would grow past it stops (``EllipseJob.max_axis``).
    """
    return MAX_AXIS_SPANS * max(float(np.ptp(xy, axis=0).max()), 1.0)


def direct_residuals(xy):
    """The direct fit of points xy and their orthogonal residuals about it.

    A cheap look at whether points are one ellipse, without the iterative
    fit: the direct (algebraic) fit [5]_ is biased but not far off, so its
    residuals tell points of one ellipse from points of two.

    Returns
    -------
    tuple or None
        (params, phases, residuals (M,), unit normals (M, 2)) of
        :func:`_ellipse_start` and :func:`ellipse_geometry`, or None when
        the direct fit is no finite ellipse.
    """
    p = _ellipse_start(xy)
    if p[3] <= 0 or not np.all(np.isfinite(p)):
        return None
    phi = foot_phases(xy, p)
    r, n, _ = ellipse_geometry(xy, p, phi)
    return p, phi, r, n


def fit_ellipse(xy, cov=None, *, corr_length=None, blur=None, max_iter=100, tol=1e-9, start=None):
    """Geometric ellipse fit in parametric form (Gander, Golub & Strebel 1994).

    Unknowns are the centre, semi-axes, angle and one phase phi_i per point;
    the residual of point i is the 2-vector p_i - x(phi_i). Each damped
    Gauss-Newton (Levenberg-Marquardt) step eliminates the diagonal phase
    block of the normal equations: a 5x5 Schur complement, then the phases
    by back-substitution, O(m) per iteration for m points [2]_
    (:func:`_lm_ellipses`). The start is the direct algebraic fit [5]_ with
    each phase at its point's foot point. At convergence dx/dphi_i is
    tangent, so the Schur complement is sum_i w_i h_i h_i^T with h_i the
    derivative of the orthogonal distance, which the covariance is computed
    from.

    Parameters
    ----------
    xy : array_like, shape (N, 2), N >= 6
        Points, px (ordered along the curve when ``corr_length`` is given).
    cov : array_like, shape (N, 2, 2) or (N,), optional
        Point covariances, px^2; weights are inverse variances along the
        ellipse normal at each foot point. Without it, equal weights and a
        common point uncertainty estimated from the residuals.
    corr_length : float, optional
        Correlation length of the point errors along the curve, px.
    blur : float, optional
        Width of the edge profile, px (e.g. the median of
        ``EdgePoints.width`` over the points). Gaussian smoothing moves
        points on a curve towards the centre of curvature by
        blur^2 kappa / 2; with ``blur`` each point is moved back by that
        amount at the fitted curvature and the fit repeated (twice). The
        residuals returned are those of the corrected points.
    start : array_like, shape (5,), optional
        Start values (xc, yc, a, b, theta) instead of the direct algebraic
        fit, e.g. the fit of nearly the same points: the same minimum is
        reached in fewer iterations when the start is near it.

    Returns
    -------
    EllipseFit

    Notes
    -----
    The 5x5 covariance is S^-1 for independent errors, Kanatani's KCR
    bound at the estimate [3]_ [4]_ (which the geometric fit attains to
    first order), and the sandwich form of the module docstring with
    ``corr_length``.
    """
    xy = as_points(xy, 6)
    return fit_ellipses([EllipseJob(xy, cov, corr_length, blur, start)], max_iter, tol)[0]


@dataclass(frozen=True)
class EllipseJob:
    """One ellipse fit of :func:`fit_ellipses`.

    Attributes
    ----------
    xy, cov, corr_length, blur, start
        The arguments of :func:`fit_ellipse` (``xy`` as checked by
        :func:`as_points`).
    init : tuple, optional
        (params, phases): an algebraic start and its foot phases the caller
        has computed already (:func:`direct_residuals`).
    max_axis : float, optional
        The fit stops before a step would take its semi-major axis beyond
        this, px (:func:`axis_bound`).
    """

    xy: np.ndarray
    cov: object = None
    corr_length: float = None
    blur: float = None
    start: object = None
    init: tuple = None
    max_axis: float = None


def fit_ellipses(jobs, max_iter=100, tol=1e-9, need_converged=False, with_cov=True, sigma_tol=None):
    """:func:`fit_ellipse` of several point sets at once.

    Each fit follows exactly the iteration it would follow alone
    (:func:`_lm_ellipses`, compiled); a batch lets the callers (the
    segmentation's trial fits, the image features' rounds of outlier
    rejection) collect their fits in one place.

    Parameters
    ----------
    jobs : list of EllipseJob
    max_iter, tol : see fit_ellipse
    need_converged : bool
        Return None for a fit that does not converge within ``max_iter``
        (its covariance and test are then not computed; blurred jobs are
        not supported).
    with_cov : bool
        Without it, the fits' ``cov`` and ``ci95`` are None (a test needs
        only the consistency; :func:`ellipse_with_covariance` adds them later, the
        same as computed here).
    sigma_tol : float, optional
        Also converged when the remaining Gauss-Newton step is below this
        many standard uncertainties in every direction (see
        :func:`_lm_ellipses`); with ``tol=None`` it is the only criterion.

    A job's ``max_axis`` stops its fit before a step that would take the
    semi-major axis beyond it (not converged; see :func:`_lm_ellipses`).

    Returns
    -------
    list of EllipseFit (or None)
    """
    if need_converged and any(job.blur for job in jobs):
        raise ValueError("need_converged is not supported with blur")
    starts = []
    for job in jobs:
        if job.init is not None:
            starts.append(job.init)
        else:
            p = _ellipse_start(job.xy) if job.start is None else _canonical(job.start)
            starts.append((p, foot_phases(job.xy, p)))
    xys = [job.xy for job in jobs]
    # A blurred job's fits before its last correction give only the points'
    # shifts: their covariances are not computed.
    fits = _fit_ellipses_once(xys, jobs, starts, max_iter, tol, need_converged,
                              [with_cov and not job.blur for job in jobs], sigma_tol)
    blurred = [k for k, job in enumerate(jobs) if job.blur]
    for last in (False, True) if blurred else ():
        for k in blurred:
            f, blur = fits[k], jobs[k].blur
            _, n, _ = ellipse_geometry(jobs[k].xy, f.params, f.phases)
            xys[k] = jobs[k].xy + (0.5 * blur * blur * ellipse_curvature(f.params, f.phases))[:, None] * n
            # The shift is a small fraction of a pixel: start from the fit
            # before it.
            p = _canonical(f.params)
            starts[k] = (p, foot_phases(xys[k], p))
        sub = _fit_ellipses_once([xys[k] for k in blurred], [jobs[k] for k in blurred],
                                 [starts[k] for k in blurred], max_iter, tol, False, with_cov and last, sigma_tol)
        for k, f in zip(blurred, sub):
            fits[k] = f  # its residuals are of the corrected points
    return fits


def _fit_ellipses_once(xys, jobs, starts, max_iter, tol, need_converged, with_cov=True, sigma_tol=None):
    """The fits of fixed points (the loop of fit_ellipses). ``with_cov``:
    for all the fits, or a sequence of one per fit."""
    if isinstance(with_cov, bool):
        with_cov = [with_cov] * len(xys)
    out = [None] * len(xys)
    res = _lm_ellipses(xys, [job.cov for job in jobs], starts, max_iter, tol, sigma_tol,
                       [job.max_axis for job in jobs])
    for k, (p, converged, it) in enumerate(res):
        if need_converged and not converged:
            continue
        try:
            out[k] = _ellipse_result(xys[k], jobs[k].cov, jobs[k].corr_length, p, converged, it, with_cov[k])
        except (ValueError, np.linalg.LinAlgError):
            if not need_converged:
                raise
    return out


def _ellipse_result(xy, cov, corr_length, p, converged, it, with_cov=True):
    """EllipseFit at the end of the iteration: foot points, covariance
    (None without ``with_cov``), test."""
    n_pts = len(xy)
    p = _canonical(p)
    phi = foot_phases(xy, p, None, iters=20)
    r, n, h = ellipse_geometry(xy, p, phi)
    if cov is not None:
        s = std_along(cov, n)
    else:
        s = np.full(n_pts, max(np.sqrt((r * r).sum() / max(n_pts - 5, 1)), 1e-12))
    if not with_cov:
        return EllipseFit(p, None, None, r, phi, s, _consistency(r, s, 5, trace_r2(xy, corr_length)), converged, it)
    covp, _, trR2 = _uncertainty(h, s, xy, corr_length)
    covp = _theta_gauge(p, h, s, covp)
    cons = _consistency(r, s, 5, trR2)
    return EllipseFit(p, covp, _ci(p, covp), r, phi, s, cons, converged, it)


def ellipse_with_covariance(fit, xy, corr_length):
    """An EllipseFit made by ``with_cov=False`` with its covariance and intervals added.

    Parameters
    ----------
    fit : EllipseFit
        Of :func:`fit_ellipses` without ``with_cov``; returned as it is
        when it has its covariance already.
    xy : array_like, shape (N, 2)
        The points it was fitted to, px.
    corr_length : float or None
        As :func:`fit_ellipse`'s.

    Returns
    -------
    EllipseFit
        From the same foot points and weights, so the same as
        :func:`_ellipse_result` computes them: a caller that tests many
        candidate arcs and keeps few pays for the covariances of the kept
        ones only.
    """
    if fit.cov is not None:
        return fit
    _, _, h = ellipse_geometry(xy, fit.params, fit.phases)
    covp, _, _ = _uncertainty(h, fit.point_std, xy, corr_length)
    covp = _theta_gauge(fit.params, h, fit.point_std, covp)
    return replace(fit, cov=covp, ci95=_ci(fit.params, covp))


def _lm_ellipses(xys, covs, starts, max_iter, tol, sigma_tol=None, max_axis=None):
    """Damped Gauss-Newton of Gander et al. [2]_ on several point sets, one by one.

    Unknowns u = (xc, yc, a, b, theta) and one phase phi_i per point; the
    residual rho_i = p_i - x(phi_i; u) is weighted by w_i, the inverse
    variance of the point along the curve's normal, and written in the
    ellipse's own frame (same cost, simpler derivatives). The diagonal phase
    block of the damped normal equations is eliminated: with J_i the 2 x 5
    dense part of the residual's derivative, n_i and t_i the unit normal and
    tangent, hn = J^T n, ht = J^T t, rn = n . rho, rt = t . rho, the 5 x 5
    system is

        (Sn + lam / (1 + lam) St + lam diag(Sn + St)) du = -(Gn + lam / (1 + lam) Gt)

    (Sn = sum w hn hn^T, St = sum w ht ht^T, Gn = sum w hn rn, Gt = sum w
    ht rt) and dphi_i = -(rt_i + ht_i . du) / (|j_i| (1 + lam)), j_i the
    phase derivative: :func:`fit_ellipse`'s Schur complement without its
    cancellation, the two matrices serving every damping tried.

    A short arc's cost is a long, curved, nearly flat valley, where plain
    Levenberg-Marquardt creeps by small steps. So each step v gets the
    geodesic acceleration a / 2 [7]_ (a solves the same system with the
    residuals' second directional derivative along v, a finite difference),
    a step whose correction exceeds ``_kernels.ACCEL_RATIO`` / 2 of it is
    refused, and the damping follows the gain ratio rho of the actual to
    the predicted decrease (Nielsen's rule [8]_: times max(1/3, 1 - (2 rho
    - 1)^3) after a success, 2, 4, 8, ... after failures), so that a
    success does not make the next step too bold.

    A fit has converged on ``tol`` (the accepted step moves the curve by
    less than ``tol`` max(1, a) px) or on ``sigma_tol`` (the undamped step
    du = -Sn^-1 Gn is below ``sigma_tol`` standard uncertainties in every
    direction, du^T Sn du <= sigma_tol^2: the chi-square is then settled,
    all a test needs). It also stops when no damping up to 1e12 gives an
    acceptable step, after ``max_iter`` steps, or before a step that would
    take its semi-major axis beyond its ``max_axis`` (or further beyond):
    the best iterate within the bound is returned (for a fit that starts
    beyond it, the start or the smallest iterate).

    The iteration runs compiled
    (:func:`partinspect.vision._kernels.lm_ellipse`): in numpy its many
    small calls per iteration cost more in overhead than in arithmetic.

    Returns
    -------
    list of (params, converged, iterations)
    """
    from partinspect.vision._kernels import lm_ellipse

    out = []
    for k, (xy, cov, (p0, phi0)) in enumerate(zip(xys, covs, starts)):
        xy = np.ascontiguousarray(xy, float)
        cparts = np.empty((len(xy), 3))
        if cov is None:  # unit weights
            cparts[:] = (1.0, 0.0, 1.0)
        else:
            cov = np.asarray(cov, float)
            if cov.ndim == 1:  # a variance along the normal, whatever the normal
                cparts[:, 0] = cparts[:, 2] = cov
                cparts[:, 1] = 0.0
            else:
                # Parts of n^T cov n for n = (nx, ny): nx^2, nx ny, ny^2.
                cparts[:, 0] = cov[:, 0, 0]
                cparts[:, 1] = cov[:, 0, 1] + cov[:, 1, 0]
                cparts[:, 2] = cov[:, 1, 1]
        bound = np.inf if max_axis is None or max_axis[k] is None else float(max_axis[k])
        p, converged, it = lm_ellipse(xy, cparts, np.array(p0, float), np.array(phi0, float), int(max_iter),
                                      -1.0 if tol is None else float(tol),
                                      -1.0 if sigma_tol is None else float(sigma_tol), bound)
        out.append((p, bool(converged), int(it)))
    return out


def _theta_gauge(p, h, s, covp):
    """Mark theta undetermined when the data cannot tell it (a circle)."""
    col = h[:, 4] / s
    others = h[:, :4] / s[:, None]
    # Part of the theta column not explained by the other four.
    coef, *_ = np.linalg.lstsq(others, col, rcond=None)
    resid = np.linalg.norm(col - others @ coef)
    if resid < 1e-9 * max(np.linalg.norm(others), 1.0):
        covp = covp.copy()
        covp[4, :] = covp[:, 4] = 0.0
        covp[4, 4] = np.inf
    return covp


def ellipse_kcr_bound(params_true, xy_true, normal_std, corr_length=None):
    """Lower bound on the covariance of (xc, yc, a, b, theta).

    KCR bound [3]_ [4]_ (H^T R^-1 H)^-1 with rows h_i evaluated at the
    foot points of the true point positions on the true ellipse, for normal
    errors of standard deviation ``normal_std`` (scalar or (N,)) and, with
    ``corr_length``, correlation exp(-d^2 / (4 l^2)).
    """
    xy_true = np.asarray(xy_true, float)
    params_true = np.asarray(params_true, float)
    phi = foot_phases(xy_true, params_true, None, iters=20)
    _, _, h = ellipse_geometry(xy_true, params_true, phi)
    s = np.broadcast_to(np.asarray(normal_std, float), (len(h),))
    return _crb(h, s, xy_true, corr_length)
