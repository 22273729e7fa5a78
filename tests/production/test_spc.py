"""SPC maths against numbers computed by hand (and printed tables), not by the code under test."""

import numpy as np
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
