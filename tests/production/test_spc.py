"""SPC maths against numbers computed by hand (and printed tables), not by the code under test."""

import numpy as np
from scipy import stats
import pytest

from partinspect.production import spc

X = np.array([1.0, 3.0, 2.0, 4.0, 3.0, 5.0])
# mean 3; deviations -2 0 -1 1 0 2: s = sqrt(10 / 5) = 1.414214;
# moving ranges 2 1 2 1 2: mean 1.6, sigma_w = 1.6 / 1.128379 = 1.417963.


def test_capability_indices_of_a_hand_computed_series():
    r = spc.characteristic_summary(X, 0.0, 9.0)
    assert r["mean"] == pytest.approx(3.0)
    assert r["s"] == pytest.approx(1.414214, abs=1e-6)
    assert r["sigma_within"] == pytest.approx(1.417963, abs=1e-6)
    assert r["pp"] == pytest.approx(9 / (6 * 1.414214), abs=1e-6)   # 1.060660
    assert r["ppk"] == pytest.approx(3 / (3 * 1.414214), abs=1e-6)  # 0.707107, the lower side
    assert r["cp"] == pytest.approx(9 / (6 * 1.417963), abs=1e-6)   # 1.057856
    assert r["cpk"] == pytest.approx(3 / (3 * 1.417963), abs=1e-6)


def test_chi_square_interval_of_pp_matches_the_table():
    # chi-square table, 5 degrees of freedom: 0.8312 (2.5 %) and 12.833 (97.5 %).
    lo, hi = spc.characteristic_summary(X, 0.0, 9.0)["pp_ci"]
    assert lo == pytest.approx(1.060660 * np.sqrt(0.8312 / 5), abs=2e-4)   # 0.4325
    assert hi == pytest.approx(1.060660 * np.sqrt(12.833 / 5), abs=2e-4)   # 1.6992


def test_bissell_interval_of_ppk():
    # 0.707107 -+ 1.959964 sqrt(1 / 54 + 0.5 / 10) = 0.707107 -+ 0.513044
    lo, hi = spc.characteristic_summary(X, 0.0, 9.0)["ppk_ci"]
    assert (lo, hi) == pytest.approx((0.194063, 1.220151), abs=1e-5)


def test_within_interval_uses_fewer_degrees_of_freedom():
    r = spc.characteristic_summary(X, 0.0, 9.0)
    width = lambda ci: ci[1] - ci[0]  # noqa: E731
    assert width(r["cp_ci"]) / r["cp"] > width(r["pp_ci"]) / r["pp"]


def test_one_sided_limits_give_cpk_only():
    cp, cpk = spc.capability_indices(0.02, 0.01, None, 0.1)
    assert cp is None and cpk == pytest.approx((0.1 - 0.02) / 0.03)
    assert spc.tolerance_width(None, 0.1) == 0.1          # natural lower limit 0
    assert spc.measurement_capability_ratio(0.02, None, 0.1) == pytest.approx(0.4)
    assert spc.measurement_capability_ratio(0.004, 11.95, 12.05) == pytest.approx(0.08)
    assert spc.measurement_capability_ratio(0.004, 11.95, None) is None


def test_individuals_chart_limits():
    lim = spc.individuals_limits(X)
    assert lim["ucl"] == pytest.approx(3 + 3 * 1.417963, abs=1e-5)
    assert lim["lcl"] == pytest.approx(3 - 3 * 1.417963, abs=1e-5)
    assert lim["mr_ucl"] == pytest.approx(3.267 * 1.6)


def test_each_run_rule_fires_on_its_pattern_and_not_on_noise():
    def fired(x):
        return {r: list(i) for r, i in spc.run_rule_violations(np.asarray(x, float), 0.0, 1.0).items() if len(i)}

    assert fired([0.5, -3.5, 0.2]) == {1: [1]}
    assert fired([0.5] * 8 + [-0.5]) == {}                           # 8 on one side: not yet
    assert fired([0.5] * 9 + [-0.5])[2] == [8]
    up = fired([-0.9, -0.6, -0.3, 0.1, 0.4, 0.8])                    # 6 rising, all within 1 sigma
    assert up == {3: [5]}
    assert fired([0.5, -0.5] * 7)[4] == [13]
    assert fired([0.0, 2.5, 0.0, 2.5])[5] == [3]                     # 2 of 3 beyond +2: at the third point
    assert fired([1.5, 1.5, 0.0, 1.5, 1.5])[6] == [4]
    assert fired([0.5, -0.5] * 8)[7] == [14, 15]                     # with rule 4 too
    assert fired([1.5, -1.5] * 4)[8] == [7]
    rng = np.random.default_rng(3)
    # A stable process trips a test rarely: a few per cent of points over the eight tests.
    noise = rng.standard_normal(2000)
    hits = np.unique(np.concatenate(list(spc.run_rule_violations(noise, 0.0, 1.0).values())))
    assert len(hits) < 0.05 * noise.size


def test_a_drift_is_flagged():
    rng = np.random.default_rng(0)
    x = 12.0 + 0.002 * rng.standard_normal(40) + np.linspace(0, 0.02, 40)
    r = spc.characteristic_summary(x, 11.95, 12.05)
    assert len(r["violations"][2]) or len(r["violations"][1])
    assert r["cpk"] > r["ppk"]  # the drift widens the overall spread, not the within one


def test_measuring_system_capability_from_the_uncertainties():
    r = spc.characteristic_summary(np.full(5, 12.0) + [0, 1e-3, 0, 2e-3, 1e-3], 11.99, 12.01,
                                   u=np.array([0.003, 0.004, 0.003, 0.004, 0.003]))
    # u_rms = sqrt((3 * 9 + 2 * 16) / 5) um = 3.4351 um; U = 6.8702 um; Q = 2 U / 20 um = 0.68702
    assert r["U"] == pytest.approx(0.0068702, abs=1e-7)
    assert r["q_mp"] == pytest.approx(0.68702, abs=1e-5)
    assert r["capable_measurement"] is False


# Montgomery's piston-ring inside diameters (mm), samples 1-25 of 5 rings each, as R's qcc
# package ships them (data(pistonrings), the trial samples) [spc.py reference 7].
PISTON_RINGS = np.array([
    74.030, 74.002, 74.019, 73.992, 74.008, 73.995, 73.992, 74.001, 74.011, 74.004,
    73.988, 74.024, 74.021, 74.005, 74.002, 74.002, 73.996, 73.993, 74.015, 74.009,
    73.992, 74.007, 74.015, 73.989, 74.014, 74.009, 73.994, 73.997, 73.985, 73.993,
    73.995, 74.006, 73.994, 74.000, 74.005, 73.985, 74.003, 73.993, 74.015, 73.988,
    74.008, 73.995, 74.009, 74.005, 74.004, 73.998, 74.000, 73.990, 74.007, 73.995,
    73.994, 73.998, 73.994, 73.995, 73.990, 74.004, 74.000, 74.007, 74.000, 73.996,
    73.983, 74.002, 73.998, 73.997, 74.012, 74.006, 73.967, 73.994, 74.000, 73.984,
    74.012, 74.014, 73.998, 73.999, 74.007, 74.000, 73.984, 74.005, 73.998, 73.996,
    73.994, 74.012, 73.986, 74.005, 74.007, 74.006, 74.010, 74.018, 74.003, 74.000,
    73.984, 74.002, 74.003, 74.005, 73.997, 74.000, 74.010, 74.013, 74.020, 74.003,
    73.988, 74.001, 74.009, 74.005, 73.996, 74.004, 73.999, 73.990, 74.006, 74.009,
    74.010, 73.989, 73.990, 74.009, 74.014, 74.015, 74.008, 73.993, 74.000, 74.010,
    73.982, 73.984, 73.995, 74.017, 74.013])


def test_xbar_r_chart_of_the_piston_rings_matches_the_textbook_figures():
    """qcc(diameter[1:25,], type="xbar") prints centre 74.00118, std.dev 0.009785039, limits 73.98805
    and 74.01431; type="R" centre 0.02276, limits 0 and 0.04812533 (Montgomery: x_bar_bar 74.001,
    R_bar 0.023, limits 73.988 and 74.014). qcc takes d2 and D4 unrounded, the tables to 3 decimals:
    the figures agree to the tables' rounding."""
    r = spc.characteristic_summary(PISTON_RINGS, 73.95, 74.05, subgroups=np.arange(125) // 5)
    lim = r["limits"]
    assert r["chart"] == "xbar-r" and r["subgroup_size"] == 5 and len(r["subgroup_means"]) == 25
    assert lim["center"] == pytest.approx(74.00118, abs=5e-6)
    assert lim["r_mean"] == pytest.approx(0.02276, abs=5e-7)
    assert r["sigma_within"] == pytest.approx(0.009785039, rel=1e-4)       # R_bar / 2.326
    assert (lim["lcl"], lim["ucl"]) == pytest.approx((73.98805, 74.01431), abs=2e-5)
    assert (lim["r_lcl"], lim["r_ucl"]) == pytest.approx((0.0, 0.04812533), abs=2e-5)
    # In control (as the textbook finds): no mean beyond its limits, no range beyond the R chart's.
    assert len(r["violations"][1]) == 0 and len(r["range_violations"]) == 0
    assert r["subgroups_left_out"] == 0


def test_xbar_r_against_an_independent_numpy_computation():
    rng = np.random.default_rng(11)
    n, k = 4, 20
    x = 8.0 + 0.003 * rng.standard_normal(n * k) + np.repeat(0.002 * rng.standard_normal(k), n)
    table = x.reshape(k, n)
    xbar, rng_ = table.mean(axis=1), table.max(axis=1) - table.min(axis=1)
    sigma_w = rng_.mean() / 2.059                                  # d2(4)
    r = spc.characteristic_summary(x, 7.98, 8.03, subgroups=np.repeat(np.arange(k), n))
    assert r["subgroup_means"] == pytest.approx(xbar) and r["subgroup_ranges"] == pytest.approx(rng_)
    assert r["limits"]["ucl"] == pytest.approx(xbar.mean() + 0.729 * rng_.mean())
    assert r["limits"]["r_ucl"] == pytest.approx(2.282 * rng_.mean())
    assert r["sigma_within"] == pytest.approx(sigma_w)
    assert r["cp"] == pytest.approx(0.05 / (6 * sigma_w))
    assert r["cpk"] == pytest.approx(min(8.03 - x.mean(), x.mean() - 7.98) / (3 * sigma_w))
    assert r["ppk"] == pytest.approx(min(8.03 - x.mean(), x.mean() - 7.98) / (3 * x.std(ddof=1)))
    # Degrees of freedom 0.9 k (n - 1) = 54 for the within interval of Cp.
    lo, hi = r["cp_ci"]
    assert lo == pytest.approx(r["cp"] * np.sqrt(stats.chi2.ppf(0.025, 54) / 54))


def test_chart_constants_follow_from_the_range_distribution():
    """d2(n) = E[range of n standard normal values] = integral of 1 - Phi^n - (1 - Phi)^n; A2 = 3 / (d2 sqrt n);
    D3 + D4 = 2 where D3 > 0 (both are 1 -+ 3 d3 / d2)."""
    from scipy import integrate

    for n, (a2, d3, d4, d2) in spc.XBAR_R_CONSTANTS.items():
        exact = integrate.quad(lambda t: 1 - stats.norm.cdf(t) ** n - stats.norm.sf(t) ** n, -10, 10)[0]
        assert d2 == pytest.approx(exact, abs=5e-4), n
        assert a2 == pytest.approx(3 / (d2 * np.sqrt(n)), abs=1.5e-3), n
        if d3 > 0:
            assert d3 + d4 == pytest.approx(2.0, abs=1.5e-3), n


def test_subgroups_of_another_size_are_left_out_and_single_parts_chart_as_individuals():
    x = np.array([1.0, 1.2, 0.9, 1.1, 1.0, 1.3, 0.8, 1.0, 1.1])
    r = spc.characteristic_summary(x, 0.0, 2.0, subgroups=["a", "a", "a", "b", "b", "b", "c", "c", "d"])
    assert r["chart"] == "xbar-r" and r["subgroup_size"] == 3 and r["subgroups_left_out"] == 2
    assert [list(g) for g in r["subgroup_index"]] == [[0, 1, 2], [3, 4, 5]]
    assert r["mean"] == pytest.approx(x.mean()) and r["s"] == pytest.approx(x.std(ddof=1))
    assert spc.characteristic_summary(x, 0.0, 2.0, subgroups=range(9))["chart"] == "individuals"
    assert spc.characteristic_summary(x, 0.0, 2.0, subgroups=[0] * 9)["chart"] == "individuals"  # one subgroup of 9
    assert spc.characteristic_summary(np.r_[x, x], 0.0, 2.0, subgroups=[0] * 11 + [1] * 7)["chart"] == "individuals"


def test_a_shift_of_the_mean_fires_on_the_xbar_chart():
    rng = np.random.default_rng(5)
    x = 12.0 + 0.002 * rng.standard_normal(5 * 24)
    x[5 * 16:] += 0.010                                      # the last 8 subgroups shifted by 5 sigma of a value
    r = spc.characteristic_summary(x, 11.95, 12.05, subgroups=np.arange(x.size) // 5)
    assert set(range(16, 24)) <= set(r["violations"][1])     # every shifted mean beyond the limits
    assert len(r["range_violations"]) == 0                   # the spread did not change
    x[5 * 16:] -= 0.010
    r = spc.characteristic_summary(x, 11.95, 12.05, subgroups=np.arange(x.size) // 5)
    assert len(r["violations"][1]) == 0
