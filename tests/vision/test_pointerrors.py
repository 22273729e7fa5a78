import numpy as np
import pytest

from partinspect.tolerances.form import straightness
from partinspect.vision.pointerrors import PointErrorModel, correlated_field, short_scale_ratio


@pytest.mark.parametrize("length", [1.0, 4.0])
def test_field_has_unit_variance_and_the_stated_correlation(length):
    rng = np.random.default_rng(0)
    s = np.cumsum(np.r_[0.0, rng.uniform(0.9, 1.5, 299)])  # uneven spacing, as on a slanted edge
    f = correlated_field(s, length, rng, 6000)
    assert f.var(axis=0).mean() == pytest.approx(1.0, abs=0.04)
    for k in (1, 3, 6):
        want = np.exp(-(s[150 + k] - s[150]) ** 2 / (4 * length * length))
        assert np.corrcoef(f[:, 150], f[:, 150 + k])[0, 1] == pytest.approx(want, abs=0.05)


def test_draws_reproduce_the_points_covariances():
    rng = np.random.default_rng(1)
    n = 40
    J = rng.normal(size=(n, 3)) * 0.05  # mm per px across the edge
    std = rng.uniform(0.01, 0.03, n)
    Jp = rng.normal(size=(n, 3, 2)) * 0.1
    Cp = np.array([[0.04, 0.01], [0.01, 0.02]])
    bias = np.full(n, 0.02)
    m = PointErrorModel(np.arange(n, dtype=float), J, ((std, 1.0), (bias, 10.0)), Jp, Cp)
    e = m.draw(rng, 20000)
    for i in (0, 17, 39):
        want = (std[i] ** 2 + bias[i] ** 2) * np.outer(J[i], J[i]) + Jp[i] @ Cp @ Jp[i].T
        assert np.cov(e[:, i].T) == pytest.approx(want, rel=0.08, abs=1e-9)
        assert m.covariances()[i] == pytest.approx(want, rel=1e-12, abs=1e-18)
    # The long-correlated part moves neighbours together: their difference
    # keeps (nearly) only the short-correlated part.
    u = np.tile([0.0, 0.0, 1.0], (n, 1))
    d = np.diff(PointErrorModel(np.arange(n, dtype=float), u, ((std, 1.0), (bias, 10.0))).draw(rng, 20000)[:, 20:22, 2])
    short = std[20] ** 2 + std[21] ** 2 - 2 * np.exp(-0.25) * std[20] * std[21]
    long_ = 2 * bias[20] ** 2 * (1 - np.exp(-1 / 400))
    assert d.var() == pytest.approx(short + long_, rel=0.08)


def _line(n, rng):
    t = np.linspace(0.0, 20.0, n)
    return np.c_[t, np.zeros(n), np.zeros(n)]


def test_form_correction_follows_the_errors_correlation():
    # Errors correlated over 6 points: the zone of a straight edge is much
    # narrower than that of independent errors with the same marginals, and
    # only a correction drawn with that correlation stays unbiased.
    rng = np.random.default_rng(2)
    n, sd, length = 300, 0.004, 6.0
    P0 = _line(n, rng)
    J = np.tile([0.0, 1.0, 0.0], (n, 1))
    model = PointErrorModel(np.arange(n, dtype=float), J, ((np.full(n, sd), length),))
    covs = np.tile(np.diag([0.0, sd * sd, 0.0]), (n, 1, 1))
    with_model, independent = [], []
    for k in range(30):
        P = P0 + model.draw(rng, 1)[0]
        with_model.append(straightness(P, covs, np.random.default_rng(k), n_draws=100, errors=model.draw))
        independent.append(straightness(P, covs, np.random.default_rng(k), n_draws=100))
    z = np.array([r.value / r.u for r in with_model])
    assert abs(z.mean()) < 0.6 and 0.5 < z.std() < 1.6
    # Independent draws over-correct: the true (zero) form comes out well below zero.
    zi = np.array([r.value / r.u for r in independent])
    assert zi.mean() < -2.0


def test_form_rejects_errors_of_the_wrong_shape():
    P = _line(10, None)
    with pytest.raises(ValueError, match="shape"):
        straightness(P, np.zeros((10, 3, 3)), errors=lambda rng, n: np.zeros((n, 9, 3)))


def test_short_scale_ratio_sees_point_scatter_not_form():
    rng = np.random.default_rng(3)
    n = 3000  # the ratio of 600 points scatters by 10 %, of 3000 by 5 %
    xy = np.c_[np.arange(n) * 1.2, np.zeros(n)]
    s = xy[:, 0]
    sigma = np.full(n, 0.01)
    bend = 0.2 * np.sin(s / s.max() * np.pi)  # a smooth form deviation of 0.2 px (20 sigma)
    ratios = []
    for scale in (1.0, 2.0):
        r = bend + scale * sigma * correlated_field(s, 1.0, rng, 1)[0]
        ratios.append(short_scale_ratio(r, sigma, xy, 1.0)[0])
    assert ratios[0] == pytest.approx(1.0, abs=0.15)
    assert ratios[1] == pytest.approx(4.0, rel=0.15)
    # A few local defects (a burr) do not move the median.
    r = sigma * correlated_field(s, 1.0, rng, 1)[0]
    r[300:303] += 0.5
    ratio, se = short_scale_ratio(r, sigma, xy, 1.0)
    assert ratio == pytest.approx(1.0, abs=0.15)
    assert se == pytest.approx(2.55 / np.sqrt(n - 1))


def test_short_scale_ratio_is_not_fooled_by_less_correlated_noise():
    # White noise where the model expects neighbours to share smoothed
    # noise: successive differences scatter more than predicted, the
    # residuals themselves do not, and the noise level is right.
    rng = np.random.default_rng(4)
    n = 3000
    xy = np.c_[np.arange(n) * 1.0, np.zeros(n)]
    sigma = np.full(n, 0.01)
    ratio, _ = short_scale_ratio(sigma * rng.standard_normal(n), sigma, xy, 1.0)
    assert ratio == pytest.approx(1.0, abs=0.15)


def test_short_scale_ratio_standard_error_is_its_spread_over_noise_draws():
    rng = np.random.default_rng(5)
    n = 600
    xy = np.c_[np.arange(n) * 1.2, np.zeros(n)]
    sigma = np.full(n, 0.01)
    draws = [short_scale_ratio(sigma * f, sigma, xy, 1.0) for f in correlated_field(xy[:, 0], 1.0, rng, 300)]
    ratios, se = np.array([d[0] for d in draws]), draws[0][1]
    assert ratios.std() == pytest.approx(se, rel=0.25)
    # The smaller of two estimates reads a little low (0.95 here): it scales the
    # noise up only when clearly above 1, never on a chance excess.
    assert 0.9 < ratios.mean() < 1.0


def test_held_draws_keep_the_type_b_part_per_scene():
    rng = np.random.default_rng(4)
    n = 30
    J = np.tile([0.0, 0.0, 1.0], (n, 1))
    std, bias = np.full(n, 0.01), np.full(n, 0.03)
    m = PointErrorModel(np.arange(n, dtype=float), J, ((std, 1.0), (bias, 10.0)), systematic=(1,))
    e = m.draw_held(rng, 400, 20)[..., 2]
    assert e.shape == (400, 20, n)
    # Within a scene only the noise varies; over scenes the whole variance.
    assert e.var(axis=1, ddof=1).mean() == pytest.approx(0.01**2, rel=0.05)
    assert e.reshape(-1, n).var(axis=0).mean() == pytest.approx(0.01**2 + 0.03**2, rel=0.1)
    assert m.draw(rng, 4000)[..., 2].var(axis=0).mean() == pytest.approx(0.01**2 + 0.03**2, rel=0.1)
