import numpy as np
import pytest

from partinspect.tolerances import form
from partinspect.tolerances.form import circularity, straightness


def _ring(n, radius=5.0):
    th = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.c_[radius * np.cos(th), radius * np.sin(th), np.full(n, 300.0)], th


def _radial_covs(th, sd):
    """Covariances with standard deviation ``sd`` along each point's radius (and a little elsewhere)."""
    r = np.c_[np.cos(th), np.sin(th), np.zeros_like(th)]
    return np.einsum("n,ni,nj->nij", sd**2, r, r) + np.eye(3) * 1e-8


def _draws(ring, th, sd, rng, bump=None):
    P = ring + (rng.standard_normal(len(th)) * sd)[:, None] * np.c_[np.cos(th), np.sin(th), np.zeros_like(th)]
    if bump is not None:
        P = P + bump[:, None] * np.c_[np.cos(th), np.sin(th), np.zeros_like(th)]
    return P


def test_a_few_much_less_certain_points_do_not_set_the_zone():
    # A rim whose points are 0.01 mm uncertain but for a stretch of 8 at
    # 0.1 mm (where the epipolar line runs along the edge): the zone of all
    # points is theirs. They are left out, and the value of a perfect rim
    # scatters as that of the certain points alone, its u honest.
    n = 96
    ring, th = _ring(n)
    sd = np.full(n, 0.01)
    sd[40:48] = 0.1
    covs = _radial_covs(th, sd)
    rng = np.random.default_rng(0)
    kept, all_points = [], []
    for k in range(120):
        P = _draws(ring, th, sd, rng)
        kept.append(circularity(P, covs, np.random.default_rng(k), n_draws=200))
        old, form.MAX_SD_RATIO = form.MAX_SD_RATIO, np.inf
        try:
            all_points.append(circularity(P, covs, np.random.default_rng(k), n_draws=200))
        finally:
            form.MAX_SD_RATIO = old
    assert {r.n_excluded for r in kept} == {8} and {r.n_points for r in kept} == {n - 8}
    assert {r.n_excluded for r in all_points} == {0}
    v = np.array([r.value for r in kept])
    u = np.array([r.u for r in kept])
    v_all = np.array([r.value for r in all_points])
    assert v.std() < 0.35 * v_all.std()
    z = v / u
    assert abs(z.mean()) < 0.3 and 0.8 < np.sqrt((z * z).mean()) < 1.25


def test_the_points_left_out_do_not_depend_on_the_monte_carlo_seed():
    # Points whose uncertainty lies just either side of the cut (0.93-1.07
    # times MAX_SD_RATIO times the median) are left out by their
    # covariances, exactly; read from 200 draws the choice changed from
    # one seed to the next, and the raw zone with it.
    from partinspect.vision.pointerrors import PointErrorModel

    n = 100
    ring, th = _ring(n)
    sd = np.full(n, 0.01)
    sd[40:60] = np.linspace(0.93, 1.07, 20) * form.MAX_SD_RATIO * 0.01
    radial = np.c_[np.cos(th), np.sin(th), np.zeros(n)]
    model = PointErrorModel(np.arange(n, dtype=float) * 3.0, radial, ((sd, 1.0),))
    P = ring + model.draw(np.random.default_rng(0), 1)[0]
    results = [circularity(P, model.covariances(), np.random.default_rng(k), errors=model.draw) for k in range(8)]
    assert {r.n_excluded for r in results} == {10}
    assert len({r.raw for r in results}) == 1


def test_points_alike_are_all_kept_and_a_defect_among_them_is_measured():
    n = 96
    ring, th = _ring(n)
    sd = np.full(n, 0.003) * np.linspace(0.8, 1.6, n)  # uncertainties that vary, but not by much
    covs = _radial_covs(th, sd)
    rng = np.random.default_rng(1)
    bump = 0.05 * np.exp(-0.5 * ((th - 1.0) / 0.1) ** 2)  # a 0.05 mm bump
    r = circularity(_draws(ring, th, sd, rng, bump), covs, rng)
    assert r.n_excluded == 0 and r.n_points == n
    truth = circularity(ring + bump[:, None] * np.c_[np.cos(th), np.sin(th), np.zeros(n)],
                        np.zeros((n, 3, 3)), rng, n_draws=5).raw
    assert truth - r.noise_bias - 3 * r.u < r.value < truth + 3 * r.u


def test_straightness_leaves_out_an_uncertain_end():
    n = 80
    s = np.linspace(0, 40, n)
    P0 = np.c_[s, np.zeros(n), np.full(n, 300.0)]
    sd = np.full(n, 0.004)
    sd[-5:] = 0.05
    covs = np.einsum("n,i,j->nij", sd**2, [0.0, 1.0, 0.0], [0.0, 1.0, 0.0]) + np.eye(3) * 1e-10
    rng = np.random.default_rng(2)
    P = P0 + np.c_[np.zeros(n), rng.standard_normal(n) * sd, np.zeros(n)]
    r = straightness(P, covs, rng)
    assert r.n_excluded == 5
    assert r.raw == pytest.approx(straightness(P[:-5], covs[:-5], rng, n_draws=5).raw)


def test_spread_over_images_of_one_scene_with_the_type_b_part_held():
    # A rim whose points carry noise (independent from image to image) and
    # a Type B displacement (fixed for a scene, unknown): the spread of the
    # value over images of one scene is wider than the noise alone gives (the
    # fixed pattern decides which points set the zone) and narrower than the
    # whole uncertainty; held draws predict it.
    from partinspect.vision.pointerrors import PointErrorModel

    n = 90
    ring, th = _ring(n)
    radial = np.c_[np.cos(th), np.sin(th), np.zeros(n)]
    s = th * 5.0 / 0.05  # arc length in "px" of 0.05 mm
    noise, bias = np.full(n, 0.01), np.full(n, 0.02)
    model = PointErrorModel(s, radial, ((noise, 1.0), (bias, 8.0)), systematic=(1,))
    noise_only = PointErrorModel(s, radial, ((noise, 1.0),))
    covs = _radial_covs(th, np.hypot(noise, bias))
    rng = np.random.default_rng(5)
    spreads = []
    for scene in range(10):
        pattern = ring + PointErrorModel(s, radial, ((bias, 8.0),)).draw(rng, 1)[0]
        values = [circularity(pattern + noise_only.draw(rng, 1)[0], covs, np.random.default_rng(k),
                              n_draws=100, errors=model.draw).value for k in range(25)]
        spreads.append(np.var(values, ddof=1))
    seen = np.sqrt(np.mean(spreads))
    P = ring + model.draw(rng, 1)[0]
    held = circularity(P, covs, np.random.default_rng(0), errors=model.draw, held=model.draw_held).u
    whole = circularity(P, covs, np.random.default_rng(0), errors=model.draw).u
    alone = circularity(P, covs, np.random.default_rng(0), errors=noise_only.draw).u
    assert alone < 0.85 * held < 0.85 * whole
    assert held == pytest.approx(seen, rel=0.2)


def test_scene_spreads_hold_the_spread_of_scenes_with_strong_ends():
    # A 270 deg rim whose Type B displacements grow towards its ends (a hole
    # seen obliquely): which points set the zone depends on the scene's
    # pattern, so the spread over 50 images of one scene varies from scene
    # to scene by more than the chance of 50 draws. The chi-square interval
    # of a sample deviation misses a quarter of the scenes; the quantiles of
    # scene_spreads hold 95 %.
    from partinspect.planning.check import chance_interval, form_interval
    from partinspect.vision.pointerrors import PointErrorModel

    n, images = 60, 50
    th = np.linspace(0, 1.5 * np.pi, n)
    ring = np.c_[5 * np.cos(th), 5 * np.sin(th), np.full(n, 300.0)]
    radial = np.c_[np.cos(th), np.sin(th), np.zeros(n)]
    noise = np.full(n, 0.005)
    bias = 0.005 + 0.03 * (np.abs(th - th.mean()) / th.mean()) ** 4
    model = PointErrorModel(th * 100.0, radial, ((noise, 1.0), (bias, 8.0)), systematic=(1,))
    covs = _radial_covs(th, np.hypot(noise, bias))
    rng = np.random.default_rng(5)
    P = ring + model.draw(rng, 1)[0]
    sp = form.scene_spreads("circularity", P, covs, model.draw_held, images, n_scenes=200,
                            rng=np.random.default_rng(1))
    held = circularity(P, covs, np.random.default_rng(0), errors=model.draw, held=model.draw_held)
    # Their RMS is the held u (both Monte Carlo: some 3 % apart).
    assert np.sqrt(np.mean(sp**2)) == pytest.approx(held.u, rel=0.08)
    lo, hi = form_interval(sp, held.u)
    c_lo, c_hi = chance_interval(images)
    assert lo < c_lo - 0.03 and hi > c_hi + 0.08
    keep, _ = form._kept(covs, ring, (np.array([0, 0, 300.0]), np.eye(3)[:, :2]))
    assert keep.sum() == held.n_points < n
    seen = np.array([form._circle_zones((ring + model.draw_held(rng, 1, images)[0])[:, keep]).std(ddof=1)
                     for _ in range(200)]) / held.u
    assert np.mean((seen >= lo) & (seen <= hi)) >= 0.9
    assert np.mean((seen >= c_lo) & (seen <= c_hi)) <= 0.85


def test_scene_spreads_rejects_what_it_cannot_spread():
    ring, th = _ring(20)
    covs = _radial_covs(th, np.full(20, 0.01))
    with pytest.raises(ValueError, match="form value"):
        form.scene_spreads("diameter", ring, covs, None, 10)
    with pytest.raises(ValueError, match="2 images"):
        form.scene_spreads("circularity", ring, covs, None, 1)


def _cut_zones(ideal, sd, directions, t, rng, n_sets, zone):
    """Zones of point sets whose errors beyond ``t`` standard deviations were rejected, as the image fits reject them."""
    out = []
    for _ in range(n_sets):
        e = rng.standard_normal(len(ideal))
        ok = np.abs(e) <= t
        out.append(zone(ideal[ok] + (e[ok] * sd[ok])[:, None] * directions[ok]))
    return np.array(out)


def test_the_zones_spread_is_that_of_points_that_passed_the_outlier_test():
    # The fits reject points beyond Chauvenet's threshold (3.9 for 500
    # points), so a measured zone never sees the Gaussian tails beyond it; a
    # zone is a maximum, set by those tails. With the cut simulated, u is
    # the spread of such zones; with the tails kept it was some 20 % larger.
    from partinspect.vision.imagefeatures import chauvenet_z

    n = 500
    line = np.c_[np.linspace(0, 50, n), np.zeros(n), np.full(n, 300.0)]
    sd = np.full(n, 0.01)
    covs = np.zeros((n, 3, 3))
    covs[:, 1, 1] = sd**2
    t = chauvenet_z(n)
    rng = np.random.default_rng(3)
    seen = _cut_zones(line, sd, np.tile([0.0, 1.0, 0.0], (n, 1)), t, rng, 3000, form._line_zone).std(ddof=1)
    P = line + np.c_[np.zeros(n), rng.normal(0, 0.01, n), np.zeros(n)]
    cut = straightness(P, covs, np.random.default_rng(0), n_draws=2000, outlier_z=t)
    full = straightness(P, covs, np.random.default_rng(0), n_draws=2000)
    assert cut.u == pytest.approx(seen, rel=0.06)
    assert full.u > 1.12 * seen
    # The noise-only mean moves far less than the spread: the tails beyond t are rare.
    assert cut.noise_bias == pytest.approx(full.noise_bias, rel=0.02)


def test_a_rims_zone_is_cut_the_same_way():
    from partinspect.vision.imagefeatures import chauvenet_z

    n = 150
    ring, th = _ring(n)
    sd = np.full(n, 0.01)
    covs = _radial_covs(th, sd)
    t = chauvenet_z(n)
    radial = np.c_[np.cos(th), np.sin(th), np.zeros(n)]
    rng = np.random.default_rng(4)
    seen = _cut_zones(ring, sd, radial, t, rng, 3000, form._circle_zone).std(ddof=1)
    P = _draws(ring, th, sd, rng)
    cut = circularity(P, covs, np.random.default_rng(0), n_draws=2000, outlier_z=t)
    full = circularity(P, covs, np.random.default_rng(0), n_draws=2000)
    assert cut.u == pytest.approx(seen, rel=0.06)
    assert full.u > 1.08 * seen


def test_a_zone_that_cannot_be_simulated_says_why_instead_of_crashing():
    """Draws whose outlier test leaves too few points have no zone (the measurement's
    fits would refuse them): the form value raises FormSimulationError, not a
    LinAlgError from a singular fit or a NaN zone."""
    t = np.linspace(0.0, 0.5, 12)
    P = np.c_[5 * np.cos(t), 5 * np.sin(t), np.zeros_like(t)]
    covs = np.repeat((1e-6 * np.eye(3))[None], len(P), axis=0)

    def wild(rng, n_draws):  # errors a hundred times what the covariances say, in every other draw
        e = rng.standard_normal((n_draws, len(P), 3)) * 1e-3
        e[::2] *= 100.0
        return e

    with pytest.raises(form.FormSimulationError, match="left fewer than"):
        circularity(P, covs, np.random.default_rng(0), errors=wild, outlier_z=3.0)
    with pytest.raises(form.FormSimulationError, match="left fewer than"):
        straightness(np.c_[t, np.zeros_like(t), np.zeros_like(t)], covs, np.random.default_rng(0), errors=wild,
                     outlier_z=3.0)
