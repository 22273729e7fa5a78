"""3D lines and circles fitted to the edge points of both images at once.

Rather than fitting a 3D primitive to triangulated points (whose errors are
correlated through the matching, and much larger in depth), the primitive is
fitted directly to the 2D edge points of both views: each edge point's
residual is its distance to the projection of the 3D primitive, weighted by
the point's standard uncertainty across the edge (a two-view bundle
adjustment of one primitive). Its covariance is first-order propagation from
pixels to the 3D parameters in one step: ``(J^T W J)^-1`` for independent
point errors, and the sandwich ``S^-1 M S^-1`` when neighbouring edge points
share smoothed noise (see :func:`partinspect.vision.fitting.information_matrices`).
A view may also carry a Type B standard uncertainty per point for an
uncorrected systematic displacement (``View.bias``, correlated along the
edge over a longer length): the points are then weighted by their random
and systematic variances together, and the systematic part of the
covariance is propagated by the same sandwich and reported separately.

Inputs are *ideal* pixel coordinates (distortion removed from the points,
``K @ [undistort_points(uv), 1]``) in the rig frame convention of
:mod:`partinspect.vision.calibration`.

References
----------
.. [1] Hartley, R., & Zisserman, A. (2004). Multiple View Geometry in
       Computer Vision, 2nd ed.: sections 4.2.6 (Sampson error), 5.2
       (covariance by back-propagation), 8.2 (action of a projective camera
       on conics) and 18.1 (bundle adjustment).
.. [2] Quan, L. (1996). Conic reconstruction and correspondence from two
       views. IEEE PAMI 18(2), 151-160.
"""

from dataclasses import dataclass

import numpy as np
from scipy.special import chdtrc

from partinspect.frames import plane_basis
from partinspect.vision.fitting import fit_ellipse, information_matrices, trace_r2

__all__ = ["View", "Line3D", "Circle3D", "fit_line_3d", "fit_circle_3d", "circle_image_conic",
           "circle_consistency", "minimal_residuals", "circle_residuals_at", "information_parts"]


@dataclass(frozen=True)
class View:
    """Edge points of one feature in one image.

    Attributes
    ----------
    xy : ndarray, shape (N, 2)
        Ideal (undistorted) pixel coordinates.
    sigma : ndarray, shape (N,)
        Standard uncertainty of each point across the edge from image
        noise, px.
    P : ndarray, shape (3, 4)
        Camera matrix ``K [R | t]`` mapping rig-frame points (mm) to ideal pixels.
    corr_length : float or None
        Correlation length of the point errors along the edge, px (the edge
        filter's sigma: neighbouring edge points share smoothed noise), with
        the points ordered along the edge; None for independent errors.
    bias : ndarray, shape (N,) or None
        Standard uncertainty of an uncorrected *systematic* displacement of
        each point across the edge, px (a Type B evaluation, JCGM 100 4.3),
        or None for none. It does not average out along the edge: the
        displacements of two points are correlated as
        ``exp(-d^2 / (4 bias_corr_length^2))`` at distance d.
    bias_corr_length : float or None
        Correlation length of ``bias`` along the edge, px; None: fully
        correlated over the whole view.
    sigma_correction : ndarray, shape (N,) or None
        Standard uncertainty across the edge from the noise of a correction
        applied to the points, px, or None: random (it changes from image
        to image, as ``sigma``), but correlated along the edge over its own
        ``correction_corr_length``, longer than the image noise's (the
        correction is averaged along the edge).
    correction_corr_length : float or None
        Its correlation length along the edge, px (same form as ``corr_length``).
    modes : ndarray, shape (k, N) or None
        Systematic displacement patterns across the edge, px: row j is the
        displacement of every point by one standard uncertainty of an
        unknown coefficient (a Type B, JCGM 100 4.3) whose effect on the
        points is known in shape, e.g. a broken rim's band place, whose
        error moves each point by its angle's own amount. One coefficient
        moves every view carrying its name (``mode_names``) together, so
        what is common round a rim goes to its radius and only what varies
        round it to its centre.
    mode_names : tuple of k hashable or None
        The coefficients' names: rows of two views with one name share it.
    """

    xy: np.ndarray
    sigma: np.ndarray
    P: np.ndarray
    corr_length: float | None = None
    bias: np.ndarray | None = None
    bias_corr_length: float | None = None
    sigma_correction: np.ndarray | None = None
    correction_corr_length: float | None = None
    modes: np.ndarray | None = None
    mode_names: tuple | None = None

    def __post_init__(self):
        # A mode without its name would be dropped where the views' modes are
        # summed by name, silently understating the fit's Type B.
        if self.modes is not None and (self.mode_names is None or len(self.mode_names) != len(self.modes)):
            raise ValueError(f"View: {len(self.modes)} modes but {0 if self.mode_names is None else len(self.mode_names)}"
                             " mode names")

    @property
    def random_sigma(self):
        """Standard uncertainty of each point from image noise, its correction's included, px."""
        if self.sigma_correction is None:
            return self.sigma
        return np.sqrt(self.sigma * self.sigma + self.sigma_correction * self.sigma_correction)

    @property
    def total_sigma(self):
        """Standard uncertainty of each point, random and systematic together, px (the fit's weights)."""
        s = self.random_sigma
        if self.bias is None and self.modes is None:
            return s
        var = s * s
        if self.bias is not None:
            var = var + self.bias * self.bias
        if self.modes is not None:
            var = var + np.sum(np.square(self.modes), axis=0)
        return np.sqrt(var)


@dataclass(frozen=True)
class Line3D:
    """A fitted 3D line (rig frame, mm).

    ``point`` is the point of the line nearest to the centroid of the
    back-projected data; ``covariance`` is its 3x3 covariance (mm^2), whose
    component along ``direction`` is zero by construction (the gauge).
    ``direction_cov`` is the 3x3 covariance of the unit direction.
    ``param_cov`` is the 4x4 covariance of the minimal parameters.
    Covariances include the views' systematic parts (``View.bias``), of
    which ``param_cov_systematic`` is the share in ``param_cov``.
    """

    point: np.ndarray
    direction: np.ndarray
    covariance: np.ndarray
    direction_cov: np.ndarray
    param_cov: np.ndarray
    chi2: float
    dof: int
    param_cov_systematic: np.ndarray | None = None


@dataclass(frozen=True)
class Circle3D:
    """A fitted 3D circle (rig frame, mm).

    Attributes
    ----------
    center, normal : ndarray, shape (3,)
    radius : float
    covariance : ndarray, shape (3, 3)
        Covariance of the centre, mm^2.
    normal_cov : ndarray, shape (3, 3)
        Covariance of the unit normal (rank 2).
    radius_std : float
        Standard uncertainty of the radius, mm.
    param_cov : ndarray, shape (6, 6)
        Covariance of (centre, normal tilt a, normal tilt b, radius).
    chi2 : float
        Weighted sum of squared residuals at the solution.
    dof : int
        Number of residuals minus 6.
    param_cov_systematic : ndarray, shape (6, 6) or None
        The share of ``param_cov`` due to the views' uncorrected systematic
        displacements (``View.bias``, ``View.modes``); the covariances above
        include it.
    """

    center: np.ndarray
    normal: np.ndarray
    radius: float
    covariance: np.ndarray
    normal_cov: np.ndarray
    radius_std: float
    param_cov: np.ndarray
    chi2: float
    dof: int
    param_cov_systematic: np.ndarray | None = None


def _cross3(a, b):
    """``np.cross`` of two 3-vectors, the same arithmetic without its
    overhead (the Gauss-Newton residuals call it thousands of times)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def _cross_rows(a, b):
    """Row-wise cross products of (k, 3) arrays (``np.cross`` without its overhead)."""
    out = np.empty_like(a)
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def _gauss_newton(residuals, theta0, max_iter=50, tol=1e-12):
    """Minimise ||r(theta)||^2 with numeric Jacobians; returns (theta, J, r)."""
    theta = np.asarray(theta0, dtype=float)
    step = 1e-6 * np.maximum(1.0, np.abs(theta))
    lam = 1e-6
    r = residuals(theta)
    cost = r @ r
    for _ in range(max_iter):
        J = _jacobian(residuals, theta, step)
        A, g = J.T @ J, J.T @ r
        while True:
            delta = np.linalg.solve(A + lam * np.diag(np.diag(A)), -g)
            r_new = residuals(theta + delta)
            cost_new = r_new @ r_new
            if cost_new <= cost or lam > 1e8:
                break
            lam *= 10
        if cost_new > cost:
            break
        theta, r, lam = theta + delta, r_new, max(lam / 10, 1e-9)
        converged = cost - cost_new <= tol * max(cost, 1e-300)
        cost = cost_new
        if converged:
            break
    J = _jacobian(residuals, theta, step)
    return theta, J, r


def _jacobian(residuals, theta, step):
    """Central-difference Jacobian, all 2p evaluations in one call of
    ``residuals.batch`` (thetas (k, p) -> residuals (k, N))."""
    E = np.diag(step)
    rr = residuals.batch(np.concatenate([theta + E, theta - E]))
    p = len(step)
    return ((rr[:p] - rr[p:]) / (2 * step)[:, None]).T


def _gram(a, xy, corr_length):
    """``a^T R a`` for rows ``a`` ordered along a curve, R_ij = exp(-d_ij^2 / (4 l^2)) (banded):
    the middle matrix of :func:`partinspect.vision.fitting.information_matrices` with unit weights."""
    return information_matrices(a, np.ones(len(a)), xy, corr_length)[1]


def _gram_dense(a, xy, corr_length):
    """``a^T R a`` with R_ij = exp(-d_ij^2 / (4 l^2)) over every pair (all ones for l None).

    Dense, so points of one edge that are near each other count whatever
    their order in the arrays (a feature merged from several segments).
    """
    if corr_length is None:
        s = a.sum(axis=0)
        return np.outer(s, s)
    from scipy.spatial.distance import cdist

    # cdist: the same squared distances without the (N, N, 2) temporary.
    R = cdist(xy, xy, "sqeuclidean")
    R *= -1.0 / (4.0 * corr_length * corr_length)
    np.exp(R, out=R)
    # R a first, by einsum's own loop: OpenBLAS splits an (N, N) x (N, p)
    # product over threads, which on cores shared with other work is slower
    # than the single-threaded loop.
    return a.T @ np.einsum("ij,jk->ik", R, a)


def _covariance(views, J):
    """Sandwich covariances of the fit: (random, systematic).

    ``J`` holds the weighted Jacobian rows of all views stacked in order
    (residuals divided by each point's ``total_sigma``). The estimate is
    ``theta = -S^-1 H_w^T e_w`` to first order, with ``S = H_w^T H_w``; the
    weighted errors e_w = e / t have the covariance ``D_s R_s D_s + D_c
    R_c D_c + D_b R_b D_b + sum_j m_j m_j^T`` (D_s = diag(sigma / t), D_c =
    diag(sigma_correction / t), D_b = diag(bias / t); R_s, R_c, R_b the
    correlations along the edge of the noise, of the correction's noise
    and of the systematic displacements; m_j the weighted pattern of mode
    j over every view that carries it), so each part is ``S^-1 (H_w^T D
    R D H_w) S^-1``, the first two the random one. The views' errors are
    independent of each other but for their shared modes.
    """
    S, M, Mb = information_parts(views, J)
    Sinv = np.linalg.inv(S)
    cov, cov_b = Sinv @ M @ Sinv, Sinv @ Mb @ Sinv
    return 0.5 * (cov + cov.T), 0.5 * (cov_b + cov_b.T)


def information_parts(views, J, random=True):
    """The normal matrix of weighted residuals and the two middles of its sandwich covariance.

    Parameters
    ----------
    views : sequence of View
        Whose points' residuals are the rows of ``J``, views stacked in order.
    J : ndarray, shape (N, p)
        Jacobian of the residuals divided by each point's ``total_sigma``,
        in any p parameters (one feature's, or several features' and a
        rig's together).
    random : bool
        False leaves the random part out (None), for callers that want
        only the systematic part.

    Returns
    -------
    S : ndarray, shape (p, p)
        ``J^T J``.
    M_random, M_systematic : ndarray, shape (p, p)
        ``J^T D R D J`` of the random errors (image noise and the
        correction's, each with its correlation along the edge) and of the
        systematic displacements (``View.bias`` and ``View.modes``, a mode's
        weighted pattern summed over the views sharing its name before its
        outer product); the estimate's covariance is ``S^-1 (M_random +
        M_systematic) S^-1`` (:func:`_covariance`).
    """
    p = J.shape[1]
    M, Mb = (np.zeros((p, p)) if random else None), np.zeros((p, p))
    shared = {}
    start = 0
    for v in views:
        n = len(v.xy)
        hw = J[start : start + n]
        t = v.total_sigma
        if random:
            M += _gram(hw * (v.sigma / t)[:, None], v.xy, v.corr_length)
        if random and v.sigma_correction is not None:
            M += _gram(hw * (v.sigma_correction / t)[:, None], v.xy, v.correction_corr_length)
        if v.bias is not None:
            Mb += _gram_dense(hw * (v.bias / t)[:, None], v.xy, v.bias_corr_length)
        if v.modes is not None:
            for name, a in zip(v.mode_names, (np.asarray(v.modes, float) / t) @ hw):
                shared[name] = shared.get(name, 0.0) + a
        start += n
    for a in shared.values():
        Mb += np.outer(a, a)
    return J.T @ J, M, Mb


def _line_residuals(views, c0, d0, e1, e2):
    total = [v.total_sigma for v in views]

    def batch(thetas):
        # Residuals for each row of thetas (k, 4) -> (k, N): the image lines
        # of all rows at once (the Jacobian evaluates 8 rows per call).
        thetas = np.asarray(thetas, float)
        p = c0 + thetas[:, :1] * e1 + thetas[:, 1:2] * e2
        d = d0 + thetas[:, 2:3] * e1 + thetas[:, 3:4] * e2
        out = []
        for v, sig in zip(views, total):
            x1 = p @ v.P[:, :3].T + v.P[:, 3]
            x2 = (p + 100.0 * d) @ v.P[:, :3].T + v.P[:, 3]
            line = _cross_rows(x1, x2)
            line /= np.hypot(line[:, 0], line[:, 1])[:, None]
            out.append((line[:, :2] @ v.xy.T + line[:, 2:]) / sig)
        return np.concatenate(out, axis=1)

    def residuals(theta):
        return batch(np.asarray(theta, float)[None])[0]

    residuals.batch = batch
    return residuals


def fit_line_3d(views, point0, direction0):
    """Fit a 3D line to the edge points of its images.

    Parameters
    ----------
    views : sequence of View
        Usually the left and right view of one matched line.
    point0, direction0 : array_like, shape (3,)
        Initial line, e.g. from triangulated correspondences (rig frame, mm).

    Returns
    -------
    Line3D
    """
    d0 = np.asarray(direction0, float) / np.linalg.norm(direction0)
    c0 = np.asarray(point0, float)
    e1, e2 = plane_basis(d0).T
    theta, J, r = _gauss_newton(_line_residuals(views, c0, d0, e1, e2), np.zeros(4))
    cov_random, cov_sys = _covariance(views, J)
    cov = cov_random + cov_sys
    a, b, al, be = theta
    d = d0 + al * e1 + be * e2
    nd = np.linalg.norm(d)
    p = c0 + a * e1 + b * e2
    # Map the parameter covariance to the point and the unit direction.
    E = np.stack([e1, e2], 1)
    Jd = (np.eye(3) - np.outer(d, d) / nd**2) / nd @ E
    d = d / nd
    # The reported point is p moved along d to the foot of c0 (fixes the gauge).
    point = p - ((p - c0) @ d) * d
    Jp = (np.eye(3) - np.outer(d, d)) @ E
    Jfull = np.zeros((6, 4))
    Jfull[:3, :2] = Jp
    Jfull[3:, 2:] = Jd
    C = Jfull @ cov @ Jfull.T
    return Line3D(point, d, C[:3, :3], C[3:, 3:], cov, float(r @ r), int(r.size - 4), cov_sys)


def circle_image_conic(center, normal, radius, P):
    """The conic (3x3, symmetric) of a 3D circle's image under camera ``P``.

    Parameters
    ----------
    center, normal : array_like, shape (3,)
    radius : float
    P : ndarray, shape (3, 4)

    Returns
    -------
    C : ndarray, shape (3, 3)
        ``x^T C x = 0`` for image points x on the ellipse, scaled so that
        ``C[2, 2]`` is 1 when that is possible.
    """
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    u, v = plane_basis(n).T
    H = P @ np.array([[*u, 0], [*v, 0], [*center, 1]]).T  # plane coords (x, y, 1) -> image
    Hinv = np.linalg.inv(H)
    C = Hinv.T @ np.diag([1.0, 1.0, -radius * radius]) @ Hinv
    return C / np.linalg.norm(C)


def _circle_residuals(views, n0, e1, e2):
    from partinspect.vision._kernels import circle_sampson

    n0, e1, e2 = (np.ascontiguousarray(x, float) for x in (n0, e1, e2))
    data = [(np.ascontiguousarray(v.P, float), np.ascontiguousarray(v.xy, float),
             np.ascontiguousarray(np.broadcast_to(v.total_sigma, (len(v.xy),)), float)) for v in views]

    def batch(thetas):
        # Sampson distances (algebraic residual over its gradient norm) for
        # each row of thetas (k, 6) -> (k, N), compiled: the Jacobian
        # evaluates a dozen rows per call.
        thetas = np.ascontiguousarray(thetas, float)
        return np.concatenate([circle_sampson(thetas, n0, e1, e2, P, xy, sig) for P, xy, sig in data], axis=1)

    def residuals(theta):
        return batch(np.asarray(theta, float)[None])[0]

    residuals.batch = batch
    return residuals


def fit_circle_3d(views, center0, normal0, radius0):
    """Fit a 3D circle to the edge points of its images.

    Parameters
    ----------
    views : sequence of View
        The left and right view of one matched circle or arc.
    center0, normal0 : array_like, shape (3,)
        Initial centre (mm) and normal, e.g. from a plane-and-circle fit to
        triangulated correspondences.
    radius0 : float
        Initial radius, mm.

    Returns
    -------
    Circle3D
        The normal is oriented towards the left camera (``n . c < 0``), since
        a circle's normal sign is not observable.
    """
    n0 = np.asarray(normal0, float) / np.linalg.norm(normal0)
    e1, e2 = plane_basis(n0).T
    theta0 = np.r_[np.asarray(center0, float), 0.0, 0.0, float(radius0)]
    theta, J, r = _gauss_newton(_circle_residuals(views, n0, e1, e2), theta0)
    cov_random, cov_sys = _covariance(views, J)
    cov = cov_random + cov_sys
    n = n0 + theta[3] * e1 + theta[4] * e2
    nn = np.linalg.norm(n)
    Jn = (np.eye(3) - np.outer(n, n) / nn**2) / nn @ np.stack([e1, e2], 1)
    n = n / nn
    if n @ theta[:3] > 0:
        n, Jn = -n, -Jn
    normal_cov = Jn @ cov[3:5, 3:5] @ Jn.T
    return Circle3D(
        theta[:3], n, float(theta[5]), cov[:3, :3], normal_cov, float(np.sqrt(cov[5, 5])), cov, float(r @ r),
        int(r.size - 6), cov_sys
    )


def circle_residuals_at(views, fit):
    """The weighted residuals of a circle fit's views at its solution, and their Jacobian.

    Parameters
    ----------
    views : sequence of View
    fit : Circle3D

    Returns
    -------
    r : ndarray, shape (N,)
        Each point's Sampson distance over its ``total_sigma``, views stacked.
    J : ndarray, shape (N, 6)
        Their derivatives by (centre, two tilts of the normal, radius).
    """
    e1, e2 = plane_basis(fit.normal).T
    res = _circle_residuals(views, fit.normal, e1, e2)
    theta = np.r_[fit.center, 0.0, 0.0, fit.radius]
    return res(theta), _jacobian(res, theta, 1e-6 * np.maximum(1.0, np.abs(theta)))


def minimal_residuals(fit, kind, views):
    """The residuals of a fit's minimal parameters about its solution, and their map to its parameters.

    The fits minimise over minimal parameters: for a line, offsets of its
    point and direction along the basis ``e1, e2`` of the plane normal to
    its direction (4); for a circle, the centre, two tilts of the normal
    along the basis of its plane and the radius (6). Taken here about the
    solution, so that ``theta0`` is the fit and a Jacobian of
    ``residuals`` at it is the fit's own, for other views of the same
    points (a perturbed calibration's).

    Parameters
    ----------
    fit : Line3D or Circle3D
    kind : str
        "line", else a circle or arc.
    views : sequence of View
        Whose points' residuals are taken (weighted by ``View.total_sigma``,
        as the fit's).

    Returns
    -------
    residuals : callable
        ``residuals(theta)``: the weighted residuals of all views' points,
        (N,), for minimal parameters ``theta``.
    theta0 : ndarray, shape (4,) or (6,)
        The solution in the minimal parameters.
    M : ndarray, shape (6, 4) or (7, 6)
        Derivative of (point, direction) or (center, normal, radius) with
        respect to ``theta`` at the solution: it carries a covariance of the
        minimal parameters (``param_cov``) to the reported ones, to first
        order.
    """
    if kind == "line":
        d0 = fit.direction
        e1, e2 = plane_basis(d0).T
        res = _line_residuals(views, fit.point, d0, e1, e2)
        theta0 = np.zeros(4)
        M = np.zeros((6, 4))
        M[:3, 0], M[:3, 1], M[3:, 2], M[3:, 3] = e1, e2, e1, e2
    else:
        n0 = fit.normal
        e1, e2 = plane_basis(n0).T
        res = _circle_residuals(views, n0, e1, e2)
        theta0 = np.r_[fit.center, 0.0, 0.0, fit.radius]
        M = np.zeros((7, 6))
        M[:3, :3] = np.eye(3)
        M[3:6, 3], M[3:6, 4] = e1, e2
        M[6, 5] = 1.0
    return res, theta0, M


def circle_consistency(views, fit, starts=None, calibration=None):
    """Whether the two views' arcs can be one circle: a likelihood-ratio test.

    Each view's points are fitted alone by an ellipse, with the same weights
    (``View.total_sigma``) as the 3D fit; a 3D circle projects to two
    ellipses bound by 4 conditions (10 ellipse parameters, 6 of the
    circle), so when the two arcs are views of one circle the 3D fit's
    chi-square exceeds the sum of the two ellipse fits' by ``c chi2(4)``,
    with ``c`` the Satterthwaite scale of the points' correlation along the
    edge (:func:`partinspect.vision.fitting._consistency`). A left arc
    matched to the right image's arc of another hole exceeds it by orders
    of magnitude.

    Parameters
    ----------
    views : sequence of View
        The left and right views of the fit.
    fit : Circle3D
    starts : sequence of ndarray, shape (5,), optional
        Starting ellipses per view (the image features' fits).
    calibration : (r0, J, D), optional
        The 3D fit's weighted residuals at its solution, their Jacobian in
        its minimal parameters and their changes along the calibration's
        principal directions of uncertainty
        (:func:`partinspect.vision.calibration_uncertainty.residual_changes`).
        The two ellipses are then asked to be one circle seen through some
        calibration its uncertainty allows, not through the stated one
        exactly: the 3D chi-square becomes ``min_z |r + A z|^2 / c + |z|^2``
        (``A`` the changes the circle cannot take up itself, ``z`` the
        directions' standard normal weights), ``(r/sqrt c)^T (I + A A^T / c)^-1 (r/sqrt c)``
        by Woodbury. Two true arcs differ by the calibration's epipolar
        error, a few hundredths of a pixel, which a precise rim's test
        would otherwise read as a mismatch.

    Returns
    -------
    delta : float
        The 3D fit's chi-square minus the two ellipse fits'.
    p_value : float
        Of ``delta / c`` under chi2(4). True pairs give p-values lower than
        uniform (the uncorrected Type B displacements bend two free ellipses
        more easily than one circle), so only gross inconsistency means a
        mismatch (:data:`partinspect.vision.stereo.MISMATCH_P`).

    References
    ----------
    .. [1] Kanatani, K. (1996). Statistical Optimization for Geometric
           Computation, ch. 7 (geometric model selection by the residual).
    """
    chi2_2d, scale = 0.0, []
    for k, v in enumerate(views):
        t = v.total_sigma
        e = fit_ellipse(v.xy, (t * t)[:, None, None] * np.eye(2), start=None if starts is None else starts[k])
        chi2_2d += float(np.sum((e.residuals / t) ** 2))
        scale.append(trace_r2(v.xy, v.corr_length) / len(v.xy))
    delta = float(fit.chi2) - chi2_2d
    c = float(np.mean(scale))
    if calibration is not None:
        r0, J, D = calibration
        A = (D - J @ (np.linalg.pinv(J) @ D)) / np.sqrt(c)
        x = r0 / np.sqrt(c)
        absorbed = float(x @ A @ np.linalg.solve(np.eye(A.shape[1]) + A.T @ A, A.T @ x))
        delta -= c * absorbed
    return delta, float(chdtrc(4, max(delta, 0.0) / c))
