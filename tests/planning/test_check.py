"""The rendered check's arithmetic: the chance interval of a spread and the u a check leaves."""

import numpy as np
import pytest

from partinspect.planning.check import chance_interval, checked_uncertainty


def test_chance_interval_is_the_chi_square_interval_of_a_sample_sd():
    # chi2(49) quantiles 31.555 and 70.222 (tables).
    assert chance_interval(50) == pytest.approx([np.sqrt(31.555 / 49), np.sqrt(70.222 / 49)], rel=1e-4)
    lo, hi = chance_interval(3)
    assert lo < 0.2 and hi > 1.9  # three draws tell little
    # The sample sd of n normal values falls inside it 95 % of the time.
    rng = np.random.default_rng(0)
    s = rng.standard_normal((20000, 10)).std(axis=1, ddof=1)
    lo, hi = chance_interval(10)
    assert np.mean((s >= lo) & (s <= hi)) == pytest.approx(0.95, abs=0.006)
    with pytest.raises(ValueError):
        chance_interval(1)


def test_chance_interval_widens_for_heavy_tails():
    # Gumbel values (excess kurtosis 2.4, as a maximum of many): the normal
    # interval holds their sample sd too rarely, the kurtosis-aware one 95 %.
    rng = np.random.default_rng(1)
    s = rng.gumbel(size=(20000, 20)).std(axis=1, ddof=1) / (np.pi / np.sqrt(6))
    lo, hi = chance_interval(20)
    assert np.mean((s >= lo) & (s <= hi)) < 0.88
    lo, hi = chance_interval(20, excess_kurtosis=2.4)
    assert np.mean((s >= lo) & (s <= hi)) == pytest.approx(0.95, abs=0.02)
    # A light-tailed sample does not narrow it.
    assert np.allclose(chance_interval(20, excess_kurtosis=-1.0), chance_interval(20))
    # Where the normal interval calls a spread beyond chance, the heavy-tailed one may not.
    assert checked_uncertainty(0.01, 0.004, 1.4 * 0.004, 20)[1] == "prediction low"
    assert checked_uncertainty(0.01, 0.004, 1.4 * 0.004, 20, excess_kurtosis=2.4) == (0.01, "agrees")


def test_a_spread_beyond_chance_adds_its_excess_in_quadrature():
    u, noise = 0.010, 0.004
    # 2 x the predicted image-noise part on 50 draws: beyond chance; the excess
    # variance (0.008^2 - 0.004^2) joins the prediction's.
    got, verdict = checked_uncertainty(u, noise, 0.008, 50)
    assert verdict == "prediction low" and got == pytest.approx(np.sqrt(u**2 + 0.008**2 - noise**2))
    # Within chance: the prediction stands.
    assert checked_uncertainty(u, noise, 0.0044, 50) == (u, "agrees")
    # Below the interval: kept as it is (conservative), but named.
    assert checked_uncertainty(u, noise, 0.002, 50) == (u, "prediction high")
    # The same ratio on 3 draws is within chance.
    assert checked_uncertainty(u, noise, 0.0072, 3) == (u, "agrees")


def test_a_form_value_is_judged_by_the_spreads_of_its_scenes():
    from partinspect.planning.check import form_interval

    rng = np.random.default_rng(2)
    spreads = 0.004 * rng.lognormal(0.0, 0.2, 4000)
    lo, hi = form_interval(spreads, 0.004)
    assert lo == pytest.approx(np.exp(-1.96 * 0.2), rel=0.03) and hi == pytest.approx(np.exp(1.96 * 0.2), rel=0.03)
    # 1.4 x the prediction on 20 draws: beyond the chance of normal values,
    # within what the scene's fixed displacements allow.
    assert checked_uncertainty(0.01, 0.004, 1.4 * 0.004, 20)[1] == "prediction low"
    assert checked_uncertainty(0.01, 0.004, 1.4 * 0.004, 20, interval=(lo, hi)) == (0.01, "agrees")
    assert checked_uncertainty(0.01, 0.004, 1.6 * 0.004, 20, interval=(lo, hi))[1] == "prediction low"


@pytest.mark.parametrize("offset", [0.0, 0.05])
def test_a_position_at_mmc_spreads_with_its_bonus(offset):
    # The chain decides position - bonus(d) (material.position_with_bonus):
    # over the draws its spread holds the size's spread too, taken at the
    # true position as the position's own spread is (a render's systematic
    # offset, here 0.05 mm, enters neither).
    from partinspect.planning.check import RenderedCheck
    from partinspect.tolerances.material import MaterialCondition

    rng = np.random.default_rng(4)
    n, u_c, u_own = 4000, 0.004, 0.006
    e = rng.standard_normal((n, 2)) * u_c
    d = np.column_stack([offset + e[:, 0], e[:, 1], np.zeros(n)])  # in-plane offsets, normal z
    sizes = 12.04 + 0.5 * e[:, 0] + u_own * rng.standard_normal(n)  # the fit ties the size to the centre
    sizes[7] = np.nan  # a draw without the size leaves the position's pair out too
    hole = MaterialCondition("MMC", internal=True)
    chk = RenderedCheck(("p",), {"p": "position"}, {"p": np.zeros(n)}, {"p": np.zeros(n)}, {"p": d}, n, [],
                        {"p": (hole, sizes)})
    plain = RenderedCheck(("p",), {"p": "position"}, {"p": np.zeros(n)}, {"p": np.zeros(n)}, {"p": d}, n, [])
    u_position = plain.spread("p")
    assert u_position == pytest.approx(2 * np.sqrt(2) * u_c, rel=0.05)
    u_size = np.hypot(0.5 * u_c, u_own)
    assert chk.spread("p") == pytest.approx(np.hypot(u_position, u_size), rel=0.02)
    assert chk.spread("p") > u_position * 1.1
