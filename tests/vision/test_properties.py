"""Property-based tests (hypothesis) of the fits and the triangulation.

What must hold for any data, not just the hand-picked cases of the other
tests:

- a fit does not depend on the order of its points (any permutation for
  independent errors; reversal for errors correlated along the edge);
- a rigid motion of the data moves the fitted geometry by the same motion,
  and its covariance by the same rotation (2D: points rotated and
  translated; 3D: the whole scene, cameras included, moved, so the images
  are unchanged);
- every covariance is symmetric positive semi-definite.
"""

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from partinspect.vision.fit3d import View, fit_circle_3d, fit_line_3d
from partinspect.vision.fitting import ellipse_points, fit_ellipse, fit_line
from partinspect.vision.triangulation import triangulate, triangulation_covariance

SETTINGS = settings(max_examples=50, deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=True)
FEW = settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=True)
FEWER = settings(max_examples=10, deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=True)

seeds = st.integers(0, 2**32 - 1)
angles = st.floats(-np.pi, np.pi, allow_nan=False)
shifts = st.tuples(*[st.floats(-500.0, 500.0, allow_nan=False)] * 2)


def rot2(phi):
    c, s = np.cos(phi), np.sin(phi)
    return np.array([[c, -s], [s, c]])


def random_covariances(rng, n, scale):
    """n random 2x2 covariances (anisotropic, px^2) with standard deviations about ``scale``."""
    ang = rng.uniform(0, np.pi, n)
    s1 = scale * rng.uniform(0.5, 1.5, n)
    s2 = scale * rng.uniform(0.5, 1.5, n)
    U = np.stack([np.stack([np.cos(ang), -np.sin(ang)], 1), np.stack([np.sin(ang), np.cos(ang)], 1)], 1)
    return np.einsum("nij,nj,nkj->nik", U, np.c_[s1 * s1, s2 * s2], U)


def assert_psd(C, rtol=1e-9):
    C = np.asarray(C, float)
    assert np.all(np.isfinite(C))
    np.testing.assert_allclose(C, np.swapaxes(C, -1, -2), rtol=0, atol=1e-12 * max(1.0, np.abs(C).max()))
    w = np.linalg.eigvalsh(0.5 * (C + np.swapaxes(C, -1, -2)))
    assert np.all(w >= -rtol * np.maximum(1e-300, np.abs(w).max(axis=-1, keepdims=True))), w


# ------------------------------------------------------------------ 2D line


def line_data(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(8, 80))
    alpha = rng.uniform(-np.pi, np.pi)
    d = np.array([np.cos(alpha), np.sin(alpha)])
    nrm = np.array([-d[1], d[0]])
    p0 = rng.uniform(-300, 300, 2)
    t = np.sort(rng.uniform(-1, 1, n)) * rng.uniform(5, 300)
    cov = random_covariances(rng, n, rng.uniform(0.02, 0.5))
    e = np.einsum("nij,nj->ni", np.linalg.cholesky(cov), rng.standard_normal((n, 2)))
    return p0 + t[:, None] * d + e, cov, (p0, nrm), rng


def line_distance_cov(fit, p, q):
    """Covariance of the signed distances of the fitted line from two points p, q (invariant to rigid motions)."""
    A, B, _ = fit.params
    J = np.array([[-B * p[0] + A * p[1], 1.0], [-B * q[0] + A * q[1], 1.0]])  # d(n.x + C)/d(alpha, C)
    return J @ fit.cov_angle_offset @ J.T


@SETTINGS
@given(seeds, angles, shifts)
def test_line_fit_moves_with_the_points(seed, phi, shift):
    xy, cov, (p0, nrm), _ = line_data(seed)
    Q, t = rot2(phi), np.asarray(shift)
    f = fit_line(xy, cov)
    g = fit_line(xy @ Q.T + t, np.einsum("ij,njk,lk->nil", Q, cov, Q))
    # The same line: its normal rotated, its points moved.
    n_f, n_g = f.normal, g.normal
    assert abs(abs((Q @ n_f) @ n_g) - 1) < 1e-9
    np.testing.assert_allclose(g.centroid, Q @ f.centroid + t, atol=1e-7)
    np.testing.assert_allclose(np.abs(g.residuals), np.abs(f.residuals), atol=1e-7)
    # The same uncertainty of the line's position at two points carried along.
    p, q = p0, p0 + 50 * nrm
    Cf = line_distance_cov(f, p, q)
    Cg = line_distance_cov(g, Q @ p + t, Q @ q + t)
    np.testing.assert_allclose(Cg, Cf, rtol=1e-6, atol=1e-12 * np.abs(Cf).max())
    for fit in (f, g):
        assert_psd(fit.cov)
        assert_psd(fit.cov_angle_offset)


@SETTINGS
@given(seeds, st.booleans())
def test_line_fit_ignores_point_order(seed, correlated):
    xy, cov, _, rng = line_data(seed)
    if correlated:
        order, corr = np.arange(len(xy))[::-1], 1.0  # correlated along the edge: reversal only
    else:
        order, corr = rng.permutation(len(xy)), None
    f = fit_line(xy, cov, corr_length=corr)
    g = fit_line(xy[order], cov[order], corr_length=corr)
    np.testing.assert_allclose(g.params, f.params, atol=1e-9)
    np.testing.assert_allclose(g.cov, f.cov, rtol=1e-7, atol=1e-12 * np.abs(f.cov).max())
    np.testing.assert_allclose(g.residuals, f.residuals[order], atol=1e-8)
    assert_psd(f.cov)


# --------------------------------------------------------------- 2D ellipse


def ellipse_data(seed, whole=False):
    """Points on an ellipse (not nearly a circle), at least half of it, ordered along it."""
    rng = np.random.default_rng(seed)
    a = rng.uniform(15, 200)
    b = a * rng.uniform(0.3, 0.85)
    p = np.array([*rng.uniform(-300, 300, 2), a, b, rng.uniform(-np.pi / 2, np.pi / 2)])
    extent = 2 * np.pi if whole else rng.uniform(np.pi, 2 * np.pi)
    n = int(rng.integers(30, 120))
    phi = rng.uniform(0, 2 * np.pi) + np.linspace(0, extent, n, endpoint=not whole)
    cov = random_covariances(rng, n, rng.uniform(0.02, 0.3))
    e = np.einsum("nij,nj->ni", np.linalg.cholesky(cov), rng.standard_normal((n, 2)))
    return ellipse_points(p, phi) + e, cov, p, rng


def wrap_half(x):
    return (x + np.pi / 2) % np.pi - np.pi / 2


@SETTINGS
@given(seeds, angles, shifts)
def test_ellipse_fit_moves_with_the_points(seed, phi, shift):
    xy, cov, _, _ = ellipse_data(seed)
    Q, t = rot2(phi), np.asarray(shift)
    f = fit_ellipse(xy, cov)
    g = fit_ellipse(xy @ Q.T + t, np.einsum("ij,njk,lk->nil", Q, cov, Q))
    assert f.converged and g.converged
    scale = f.params[2]
    np.testing.assert_allclose(g.params[:2], Q @ f.params[:2] + t, atol=1e-6 * scale)
    np.testing.assert_allclose(g.params[2:4], f.params[2:4], atol=1e-6 * scale)
    assert abs(wrap_half(g.params[4] - f.params[4] - phi)) < 1e-6
    # Centre covariance rotated, axes and angle unchanged.
    J = np.eye(5)
    J[:2, :2] = Q
    expected = J @ f.cov @ J.T
    scale = np.diag(f.cov).max()
    np.testing.assert_allclose(g.cov, expected, rtol=1e-4, atol=1e-6 * scale)
    assert_psd(f.cov)
    assert_psd(g.cov)


@SETTINGS
@given(seeds, st.booleans())
def test_ellipse_fit_ignores_point_order(seed, correlated):
    xy, cov, _, rng = ellipse_data(seed)
    if correlated:
        order, corr = np.arange(len(xy))[::-1], 1.0
    else:
        order, corr = rng.permutation(len(xy)), None
    f = fit_ellipse(xy, cov, corr_length=corr)
    g = fit_ellipse(xy[order], cov[order], corr_length=corr)
    scale = f.params[2]
    np.testing.assert_allclose(g.params[:4], f.params[:4], atol=1e-6 * scale)
    assert abs(wrap_half(g.params[4] - f.params[4])) < 1e-6
    np.testing.assert_allclose(g.cov, f.cov, rtol=1e-4, atol=1e-6 * np.abs(f.cov).max())
    assert_psd(f.cov)


@SETTINGS
@given(seeds)
def test_closed_ellipse_fit_ignores_the_starting_point(seed):
    """A whole ellipse with errors correlated along it: any point may come first (the order is cyclic)."""
    xy, cov, _, rng = ellipse_data(seed, whole=True)
    k = int(rng.integers(1, len(xy)))
    f = fit_ellipse(xy, cov, corr_length=1.0)
    g = fit_ellipse(np.roll(xy, k, axis=0), np.roll(cov, k, axis=0), corr_length=1.0)
    np.testing.assert_allclose(g.params[:4], f.params[:4], atol=1e-6 * f.params[2])
    np.testing.assert_allclose(g.cov, f.cov, rtol=1e-4, atol=1e-6 * np.abs(f.cov).max())


# ------------------------------------------------------------------ 3D fits

K = np.array([[7246.0, 0, 1224], [0, 7246, 1024], [0, 0, 1]])


def rig():
    from scipy.spatial.transform import Rotation

    R = Rotation.from_rotvec([0.0, -np.radians(17), 0.0]).as_matrix()
    T = -R @ np.array([120.0, 0, 0])
    return np.eye(3), np.zeros(3), R, T


def cameras():
    _, _, R, T = rig()
    return K @ np.c_[np.eye(3), np.zeros(3)], K @ np.c_[R, T]


def proj(P, X):
    x = np.c_[X, np.ones(len(X))] @ P.T
    return x[:, :2] / x[:, 2:]


def rigid(rng, max_shift=100.0):
    """A random rotation and translation, as a 4x4 matrix."""
    from scipy.spatial.transform import Rotation

    M = np.eye(4)
    M[:3, :3] = Rotation.from_rotvec(rng.normal(size=3) * rng.uniform(0, np.pi) / np.sqrt(3)).as_matrix()
    M[:3, 3] = rng.uniform(-max_shift, max_shift, 3)
    return M


def views_of(X_per_view, rng, sigma, Ps):
    out = []
    for X, P in zip(X_per_view, Ps):
        x = proj(P, X)
        out.append(View(x + rng.normal(0, sigma, x.shape), np.full(len(x), sigma), P))
    return out


def moved(views, M):
    """The same images seen by the cameras after the scene (cameras included) moved by M."""
    Minv = np.linalg.inv(M)
    return [View(v.xy, v.sigma, v.P @ Minv, v.corr_length) for v in views]


def line_scene(seed):
    rng = np.random.default_rng(seed)
    c = np.r_[rng.uniform(-30, 30, 2), rng.uniform(370, 430)]
    d = rng.normal(size=3)
    d[2] *= 0.3
    d /= np.linalg.norm(d)
    length = rng.uniform(10, 60)
    X = [c + np.linspace(-0.5, 0.5, int(rng.integers(20, 120)))[:, None] * length * d for _ in range(2)]
    return rng, c, d, X


@FEW
@given(seeds)
def test_line_3d_moves_with_the_scene(seed):
    rng, c, d, X = line_scene(seed)
    views = views_of(X, rng, rng.uniform(0.02, 0.3), cameras())
    p0, d0 = c + rng.normal(0, 0.2, 3), d + rng.normal(0, 0.02, 3)
    f = fit_line_3d(views, p0, d0)
    M = rigid(rng)
    R, t = M[:3, :3], M[:3, 3]
    g = fit_line_3d(moved(views, M), R @ p0 + t, R @ d0)
    # Agreement to a thousandth of the standard uncertainty: the fits stop
    # at a relative cost change, not at a fixed point of the parameters.
    assert abs(abs(g.direction @ (R @ f.direction)) - 1) < max(1e-7, 1e-3 * np.trace(f.direction_cov))
    # Both points are the feet of the (moved) start point on the line.
    np.testing.assert_allclose(g.point, R @ f.point + t, atol=1e-3 * np.sqrt(np.trace(f.covariance)))
    scale = np.abs(f.covariance).max()
    np.testing.assert_allclose(g.covariance, R @ f.covariance @ R.T, rtol=1e-3, atol=1e-4 * scale)
    np.testing.assert_allclose(g.direction_cov, R @ f.direction_cov @ R.T, rtol=1e-3,
                               atol=1e-4 * np.abs(f.direction_cov).max())
    for fit in (f, g):
        assert_psd(fit.covariance, rtol=1e-7)
        assert_psd(fit.direction_cov, rtol=1e-7)
        assert_psd(fit.param_cov)


@FEW
@given(seeds)
def test_line_3d_ignores_point_and_view_order(seed):
    rng, c, d, X = line_scene(seed)
    views = views_of(X, rng, 0.1, cameras())
    f = fit_line_3d(views, c, d)
    shuffled = [View(v.xy[o], v.sigma[o], v.P) for v in views for o in [rng.permutation(len(v.xy))]]
    g = fit_line_3d(shuffled[::-1], c, d)
    np.testing.assert_allclose(g.point, f.point, atol=1e-3 * np.sqrt(np.trace(f.covariance)))
    assert abs(abs(g.direction @ f.direction) - 1) < max(1e-10, 1e-3 * np.trace(f.direction_cov))
    np.testing.assert_allclose(g.covariance, f.covariance, rtol=1e-4, atol=1e-6 * np.abs(f.covariance).max())


def circle_scene(seed):
    rng = np.random.default_rng(seed)
    c = np.r_[rng.uniform(-30, 30, 2), rng.uniform(370, 430)]
    # Normals within 60 degrees of facing the cameras: ellipses at least half as wide as long.
    n = np.r_[rng.normal(0, 0.6, 2), -1.0]
    n /= np.linalg.norm(n)
    r = rng.uniform(2, 15)
    u = np.cross(n, [1.0, 0, 0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    X = []
    for _ in range(2):
        ph = np.linspace(0, 2 * np.pi, int(rng.integers(40, 100)), endpoint=False)
        X.append(c + r * (np.cos(ph)[:, None] * u + np.sin(ph)[:, None] * v))
    return rng, c, n, r, X


@FEWER
@given(seeds)
def test_circle_3d_moves_with_the_scene(seed):
    rng, c, n, r, X = circle_scene(seed)
    views = views_of(X, rng, rng.uniform(0.02, 0.2), cameras())
    c0, n0, r0 = c + rng.normal(0, 0.1, 3), n + rng.normal(0, 0.02, 3), r * 1.01
    f = fit_circle_3d(views, c0, n0, r0)
    M = rigid(rng)
    R, t = M[:3, :3], M[:3, 3]
    g = fit_circle_3d(moved(views, M), R @ c0 + t, R @ n0, r0)
    # To a thousandth of the standard uncertainties (see the line's test).
    np.testing.assert_allclose(g.center, R @ f.center + t, atol=1e-3 * np.sqrt(np.trace(f.covariance)))
    # A circle's normal sign is a convention.
    assert abs(abs(g.normal @ (R @ f.normal)) - 1) < max(1e-8, 1e-3 * np.trace(f.normal_cov))
    assert abs(g.radius - f.radius) < 1e-3 * f.radius_std
    assert abs(g.radius_std - f.radius_std) <= 1e-3 * f.radius_std
    np.testing.assert_allclose(g.covariance, R @ f.covariance @ R.T, rtol=1e-3, atol=1e-4 * np.abs(f.covariance).max())
    np.testing.assert_allclose(g.normal_cov, R @ f.normal_cov @ R.T, rtol=1e-3,
                               atol=1e-4 * np.abs(f.normal_cov).max())
    for fit in (f, g):
        assert_psd(fit.covariance, rtol=1e-7)
        assert_psd(fit.normal_cov, rtol=1e-7)
        assert_psd(fit.param_cov)


@FEWER
@given(seeds)
def test_circle_3d_ignores_point_and_view_order(seed):
    rng, c, n, r, X = circle_scene(seed)
    views = views_of(X, rng, 0.1, cameras())
    f = fit_circle_3d(views, c, n, r)
    shuffled = [View(v.xy[o], v.sigma[o], v.P) for v in views for o in [rng.permutation(len(v.xy))]]
    g = fit_circle_3d(shuffled[::-1], c, n, r)
    np.testing.assert_allclose(g.center, f.center, atol=1e-3 * np.sqrt(np.trace(f.covariance)))
    assert abs(g.radius - f.radius) < 1e-3 * f.radius_std
    np.testing.assert_allclose(g.param_cov, f.param_cov, rtol=1e-4, atol=1e-6 * np.abs(f.param_cov).max())


# ------------------------------------------------------------ triangulation


@FEW
@given(seeds)
def test_triangulation_is_symmetric_and_its_covariance_psd(seed):
    """Swapping the cameras (and inverting their motion) gives the same points, in the right camera's frame."""
    rng = np.random.default_rng(seed)
    _, _, R, T = rig()
    K1 = K.copy()
    K2 = K.copy()
    K2[0, 0] = K2[1, 1] = K[0, 0] * rng.uniform(0.9, 1.1)
    n = int(rng.integers(1, 40))
    X = np.c_[rng.uniform(-60, 60, (n, 2)), rng.uniform(250, 700, n)]
    cov1 = random_covariances(rng, n, rng.uniform(0.01, 1.0))
    cov2 = random_covariances(rng, n, rng.uniform(0.01, 1.0))
    x1 = proj(K1 @ np.c_[np.eye(3), np.zeros(3)], X) + rng.normal(0, 0.3, (n, 2))
    x2 = proj(K2 @ np.c_[R, T], X) + rng.normal(0, 0.3, (n, 2))
    Xl = triangulate(x1, x2, K1, K2, R, T)
    Xr = triangulate(x2, x1, K2, K1, R.T, -R.T @ T)
    np.testing.assert_allclose(Xr, Xl @ R.T + T, atol=1e-6)
    C = triangulation_covariance(Xl, cov1, cov2, K1, K2, R, T)
    Cr = triangulation_covariance(Xr, cov2, cov1, K2, K1, R.T, -R.T @ T)
    for k in range(n):
        assert_psd(C[k], rtol=1e-9)
        assert np.linalg.eigvalsh(C[k]).min() > 0  # two views of a point in front of both: full rank
        np.testing.assert_allclose(Cr[k], R @ C[k] @ R.T, rtol=1e-6, atol=1e-9 * np.abs(C[k]).max())
