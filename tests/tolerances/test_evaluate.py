"""Characteristic values and uncertainties against the truth over repeated noise draws."""

import math

import numpy as np
import pytest

from partinspect.cad.registration import register
from partinspect.simulate.measured import measure_features
from partinspect.tolerances.evaluate import evaluate, monte_carlo, propagate, true_position
from partinspect.tolerances.form import circularity, straightness
from partinspect.tolerances.geometry import feature_distance, line_angle
from partinspect.tolerances.resolve import Characteristic, characteristics_for
from partinspect.tolerances.spec import load_spec, parse_spec

from tests.cad.conftest import EXAMPLES

N_DRAWS = 60


def C(cid, ctype, feats, nominal=0.0, lo=None, up=1.0, unit="mm"):
    return Characteristic(cid, ctype, tuple(feats), nominal, lo, up, "test", unit=unit)


def _z_rms(chars, truths, plate, n_points=0, shifts=None, datums=None, seed=0):
    """RMS of (measured - truth) / u per characteristic over noise draws; and the values."""
    inv, T, ids = plate
    rng = np.random.default_rng(seed)
    z, vals = [], []
    for draw in range(N_DRAWS):
        m = measure_features(inv, T, ids, rng, n_points=n_points, shifts=shifts)
        reg = register(m.circles, m.lines, inv, datums=datums, pose_hint=T)
        ev = evaluate(chars, reg, inv, seed=draw, n_mc=1000)
        z.append([(e.measured - t) / e.standard_uncertainty for e, t in zip(ev, truths)])
        vals.append([e.measured for e in ev])
    return np.sqrt(np.mean(np.square(z), axis=0)), np.array(vals)


def test_pose_invariant_characteristics_are_consistent(plate):
    inv = plate[0]
    chars = [
        C("d", "diameter", ["circle-4"], 12.0, 11.9, 12.1),
        C("r", "radius", ["circle-6"], 2.0, 1.9, 2.1),
        C("cc", "distance", ["circle-2", "circle-4"], feature_distance(inv["circle-2"], inv["circle-4"]), 0, 100),
        C("cl", "distance", ["circle-2", "line-5"], feature_distance(inv["circle-2"], inv["line-5"]), 0, 100),
        C("ll", "distance", ["line-5", "line-8"], 60.0, 59, 61),
        C("a", "angle", ["line-5", "line-1"], math.pi / 2, 1.5, 1.6, unit="rad"),
    ]
    truths = [c.nominal for c in chars]
    assert abs(line_angle(inv["line-5"].start, inv["line-5"].end, inv["line-1"].start, inv["line-1"].end) - math.pi / 2) < 1e-12
    rms, _ = _z_rms(chars, truths, plate)
    assert np.all((rms > 0.65) & (rms < 1.4)), rms


def test_angle_between_skew_edges_does_not_depend_on_their_seen_extent(plate):
    # line-3 (top of the left face, along y) and line-6 (bottom of the front face, along x): perpendicular
    # planes, edges 10 mm apart. Seen over 90 % or 40 % of their length, the angle is 90 degrees.
    inv, T, ids = plate
    (c,) = [x for x in characteristics_for(parse_spec("angles:\n  - {between: [line-3, line-6], upper: 0.5, "
                                                      "lower: -0.5}\n"), inv) if x.type == "angle"]
    assert c.id == "angle(line-3,line-6)" and c.nominal == pytest.approx(math.pi / 2, abs=1e-12)
    rng = np.random.default_rng(5)
    for inset in (0.05, 0.3):
        z = []
        for draw in range(20):
            m = measure_features(inv, T, ids, rng, n_points=0, inset=inset)
            (e,) = evaluate([c], register(m.circles, m.lines, inv, pose_hint=T), inv, seed=draw)
            z.append((e.measured - math.pi / 2) / e.standard_uncertainty)
        assert 0.5 < np.sqrt(np.mean(np.square(z))) < 1.5, (inset, z)


def test_position_of_moved_hole_and_profile_of_moved_edge(plate):
    inv, T, ids = plate
    shifts = {"circle-4": np.array([0.1, 0.0, 0.0]), "line-5": np.array([0.0, 0.05, 0.0])}
    datums = [i for i in ids if i not in shifts]
    chars = [C("p4", "position", ["circle-4"], up=0.1), C("pl", "profile", ["line-5"], up=0.1), C("p2", "position", ["circle-8"], up=0.1)]
    # truths: 2 x 0.1 mm in the hole's plane, 2 x 0.05 mm offset of the edge, 0 for an unmoved hole
    rms, vals = _z_rms(chars, [0.2, 0.1, 0.0], plate, shifts=shifts, datums=datums, seed=1)
    assert abs(vals[:, 0].mean() - 0.2) < 0.005
    # the profile is a maximum over the stretch: biased up by about one u, which u covers
    assert 0.1 < vals[:, 1].mean() < 0.115
    assert np.all((rms[:2] > 0.65) & (rms[:2] < 1.4)), rms
    # at zero the Monte Carlo u (RMS about the estimate) still matches the Rice-distributed error
    assert 0.6 < rms[2] < 1.5, rms


def test_position_uncertainty_includes_pose(plate):
    inv, T, ids = plate
    m = measure_features(inv, T, ids, np.random.default_rng(2), n_points=0)
    reg = register(m.circles, m.lines, inv, datums=[i for i in ids if i.startswith("line")], pose_hint=T)
    (e,) = evaluate([C("p", "position", ["circle-4"])], reg, inv)
    pf = [p for p in reg.features_in_part_frame() if p.cad_id == "circle-4"][0]
    R = reg.rotation
    own = R.T @ m.circles[m.circle_ids.index("circle-4")].covariance @ R
    nominal = inv["circle-4"]
    v, u = true_position(pf.center, pf.covariance, nominal.center, nominal.normal, np.random.default_rng(99))
    assert e.measured == pytest.approx(v) and e.standard_uncertainty == pytest.approx(u, rel=0.05)
    # the pose (estimated from the lines only) adds to the in-plane covariance of the hole's centre
    P = np.eye(3) - np.outer(nominal.normal, nominal.normal)
    B = pf.pose_jacobian[:3]
    pose_part = np.trace(P @ B @ reg.pose_cov @ B.T @ P)
    assert pose_part > 0.05 * np.trace(P @ own @ P)
    assert np.trace(P @ pf.covariance @ P) == pytest.approx(np.trace(P @ own @ P) + pose_part, rel=1e-9)
    assert "pose" in e.method


def test_form_noise_bias_is_removed(plate):
    chars = [C("s", "straightness", ["line-5"]), C("k", "circularity", ["circle-4"])]
    inv, T, ids = plate
    rng = np.random.default_rng(3)
    raw, val, u = [], [], []
    for draw in range(N_DRAWS):
        m = measure_features(inv, T, ids, rng, n_points=60)
        reg = register(m.circles, m.lines, inv, pose_hint=T)
        ev = evaluate(chars, reg, inv, seed=draw)
        raw.append([e.details["raw"] for e in ev])
        val.append([e.measured for e in ev])
        u.append([e.standard_uncertainty for e in ev])
    raw, val, u = map(np.array, (raw, val, u))
    # uncorrected, noise alone looks like several sigma of form; corrected, about zero
    assert np.all(raw.mean(0) > 3 * u.mean(0))
    assert np.all(np.abs(val.mean(0)) < 0.5 * u.mean(0))
    rms = np.sqrt(np.mean((val / u) ** 2, axis=0))
    assert np.all((rms > 0.65) & (rms < 1.4)), rms
    # report.json carries what was subtracted, so a user can judge the value.
    d = ev[0].to_dict()["details"]
    assert d["raw"] - d["noise_bias"] == pytest.approx(ev[0].measured)
    assert d["noise_bias"] > 0 and d["n_points"] > 0


def test_true_form_is_measured():
    rng = np.random.default_rng(4)
    s = np.linspace(0, 40, 80)
    ideal = np.c_[s, 0.03 * np.sin(np.pi * s / 40), np.zeros_like(s)] + [0, 0, 300]
    covs = np.array([np.diag([0.002, 0.002, 0.008]) ** 2] * len(s))
    truth = straightness(ideal, np.zeros_like(covs), rng, n_draws=5).raw  # noise-free LS zone
    r = straightness(ideal + rng.standard_normal(ideal.shape) * [0.002, 0.002, 0.008], covs, rng)
    # corrected value: not above the truth by more than noise, low by at most the bias
    assert truth - r.noise_bias - 3 * r.u < r.value < truth + 3 * r.u
    assert r.raw > r.value
    th = np.linspace(0, 2 * np.pi, 90, endpoint=False)
    rad = 5 + 0.01 * np.cos(3 * th)
    ring = np.c_[rad * np.cos(th), rad * np.sin(th), np.full_like(th, 300)]
    k0 = circularity(ring, np.zeros((90, 3, 3)), rng, n_draws=5).raw
    assert abs(k0 - 0.02) < 1e-3
    k = circularity(ring + rng.standard_normal(ring.shape) * 0.002, np.array([np.eye(3) * 0.002**2] * 90), rng)
    assert k0 - k.noise_bias - 3 * k.u < k.value < k0 + 3 * k.u


def test_propagation_helpers():
    v, u = propagate(lambda x: x[0] * 3 - x[1], np.array([1.0, 2.0]), np.diag([0.01, 0.04]))
    assert v == pytest.approx(1.0) and u == pytest.approx(math.sqrt(0.09 + 0.04), rel=1e-6)
    v, u = monte_carlo(lambda x: x.sum(1), np.zeros(2), np.eye(2), np.random.default_rng(0), 20000)
    assert v == 0 and u == pytest.approx(math.sqrt(2), rel=0.03)


def test_spec_characteristics_and_unmeasured(plate):
    inv, T, ids = plate
    path = EXAMPLES / "plate" / "part.tol.yaml"
    chars = characteristics_for(load_spec(path), inv, path)
    m = measure_features(inv, T, ids, np.random.default_rng(5), n_points=40)
    reg = register(m.circles, m.lines, inv)
    ev = evaluate(chars, reg, inv)
    assert [e.id for e in ev] == [c.id for c in chars]
    by_id = {e.id: e for e in ev}
    hidden = by_id["circle-1.diameter"]
    assert hidden.measured is None and "circle-1 not measured" in hidden.reason
    d = by_id["circle-4.diameter"]
    assert abs(d.measured - 12.0) < 0.02 and d.expanded_uncertainty == pytest.approx(2 * d.standard_uncertainty)
    assert d.to_dict()["measured"] == pytest.approx(d.measured)
    # reproducible: same inputs, same numbers
    again = evaluate(chars, reg, inv)
    assert [e.measured for e in again] == [e.measured for e in ev]


def test_a_form_value_that_cannot_be_simulated_is_inconclusive_with_its_reason(plate, monkeypatch):
    """Never a crash, never a pass: the characteristic is left unmeasured, so its decision is inconclusive."""
    from partinspect.tolerances import evaluate as E
    from partinspect.tolerances.decision import decide
    from partinspect.tolerances.form import FormSimulationError

    inv, T, ids = plate
    m = measure_features(inv, T, ids, np.random.default_rng(0), n_points=60)
    reg = register(m.circles, m.lines, inv, pose_hint=T)

    def fails(*args, **kwargs):
        raise FormSimulationError("in 3 of 200 simulated draws the outlier test left fewer than 4 points")

    monkeypatch.setattr(E, "circularity", fails)
    ev = evaluate([C("k", "circularity", ["circle-4"])], reg, inv)[0]
    assert ev.measured is None and ev.standard_uncertainty is None
    assert "cannot be simulated" in ev.reason and "fewer than 4 points" in ev.reason
    assert decide(ev).decision == "inconclusive"


def test_distances_and_positions_under_a_calibration_error_all_features_share(plate):
    """A calibration's error (a turn and shift of the rig frame and a 1e-4 scale, shared by every
    feature): distances and positions state what reaches them, neither the shared error whole (which
    the pose and the difference take up) nor nothing (the scale remains)."""
    from tests.cad.test_registration import _with_shared_error

    inv, T, ids = plate
    chars = [
        C("cc", "distance", ["circle-2", "circle-4"], feature_distance(inv["circle-2"], inv["circle-4"]), 0, 100),
        C("cl", "distance", ["circle-2", "line-5"], feature_distance(inv["circle-2"], inv["line-5"]), 0, 100),
        C("p4", "position", ["circle-4"], 0.0, None, 1.0),
        C("p6", "position", ["circle-6"], 0.0, None, 1.0),
    ]
    truths = [c.nominal for c in chars]
    rng = np.random.default_rng(5)
    z = []
    for draw in range(40):
        m = measure_features(inv, T, ids, rng, n_points=0)
        circles, lines = _with_shared_error(m, rng.standard_normal(7), (5e-4, 0.2, 1e-4))
        reg = register(circles, lines, inv)
        ev = evaluate(chars, reg, inv, seed=draw, n_mc=1000)
        z.append([(e.measured - t) / e.standard_uncertainty for e, t in zip(ev[:2], truths[:2])])
        # a position's true value is 0: its measured value is a distance, judged by its own u
        z[-1] += [e.measured / e.standard_uncertainty for e in ev[2:]]
    rms = np.sqrt(np.mean(np.square(z), axis=0))
    assert np.all((rms[:2] > 0.7) & (rms[:2] < 1.35)), rms
    # A position's value over its u: 1.05-1.11 with image noise alone on these draws (the value is a
    # length, never negative); the shared error must leave it there, not at a tenth of it.
    assert np.all((rms[2:] > 0.8) & (rms[2:] < 1.45)), rms


def test_angle_of_segments_that_cross_is_the_nominal_angle_not_its_supplement():
    # A leg's side is set by the segment's farther end from the vertex: where
    # a segment runs across the vertex, that end is as likely on one side as
    # the other. The measured directions are turned to the CAD legs instead.
    from partinspect.tolerances.geometry import line_legs

    c60, s60 = math.cos(math.pi / 3), math.sin(math.pi / 3)
    a0, a1 = np.array([-10.0, 0, 0]), np.array([10.0, 0, 0])  # a tie: the end is the leg
    b0, b1 = np.array([-8 * c60, -8 * s60, 0]), np.array([12 * c60, 12 * s60, 0])
    assert math.degrees(line_angle(a0, a1, b0, b1)) == pytest.approx(60)
    legs = line_legs(a0, a1, b0, b1)
    seen = (a0 + [-0.5, 0, 0], a1 + [-0.5, 0, 0], b0, b1)  # a seen 0.5 mm short at its end
    assert math.degrees(line_angle(*seen)) == pytest.approx(120)  # the old reading
    assert math.degrees(line_angle(*seen, legs=legs)) == pytest.approx(60)
    # Legs in another frame: turned with it.
    R = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    turned = [R @ p for p in seen]
    assert math.degrees(line_angle(*turned, legs=[R @ u for u in legs])) == pytest.approx(60)


def test_measured_angle_follows_the_cad_legs_when_a_segment_runs_past_the_vertex():
    # NIST CTC 01's 60 degree pair (PMI dim-3): line-129 measured across the
    # vertex of the two lines, its longer part beyond it.
    from dataclasses import replace

    from partinspect.cad.features import inventory
    from partinspect.cad.step import load_step

    from tests.cad.conftest import STEP_DIR

    inv = inventory(load_step(STEP_DIR / "nist_ctc_01_asme1_ap242-e1.stp"))
    (c,) = [x for x in characteristics_for(parse_spec("angles:\n  - {between: [line-138, line-129], upper: 0.5, "
                                                      "lower: -0.5}\n"), inv) if x.type == "angle"]
    assert c.nominal == pytest.approx(math.pi / 3)
    ids = [f.id for f in inv.features if not f.smooth]
    T = np.eye(4)
    T[:3, :3] = np.array([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]])  # looking down at the part
    T[:3, 3] = [-100.0, -100.0, 600.0]
    m = measure_features(inv, T, ids, np.random.default_rng(7), n_points=0)
    reg = register(m.circles, m.lines, inv, pose_hint=T)
    (e,) = evaluate([c], reg, inv)
    assert math.degrees(e.measured) == pytest.approx(60, abs=0.05)
    # The registration keeps the measured records; line-129's is now seen
    # from 30 mm beyond the vertex to 10 mm along its CAD leg.
    from partinspect.tolerances.geometry import line_legs

    j = m.line_ids.index("line-129")
    ln = m.lines[j]
    a, b = inv["line-138"], inv["line-129"]
    leg = T[:3, :3] @ line_legs(a.start, a.end, b.start, b.end)[1]
    vertex = T[:3, :3] @ np.array([110.0, -75.0, 0.0]) + T[:3, 3]  # where the two lines meet
    d = ln.direction / np.linalg.norm(ln.direction)
    v = ln.point + ((vertex - ln.point) @ d) * d
    d = d if d @ leg > 0 else -d
    lines = list(reg._lines)
    k = next(i for i, cid in reg.assignment["line"].items() if cid == "line-129")
    assert lines[k] is ln
    lines[k] = replace(ln, start=v - 30 * d, end=v + 10 * d)
    (e2,) = evaluate([c], replace(reg, _lines=tuple(lines)), inv)
    assert math.degrees(e2.measured) == pytest.approx(60, abs=0.05)
    assert e2.standard_uncertainty == pytest.approx(e.standard_uncertainty, rel=0.5)
