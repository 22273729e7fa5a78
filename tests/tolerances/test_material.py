"""Position at MMC / LMC: the bonus from the measured size and its uncertainty."""

import math
from dataclasses import replace

import numpy as np
import pytest

from partinspect.cad.registration import register
from partinspect.errors import InputError
from partinspect.simulate.measured import measure_features
from partinspect.tolerances.decision import decide
from partinspect.tolerances.evaluate import evaluate, position_gradient
from partinspect.tolerances.material import bonus_sign, position_with_bonus, reference_size
from partinspect.tolerances.resolve import characteristics_for
from partinspect.tolerances.spec import parse_spec


def test_bonus_signs_and_reference_sizes():
    # hole at MMC: its smallest size; boss at MMC: its largest; LMC the other way round
    assert reference_size("MMC", True, 9.75, 10.25) == 9.75 and bonus_sign("MMC", True) == 1
    assert reference_size("MMC", False, 9.75, 10.25) == 10.25 and bonus_sign("MMC", False) == -1
    assert reference_size("LMC", True, 9.75, 10.25) == 10.25 and bonus_sign("LMC", True) == -1
    assert reference_size("LMC", False, 9.75, 10.25) == 9.75 and bonus_sign("LMC", False) == 1
    assert reference_size("MMC", True, 4.9, 5.1, scale=2.0) == pytest.approx(9.8)
    g = np.zeros(3)
    # a hole 0.12 mm over its MMC size: the zone grows by exactly 0.12 mm
    q, u, bonus, u_b, rho = position_with_bonus(0.30, 0.01, g, 9.87, 0.004, np.zeros(3), "MMC", True, 9.75)
    assert bonus == pytest.approx(0.12) and q == pytest.approx(0.18) and u_b == 0.004
    assert u == pytest.approx(math.hypot(0.01, 0.004)) and rho == 0
    # a boss 0.12 under its MMC size: the same bonus; at LMC a hole gets d_LMC - d
    assert position_with_bonus(0.30, 0.01, g, 10.13, 0.004, np.zeros(3), "MMC", False, 10.25)[2] == pytest.approx(0.12)
    assert position_with_bonus(0.30, 0.01, g, 10.13, 0.004, np.zeros(3), "LMC", True, 10.25)[2] == pytest.approx(0.12)
    # a hole below its MMC size: a negative bonus (the virtual condition boundary), not clipped
    assert position_with_bonus(0.30, 0.01, g, 9.70, 0.004, np.zeros(3), "MMC", True, 9.75)[0] == pytest.approx(0.35)


def test_covariance_enters_the_combined_uncertainty():
    # position grows along x; the centre's x error goes with the diameter's
    g = np.array([2.0, 0.0, 0.0])
    cov_cd = np.array([1e-5, 0.0, 0.0])  # Cov(centre_x, d), mm^2
    u_p, u_d = 0.01, 0.004
    cov_pd = 2.0 * 1e-5
    q, u, _, _, rho = position_with_bonus(0.3, u_p, g, 9.8, u_d, cov_cd, "MMC", True, 9.75)
    # q = p - (d - d_MMC): Var q = u_p^2 + u_d^2 - 2 Cov(p, d)
    assert u == pytest.approx(math.sqrt(u_p**2 + u_d**2 - 2 * cov_pd))
    assert rho == pytest.approx(cov_pd / (u_p * u_d))
    # for a boss the bonus falls as d grows: the same covariance now adds
    _, u_boss, *_ = position_with_bonus(0.3, u_p, g, 9.8, u_d, cov_cd, "MMC", False, 9.9)
    assert u_boss == pytest.approx(math.sqrt(u_p**2 + u_d**2 + 2 * cov_pd))


def _spec_chars(inv, text):
    return characteristics_for(parse_spec(text, "part.tol.yaml"), inv, "part.tol.yaml")


def test_spec_material_resolves_the_size_and_the_side(plate):
    inv = plate[0]
    chars = {c.id: c for c in _spec_chars(inv, "features:\n  circle-4:\n    diameter: {upper: 0.1, lower: -0.05}\n"
                                               "    position: {tolerance: 0.05, material: MMC}\n"
                                               "  circle-8:\n    position: {tolerance: 0, material: LMC}\n")}
    p4, p8 = chars["circle-4.position"], chars["circle-8.position"]
    assert p4.material.internal is True and p4.material.size.id == "circle-4.diameter"
    assert p4.material.reference == pytest.approx(12.0 - 0.05)
    # no size in the spec: the general tolerance's (ISO 2768-m, 10 mm: +-0.2) is the one the bonus uses
    assert p8.upper_limit == 0 and p8.material.size.source.startswith("ISO 2768")
    assert p8.material.reference == pytest.approx(10.0 + 0.2)
    d = p4.to_dict()["material"]
    assert d == {"modifier": "MMC", "feature": "hole", "size": "circle-4.diameter", "reference_size": 11.95}


def test_spec_material_errors(plate):
    inv = plate[0]
    with pytest.raises(InputError, match="circle-4.position: tolerance 0 needs material"):
        _spec_chars(inv, "features:\n  circle-4:\n    position: {tolerance: 0}\n")
    with pytest.raises(InputError, match="expected 'MMC' or 'LMC'"):
        _spec_chars(inv, "features:\n  circle-4:\n    position: {tolerance: 0.1, material: max}\n")


def _measure(plate, rng, grow, shift):
    inv, T, ids = plate
    m = measure_features(inv, T, ids, rng, n_points=0, shifts={"circle-4": shift})
    i = m.circle_ids.index("circle-4")
    circles = list(m.circles)
    circles[i] = replace(circles[i], radius=circles[i].radius + grow / 2)  # the hole made larger
    datums = [x for x in ids if x.startswith("line")]
    return register(circles, m.lines, inv, datums=datums, pose_hint=T), i


def test_hole_larger_than_mmc_gets_exactly_that_bonus(plate):
    inv = plate[0]
    chars = _spec_chars(inv, "features:\n  circle-4:\n    diameter: {upper: 0.1, lower: -0.05}\n"
                             "    position: {tolerance: 0.05, material: MMC}\n")
    pos = next(c for c in chars if c.id == "circle-4.position")
    size = next(c for c in chars if c.id == "circle-4.diameter")
    reg, _ = _measure(plate, np.random.default_rng(5), 0.08, np.array([0.06, 0.0, 0.0]))
    e_pos, e_size = evaluate([pos, size], reg, inv, n_mc=2000)
    d = e_pos.details
    assert d["measured_size"] == e_size.measured
    assert d["bonus"] == pytest.approx(e_size.measured - 11.95, abs=1e-12)
    assert e_pos.measured == pytest.approx(d["position"] - d["bonus"], abs=1e-12)
    assert d["measured_size_standard_uncertainty"] == pytest.approx(e_size.standard_uncertainty)
    u = math.sqrt(d["position_standard_uncertainty"] ** 2 + d["bonus_standard_uncertainty"] ** 2
                  - 2 * d["position_bonus_correlation"] * d["position_standard_uncertainty"] * d["bonus_standard_uncertainty"])
    assert e_pos.standard_uncertainty == pytest.approx(u)
    # the position alone (about 0.12) fails its 0.05 zone; with the bonus (about 0.13) it passes
    assert d["position"] > 0.1 and decide(e_pos).decision == "pass"
    assert decide(replace(e_pos, measured=d["position"], expanded_uncertainty=2 * d["position_standard_uncertainty"])).decision == "fail"
    out = e_pos.to_dict()
    assert out["material"]["reference_size"] == 11.95 and out["details"]["bonus"] == pytest.approx(d["bonus"])
    # report.html shows where the value came from
    from partinspect.reports.html import render_html
    from tests.reports.synthetic import make_report

    report = make_report()
    report["characteristics"] = [decide(e_pos).to_dict()]
    html = render_html(report)
    assert (f"at MMC: position {d['position']:.4f} − bonus {d['bonus']:.4f} (measured size {d['measured_size']:.4f}, "
            "11.9500 at MMC)") in html
    # and junit.xml's failure body, had it failed
    from partinspect.reports.junit import junit_xml

    report["characteristics"][0]["decision"] = "fail"
    assert f"at MMC: position {d['position']:.4f} - bonus {d['bonus']:.4f}" in junit_xml(report)


def test_the_fits_centre_size_covariance_reaches_u(plate):
    inv = plate[0]
    (pos,) = [c for c in _spec_chars(inv, "features:\n  circle-4:\n    position: {tolerance: 0.05, material: MMC}\n")
              if c.id == "circle-4.position"]
    reg, i = _measure(plate, np.random.default_rng(6), 0.05, np.array([0.2, 0.0, 0.0]))
    pf = next(p for p in reg.features_in_part_frame() if p.cad_id == "circle-4")
    (plain,) = evaluate([pos], reg, inv, n_mc=2000)
    # The same measurement whose fit states the centre and the radius correlated (rig frame).
    rec = reg.measured_feature("circle", pf.index)
    g_rig = reg.rotation @ position_gradient(pf.center, pf.covariance, inv["circle-4"].center, inv["circle-4"].normal)
    C = np.zeros((7, 7))
    C[:3, :3] = rec.covariance
    C[3:6, 3:6] = rec.normal_cov
    C[6, 6] = rec.radius_std**2
    e = g_rig / np.linalg.norm(g_rig)  # correlated along the offset only: a valid covariance
    C[:3, 6] = C[6, :3] = 0.6 * rec.radius_std * np.sqrt(e @ rec.covariance @ e) * e
    object.__setattr__(rec, "param_cov", C)
    pf2 = next(p for p in reg.features_in_part_frame() if p.cad_id == "circle-4")
    (corr,) = evaluate([pos], reg, inv, n_mc=2000)
    assert corr.measured == pytest.approx(plain.measured)
    assert plain.details["position_bonus_correlation"] == pytest.approx(0.0, abs=1e-12)
    cov_pd = position_gradient(pf2.center, pf2.covariance, inv["circle-4"].center, inv["circle-4"].normal) @ (2 * pf2.param_cov[:3, 6])
    assert cov_pd > 0
    u_p, u_b = corr.details["position_standard_uncertainty"], corr.details["bonus_standard_uncertainty"]
    assert corr.standard_uncertainty == pytest.approx(math.sqrt(u_p**2 + u_b**2 - 2 * cov_pd), rel=1e-9)
    assert corr.standard_uncertainty < plain.standard_uncertainty


def test_value_and_u_agree_with_the_truth_over_draws(plate):
    inv = plate[0]
    chars = _spec_chars(inv, "features:\n  circle-4:\n    diameter: {upper: 0.1, lower: -0.05}\n"
                             "    position: {tolerance: 0.05, material: MMC}\n")
    pos = next(c for c in chars if c.id == "circle-4.position")
    rng = np.random.default_rng(7)
    truth = 2 * 0.06 - (12.04 - 11.95)  # the position minus the hole's 0.09 mm bonus
    z = []
    for draw in range(40):
        reg, _ = _measure(plate, rng, 0.04, np.array([0.06, 0.0, 0.0]))
        (e,) = evaluate([pos], reg, inv, seed=draw, n_mc=1000)
        z.append((e.measured - truth) / e.standard_uncertainty)
    assert 0.6 < math.sqrt(np.mean(np.square(z))) < 1.4, z
