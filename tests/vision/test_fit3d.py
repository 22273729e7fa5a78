"""3D lines and circles fitted to both views: accuracy and honest covariances."""

from dataclasses import replace

import cv2
import numpy as np
import pytest
from scipy.stats import chi2

from partinspect.vision.fit3d import View, circle_image_conic, fit_circle_3d, fit_line_3d

K = np.array([[7246.0, 0, 1224], [0, 7246, 1024], [0, 0, 1]])
R = cv2.Rodrigues(np.array([0.0, -np.radians(17), 0.0]))[0]
T = -R @ np.array([120.0, 0, 0])
PS = (K @ np.c_[np.eye(3), np.zeros(3)], K @ np.c_[R, T])
SIGMA = 0.05  # px, across the edge


def proj(P, X):
    x = np.c_[X, np.ones(len(X))] @ P.T
    return x[:, :2] / x[:, 2:]


def normals(x):
    """Unit normals of points x ordered along a curve."""
    t = np.gradient(x, axis=0)
    return np.c_[-t[:, 1], t[:, 0]] / np.linalg.norm(t, axis=1)[:, None]


def correlated(x, sigma, corr_length, rng):
    """Normal errors of standard deviation sigma correlated along the curve as exp(-d^2 / (4 l^2))."""
    d = np.linalg.norm(x[:, None] - x[None], axis=2)
    L = np.linalg.cholesky(np.exp(-d * d / (4 * corr_length**2)) + 1e-9 * np.eye(len(x)))
    return sigma * (L @ rng.standard_normal(len(x)))


def noisy_view(P, X, rng, corr_length=None):
    """Image points of X with normal noise, optionally correlated along the edge."""
    x = proj(P, X)
    e = correlated(x, SIGMA, corr_length, rng) if corr_length else rng.normal(0, SIGMA, len(x))
    return View(x + normals(x) * e[:, None], np.full(len(x), SIGMA), P, corr_length)


CIRCLE = dict(center=np.array([5.0, -3, 400]), normal=np.array([0.3, -0.6, -0.7]) / np.linalg.norm([0.3, -0.6, -0.7]), radius=6.0)


def circle_points(n):
    c, nrm, r = CIRCLE["center"], CIRCLE["normal"], CIRCLE["radius"]
    u = np.cross(nrm, [1, 0, 0])
    u /= np.linalg.norm(u)
    v = np.cross(nrm, u)
    ph = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return c + r * (np.cos(ph)[:, None] * u + np.sin(ph)[:, None] * v)


def test_circle_conic_contains_projected_points():
    X = circle_points(50)
    for P in PS:
        C = circle_image_conic(CIRCLE["center"], CIRCLE["normal"], CIRCLE["radius"], P)
        x = np.c_[proj(P, X), np.ones(50)]
        Cx = x @ C
        assert np.abs(np.einsum("ni,ni->n", Cx, x) / (2 * np.hypot(Cx[:, 0], Cx[:, 1]))).max() < 1e-9


def test_noiseless_circle_recovered_from_rough_start():
    X = circle_points(400)
    views = [View(proj(P, X), np.full(400, SIGMA), P) for P in PS]
    f = fit_circle_3d(views, CIRCLE["center"] + [0.5, -0.4, 2.0], CIRCLE["normal"] + [0.1, 0.05, 0], 5.5)
    assert np.abs(f.center - CIRCLE["center"]).max() < 1e-7
    assert abs(f.radius - CIRCLE["radius"]) < 1e-8
    assert abs(abs(f.normal @ CIRCLE["normal"]) - 1) < 1e-12
    assert f.normal @ f.center < 0  # oriented towards the camera


@pytest.mark.parametrize("corr", [None, 1.0])
def test_circle_covariance_is_honest(corr):
    rng = np.random.default_rng(7 if corr else 8)
    X = circle_points(680)  # ~1 px apart, as edge points are
    m, z = [], []
    for _ in range(80 if corr else 120):
        f = fit_circle_3d([noisy_view(P, X, rng, corr) for P in PS], CIRCLE["center"], CIRCLE["normal"], 6.0)
        e = f.center - CIRCLE["center"]
        m.append(e @ np.linalg.solve(f.covariance, e))
        z.append((f.radius - CIRCLE["radius"]) / f.radius_std)
    m, z = np.array(m), np.array(z)
    assert 0.88 <= np.mean(m < chi2.ppf(0.95, 3)) <= 0.99
    assert 0.8 <= np.sqrt(m.mean() / 3) <= 1.25
    assert 0.8 <= np.sqrt((z * z).mean()) <= 1.25


def test_a_corrections_noise_is_propagated_over_its_own_correlation_length():
    """Points displaced by image noise (correlated over 1 px) and by the
    noise of a correction averaged along the edge (correlated over 2.2 px,
    1.5 times as large): the covariance is honest when the correction is
    a component of its own, and too small when its variance is taken as
    image noise (what the chain did)."""
    rng = np.random.default_rng(21)
    X = circle_points(680)
    sc, lc = 1.5 * SIGMA, 2.2
    m_own, m_lumped = [], []
    for _ in range(60):
        views = []
        for P in PS:
            v = noisy_view(P, X, rng, 1.0)
            e = correlated(v.xy, sc, lc, rng)
            views.append(View(v.xy + normals(v.xy) * e[:, None], v.sigma, P, 1.0,
                              sigma_correction=np.full(len(e), sc), correction_corr_length=lc))
        for out, vs in ((m_own, views),
                        (m_lumped, [View(v.xy, np.hypot(v.sigma, sc), v.P, 1.0) for v in views])):
            f = fit_circle_3d(vs, CIRCLE["center"], CIRCLE["normal"], 6.0)
            e = f.center - CIRCLE["center"]
            out.append(np.r_[e @ np.linalg.solve(f.covariance, e), ((f.radius - CIRCLE["radius"]) / f.radius_std) ** 2])
    own, lumped = np.sqrt(np.mean(m_own, axis=0) / [3, 1]), np.sqrt(np.mean(m_lumped, axis=0) / [3, 1])
    assert np.all((0.8 <= own) & (own <= 1.2)), own
    assert np.all(lumped > 1.2), lumped


def test_ignoring_correlation_would_understate_uncertainty():
    """The same correlated data fitted as if independent: covariances come out too small."""
    rng = np.random.default_rng(9)
    X = circle_points(680)
    m = []
    for _ in range(40):
        views = [noisy_view(P, X, rng, 1.0) for P in PS]
        views = [View(v.xy, v.sigma, v.P, None) for v in views]
        f = fit_circle_3d(views, CIRCLE["center"], CIRCLE["normal"], 6.0)
        e = f.center - CIRCLE["center"]
        m.append(e @ np.linalg.solve(f.covariance, e))
    assert np.sqrt(np.mean(m) / 3) > 1.4


def test_line_covariance_is_honest_and_depth_is_worst():
    rng = np.random.default_rng(11)
    p, d = np.array([-10.0, 5, 395]), np.array([0.8, 0.5, 0.3]) / np.linalg.norm([0.8, 0.5, 0.3])
    X = p + np.linspace(-20, 20, 800)[:, None] * d
    m = []
    for _ in range(120):
        f = fit_line_3d([noisy_view(P, X, rng) for P in PS], p + [0.2, -0.1, 0.5], d + [0.01, 0, -0.02])
        e = f.point - p
        e = e - (e @ f.direction) * f.direction
        m.append(e @ np.linalg.pinv(f.covariance, rcond=1e-9) @ e)
    m = np.array(m)
    assert 0.88 <= np.mean(m < chi2.ppf(0.95, 2)) <= 0.99
    assert 0.8 <= np.sqrt(m.mean() / 2) <= 1.25
    assert abs(f.covariance @ f.direction).max() < 1e-12  # the gauge: no uncertainty along the line
    sd = np.sqrt(np.diag(f.covariance))
    assert sd[2] > 2 * max(sd[0], sd[1])


@pytest.mark.parametrize("corr", [None, 40.0])
def test_systematic_part_is_the_response_to_the_stated_displacement(corr):
    """A Type B displacement b_i of the left view's points: the propagated covariance is
    that of xi * (the response to b)."""
    X = circle_points(680)
    ph = np.linspace(0, 2 * np.pi, 680, endpoint=False)
    b = 0.04 * (1.2 + np.cos(ph))  # px, larger on one side of the rim
    x = proj(PS[0], X)
    t = np.gradient(x, axis=0)
    nrm = np.c_[-t[:, 1], t[:, 0]] / np.linalg.norm(t, axis=1)[:, None]
    clean = [View(proj(P, X), np.full(680, SIGMA), P, 1.0) for P in PS]
    clean[0] = View(clean[0].xy, clean[0].sigma, PS[0], 1.0, b, corr)
    f0 = fit_circle_3d(clean, CIRCLE["center"], CIRCLE["normal"], 6.0)
    assert np.abs(f0.center - CIRCLE["center"]).max() < 1e-7  # noiseless, unbiased
    S = f0.param_cov_systematic
    assert np.all(np.linalg.eigvalsh(S) > -1e-15)
    assert np.allclose(S, S.T)
    if corr is None:
        # Fully correlated: one common xi, so S is the outer product of the response to b.
        moved = [View(clean[0].xy + b[:, None] * nrm, clean[0].sigma, PS[0], 1.0, b, None), clean[1]]
        f1 = fit_circle_3d(moved, CIRCLE["center"], CIRCLE["normal"], 6.0)
        d = np.r_[f1.center - f0.center, f1.radius - f0.radius]
        s = np.sqrt(np.diag(S)[[0, 1, 2, 5]])
        assert np.allclose(np.abs(d), s, rtol=0.02, atol=1e-9), (d, s)
    else:
        # Correlated over a part of the rim only: less than the common displacement.
        full = fit_circle_3d([View(clean[0].xy, clean[0].sigma, PS[0], 1.0, b, None), clean[1]],
                             CIRCLE["center"], CIRCLE["normal"], 6.0).param_cov_systematic
        assert S[5, 5] < full[5, 5]


def _outward(x):
    """Unit normals of image points x of a closed curve, pointing away from its centroid."""
    n = normals(x)
    return n * np.sign(np.einsum("ni,ni->n", n, x - x.mean(axis=0)))[:, None]


def test_a_shared_mode_moves_both_views_at_once():
    """A displacement pattern named alike in both views (one coefficient, e.g. a broken rim's band place):
    its propagated covariance is the outer product of the fit's response to moving both views by it
    (named apart, each view would move alone: another covariance). Common round the rim, it moves the
    radius, the centre hardly."""
    X = circle_points(400)
    xs = [proj(P, X) for P in PS]
    c = 0.1  # px, outward all round, in both images
    views = [View(x, np.full(400, SIGMA), P, 1.0, modes=np.full((1, 400), c), mode_names=("place",))
             for x, P in zip(xs, PS)]
    f0 = fit_circle_3d(views, CIRCLE["center"], CIRCLE["normal"], 6.0)
    moved = [View(x + c * _outward(x), v.sigma, v.P, 1.0, modes=v.modes, mode_names=v.mode_names)
             for x, v in zip(xs, views)]
    f1 = fit_circle_3d(moved, CIRCLE["center"], CIRCLE["normal"], 6.0)
    d = np.r_[f1.center - f0.center, f1.radius - f0.radius]
    S = f0.param_cov_systematic
    s = np.sqrt(np.diag(S)[[0, 1, 2, 5]])
    assert np.allclose(np.abs(d), s, rtol=0.03, atol=1e-9), (d, s)
    apart = [View(v.xy, v.sigma, v.P, 1.0, modes=v.modes, mode_names=(f"place {i}",)) for i, v in enumerate(views)]
    S_apart = fit_circle_3d(apart, CIRCLE["center"], CIRCLE["normal"], 6.0).param_cov_systematic
    assert S_apart[5, 5] < 0.8 * S[5, 5]
    assert np.sqrt(np.trace(S[:3, :3])) < 0.1 * np.sqrt(S[5, 5])


def _half_arc(n):
    """Image points of the front half of CIRCLE in both cameras and their ellipse fits."""
    from partinspect.vision.fitting import fit_ellipse

    X = circle_points(2 * n)[:n]
    xs = [proj(P, X) for P in PS]
    return xs, [fit_ellipse(x) for x in xs]


def test_a_band_place_moves_a_rims_image_as_a_whole_and_its_size_and_bends_it():
    """band_harmonics: its mean row moves every point outward alike; its first harmonic's two rows are what a
    shift of the whole image along x and along y moves each point along its outward normal; the second and
    third harmonics' rows follow the normal's angle t as cos(k t), sin(k t). Their sizes: a place uniform on a
    band of width w (RMS distance b = w / sqrt(3) from the sharp edge), its mean's u w / sqrt(12); each
    harmonic's amplitude uniform on [0, w / 2] at any angle, so the place's variance about its mean is w^2 / 8
    at every point, between a place uniform on the band at each point (w^2 / 12) and the most (w^2 / 4)."""
    from partinspect.vision.band_modes import BAND_HARMONICS, band_harmonics

    (x, _), (fit, _) = _half_arc(120)
    b = 0.7
    rows = band_harmonics(x, fit, b)
    assert rows.shape == (1 + 2 * BAND_HARMONICS, len(x)) and BAND_HARMONICS == 3
    n = _outward_of(x, fit)
    w = b * np.sqrt(3.0)
    assert np.allclose(rows[0], w / np.sqrt(12.0))
    rng = np.random.default_rng(5)
    a, phase = rng.uniform(0.0, w / 2, 200_000), rng.uniform(0.0, 2 * np.pi, 200_000)
    h = np.sqrt(np.mean((a * np.cos(phase)) ** 2))  # one component's u, by simulation
    assert np.allclose(rows[1], h * n[:, 0], rtol=0.01) and np.allclose(rows[2], h * n[:, 1], rtol=0.01)
    shift = np.array([0.3, -0.2])
    assert np.allclose(0.3 * rows[1] - 0.2 * rows[2], h * (n @ shift), rtol=0.01)
    t = np.arctan2(n[:, 1], n[:, 0])
    assert np.allclose(rows[3:], h * np.array([np.cos(2 * t), np.sin(2 * t), np.cos(3 * t), np.sin(3 * t)]),
                       rtol=0.01, atol=1e-12)
    assert np.allclose(np.sum(rows[1:] ** 2, axis=0), w ** 2 / 8, rtol=0.02)
    # Outward: away from the ellipse's centre.
    assert np.all(np.einsum("ni,ni->n", n, x - fit.params[:2]) > 0)


def test_a_broken_rims_band_on_a_half_arc_states_its_radius_between_its_mean_and_a_per_point_field():
    """A half arc's band place as modes per image (both cameras alike): the radius's systematic u is more than
    moving every point outward by the mean's u moves it, since a half arc's radius takes up the place's second
    and third waves too; a per-point field of the band's size correlated over 0.2 rad lets the half arc trade
    radius against centre over every short wave as well, and states it at least twice as large."""
    from partinspect.vision.band_modes import band_harmonics

    xs, fits = _half_arc(150)
    b = 0.8  # px
    rows = [band_harmonics(x, fit, b) for x, fit in zip(xs, fits)]
    names = tuple(("band", 0, j) for j in range(len(rows[0])))
    views = [View(x, np.full(len(x), SIGMA), P, 1.0, modes=r, mode_names=names) for x, r, P in zip(xs, rows, PS)]
    u_r = np.sqrt(fit_circle_3d(views, CIRCLE["center"], CIRCLE["normal"], 6.0).param_cov_systematic[5, 5])
    f0 = fit_circle_3d([View(x, v.sigma, v.P, 1.0) for x, v in zip(xs, views)], CIRCLE["center"],
                       CIRCLE["normal"], 6.0)
    mean = rows[0][0, 0]  # the mean's u, px
    moved = [View(x + mean * _outward_of(x, fit), v.sigma, v.P, 1.0) for x, fit, v in zip(xs, fits, views)]
    f1 = fit_circle_3d(moved, CIRCLE["center"], CIRCLE["normal"], 6.0)
    assert u_r > 2.0 * abs(f1.radius - f0.radius)
    # Mean and first harmonic alone: the mean's move.
    first = [View(x, v.sigma, v.P, 1.0, modes=r[:3], mode_names=names[:3]) for x, r, v in zip(xs, rows, views)]
    u_first = np.sqrt(fit_circle_3d(first, CIRCLE["center"], CIRCLE["normal"], 6.0).param_cov_systematic[5, 5])
    assert u_first == pytest.approx(abs(f1.radius - f0.radius), rel=0.25)
    field = [View(x, np.full(len(x), SIGMA), P, 1.0, np.full(len(x), b), 0.2 * float(max(fit.params[2:4])))
             for x, fit, P in zip(xs, fits, PS)]
    u_field = np.sqrt(fit_circle_3d(field, CIRCLE["center"], CIRCLE["normal"], 6.0).param_cov_systematic[5, 5])
    assert u_field > 2.0 * u_r


def _outward_of(x, fit):
    from partinspect.vision.fitting import ellipse_geometry

    return ellipse_geometry(x, fit.params, fit.phases)[1]


def test_a_broken_rims_band_radius_u_is_the_spread_of_radii_under_drawn_band_places():
    """The half arc's radius u from the band's modes (the fit's first-order propagation) against the spread of
    its fitted radius over 200 band places drawn at the modes' stated sizes (each coefficient uniform, unit
    variance, shared by both images) and moved into the points."""
    from partinspect.vision.band_modes import band_harmonics

    xs, fits = _half_arc(150)
    rows = [band_harmonics(x, fit, 0.8) for x, fit in zip(xs, fits)]
    names = tuple(("band", 0, j) for j in range(len(rows[0])))
    views = [View(x, np.full(len(x), SIGMA), P, 1.0, modes=r, mode_names=names) for x, r, P in zip(xs, rows, PS)]
    u_r = np.sqrt(fit_circle_3d(views, CIRCLE["center"], CIRCLE["normal"], 6.0).param_cov_systematic[5, 5])
    outward = [_outward_of(x, fit) for x, fit in zip(xs, fits)]
    rng = np.random.default_rng(3)
    radii = []
    for _ in range(200):
        z = rng.uniform(-np.sqrt(3.0), np.sqrt(3.0), len(names))
        moved = [replace(v, xy=v.xy + (z @ r)[:, None] * o) for v, r, o in zip(views, rows, outward)]
        radii.append(fit_circle_3d(moved, CIRCLE["center"], CIRCLE["normal"], 6.0).radius)
    assert 0.85 < np.std(radii) / u_r < 1.15


def test_a_view_refuses_modes_without_their_names():
    """The fit sums the views' modes by name: a mode without one would be dropped, understating its Type B."""
    xy = np.zeros((4, 2))
    with pytest.raises(ValueError, match="2 modes but 1 mode names"):
        View(xy, np.ones(4), PS[0], modes=np.ones((2, 4)), mode_names=("a",))
    with pytest.raises(ValueError):
        View(xy, np.ones(4), PS[0], modes=np.ones((1, 4)))
    assert View(xy, np.ones(4), PS[0], modes=np.ones((1, 4)), mode_names=("a",)).modes.shape == (1, 4)
