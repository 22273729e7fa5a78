"""Datum shift: a pattern of holes located from datum features of size at MMB (issue 40)."""

import json
import math
from dataclasses import replace
from importlib import resources

import jsonschema
import numpy as np
import pytest

from partinspect.cad.registration import register
from partinspect.errors import InputError
from partinspect.simulate.measured import measure_features
from partinspect.tolerances.datum_shift import allowance, best_shift, parse_datum
from partinspect.tolerances.decision import decide
from partinspect.tolerances.evaluate import evaluate
from partinspect.tolerances.resolve import characteristics_for
from partinspect.tolerances.spec import dump_spec, parse_spec, spec_to_dict

SQUARE = np.array([[20.0, 0.0], [0.0, 20.0], [-20.0, 0.0], [0.0, -20.0]])
DATUMS = np.array([[0.0, 0.0], [40.0, 0.0]])


def test_parse_datum():
    assert parse_datum("B(M)") == ("B", "MMB") and parse_datum("C(L)") == ("C", "LMB") and parse_datum("A") == ("A", None)
    with pytest.raises(ValueError, match="datum letter"):
        parse_datum("B(X)")


def test_allowance_is_half_the_departure_from_the_boundary():
    # a hole 0.3 mm over its MMB lets its simulator move 0.15 mm each way; a boss under it alike
    assert allowance("MMB", True, 12.3, 0.004, 12.0) == pytest.approx((0.15, 0.002))
    assert allowance("MMB", False, 9.7, 0.004, 10.0) == pytest.approx((0.15, 0.002))
    assert allowance("LMB", True, 12.2, 0.004, 12.5) == pytest.approx((0.15, 0.002))
    # beyond its boundary (a hole below its MMB size): no shift, and no uncertainty in that nothing
    assert allowance("MMB", True, 11.9, 0.004, 12.0) == pytest.approx((0.0, 0.0))
    assert allowance(None, True, 12.3, 0.004, None) == pytest.approx((0.0, 0.0))


def test_a_pattern_shifted_as_one_passes_within_the_allowance_and_not_beyond():
    moved = SQUARE + [0.15, 0.0]  # every hole 0.15 mm off, together: positions 0.3 in a 0.1 zone
    b, t = np.zeros(4), np.full(4, 0.1)
    wide = best_shift(SQUARE, moved, b, t, DATUMS, DATUMS, np.array([0.2, 0.2]))
    assert wide.values == pytest.approx(np.zeros(4), abs=1e-4) and wide.unshifted == pytest.approx(np.full(4, 0.3))
    assert wide.translation == pytest.approx([0.15, 0.0], abs=1e-5)
    # an allowance of 0.02 takes 0.04 off each position, no more
    narrow = best_shift(SQUARE, moved, b, t, DATUMS, DATUMS, np.array([0.02, 0.02]))
    assert narrow.values == pytest.approx(np.full(4, 0.26), abs=1e-5)
    # at RFS (no departure) nothing moves
    assert best_shift(SQUARE, moved, b, t, DATUMS, DATUMS, np.zeros(2)).values == pytest.approx(np.full(4, 0.3))


def test_rotation_clocked_by_the_second_datum_free_or_held():
    a = 0.002
    R = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    turned = SQUARE @ R.T  # the pattern turned 0.002 rad about datum B
    b, t, rho = np.zeros(4), np.full(4, 0.1), np.array([0.05, 0.05])
    # C, 40 mm from B, lets the frame turn by 0.05 / 40 rad: 20 mm x (0.002 - 0.00125) left, doubled
    clocked = best_shift(SQUARE, turned, b, t, DATUMS, DATUMS, rho, "clocked")
    assert clocked.rotation == pytest.approx(0.05 / 40, rel=1e-4)
    assert clocked.values == pytest.approx(np.full(4, 2 * 20 * (a - 0.05 / 40)), rel=1e-3)
    assert best_shift(SQUARE, turned, b, t, DATUMS, DATUMS, rho, "free").values == pytest.approx(np.zeros(4), abs=1e-4)
    held = best_shift(SQUARE, turned, b, t, DATUMS, DATUMS, rho, "fixed")
    assert held.rotation == 0 and held.values == pytest.approx(np.full(4, 2 * 20 * math.sin(a)), rel=1e-3)


SPEC = """\
datum_features: {{A: [line-1], B: [circle-4], C: [circle-8]}}
features:
  circle-4: {{diameter: {{upper: 0.5, lower: 0}}}}
  circle-8: {{diameter: {{upper: 0.5, lower: 0}}}}
  circle-2: {{position: {{tolerance: 0.1, datums: [A, {b}, {c}]}}}}
  circle-6: {{position: {{tolerance: 0.1, datums: [A, {b}, {c}]}}}}
  circle-10: {{position: {{tolerance: 0.1, datums: [A, {b}, {c}]}}}}
"""
PATTERN = ("circle-2.position", "circle-6.position", "circle-10.position")


def test_spec_datums_read_back_and_errors(plate):
    inv = plate[0]
    spec = parse_spec(SPEC.format(b="B(M)", c="C(M)"))
    assert spec.features["circle-2"].position.datums == ("A", "B(M)", "C(M)")
    assert spec_to_dict(parse_spec(dump_spec(spec))) == spec_to_dict(spec)
    chars = {c.id: c for c in characteristics_for(spec, inv)}
    refs = chars["circle-2.position"].datums
    assert [d.label for d in refs] == ["A", "B(M)", "C(M)"]
    assert refs[1].features == ("circle-4",) and refs[1].internal is True and refs[1].sizes[0].id == "circle-4.diameter"
    assert refs[1].reference(refs[1].sizes[0]) == pytest.approx(12.0) and not refs[0].of_size
    assert chars["circle-2.position"].to_dict()["datum_reference"][1] == {
        "datum": "B", "boundary": "MMB", "features": ["circle-4"], "feature_of_size": "hole", "boundary_size": 12.0}
    with pytest.raises(InputError, match=r"line 5: features.circle-2.position.datums: expected a datum letter"):
        parse_spec(SPEC.format(b="B(X)", c="C(M)"))
    with pytest.raises(InputError, match="datum B named twice"):
        parse_spec(SPEC.format(b="B(M)", c="B"))
    with pytest.raises(InputError, match=r"datum_features\.B\[0\]: unknown feature 'hole-4'"):
        parse_spec(SPEC.format(b="B(M)", c="C(M)").replace("B: [circle-4]", "B: [hole-4]"))


def _measured(plate, grow_b, grow_c, seed=5):
    """The plate with its three small holes 0.12 mm off in x together, datums B (circle-4) and C (circle-8) grown."""
    inv, T, ids = plate
    shift = np.array([0.12, 0.0, 0.0])
    m = measure_features(inv, T, ids, np.random.default_rng(seed), n_points=0,
                         shifts={"circle-2": shift, "circle-6": shift, "circle-10": shift})
    circles = list(m.circles)
    for fid, grow in (("circle-4", grow_b), ("circle-8", grow_c)):
        i = m.circle_ids.index(fid)
        circles[i] = replace(circles[i], radius=circles[i].radius + grow / 2)
    return register(circles, m.lines, inv, datums=[x for x in ids if x.startswith("line")], pose_hint=T)


def _evaluate(plate, spec, reg):
    chars = [c for c in characteristics_for(parse_spec(spec), plate[0]) if c.id in PATTERN]
    return {e.id: decide(e) for e in evaluate(chars, reg, plate[0])}


def test_the_datum_shift_turns_a_fail_into_a_pass(plate):
    reg = _measured(plate, 0.4, 0.4)  # B and C 0.4 mm over their MMB: 0.2 mm of shift allowed
    shifted = _evaluate(plate, SPEC.format(b="B(M)", c="C(M)"), reg)
    rfs = _evaluate(plate, SPEC.format(b="B", c="C"), reg)
    for cid in PATTERN:
        e, plain = shifted[cid].evaluation, rfs[cid].evaluation
        # without the shift each hole is 0.24 mm off its place (a 0.1 zone): fail
        assert plain.measured == pytest.approx(0.24, abs=0.02) and rfs[cid].decision == "fail"
        assert "datum_shift" not in plain.details
        d = e.details["datum_shift"]
        assert shifted[cid].decision == "pass", (e.measured, e.expanded_uncertainty)
        assert e.measured < 0.02 and e.details["without_shift"] == pytest.approx(plain.measured, abs=0.01)
        assert d["applied"] and d["datums"] == "A | B(M) | C(M)" and d["pattern"] == list(PATTERN)
        assert d["translation"] == pytest.approx(0.12, abs=0.01) and d["translation"] <= d["allowance"]["B"]
        assert d["allowance"]["B"] == pytest.approx(0.2, abs=0.01) and d["boundary_sizes"] == {"B": 12.0, "C": 10.0}
        assert 0 < e.standard_uncertainty < 0.02
        assert e.to_dict()["details"]["datum_shift"]["translation"] == pytest.approx(d["translation"])


def test_a_shift_too_small_cannot_save_the_pattern(plate):
    reg = _measured(plate, 0.1, 0.1)  # 0.05 mm of shift: positions about 0.24 - 0.1
    out = _evaluate(plate, SPEC.format(b="B(M)", c="C(M)"), reg)
    for cid in PATTERN:
        e = out[cid].evaluation
        assert out[cid].decision == "fail" and e.measured == pytest.approx(0.14, abs=0.02)
        assert e.details["datum_shift"]["translation"] == pytest.approx(0.05, abs=0.005)


def test_datums_without_features_say_no_shift_was_applied(plate):
    reg = _measured(plate, 0.4, 0.4)
    out = _evaluate(plate, SPEC.format(b="B(M)", c="C(M)").replace("B: [circle-4], ", ""), reg)
    for cid in PATTERN:
        d = out[cid].evaluation.details["datum_shift"]
        assert not d["applied"] and "datum B's features are not known" in d["reason"]
        assert out[cid].decision == "fail"


def test_the_report_says_the_shift_applied(plate):
    from partinspect.reports.html import render_html
    from partinspect.reports.junit import junit_xml
    from partinspect.reports.writer import report_json
    from tests.reports.synthetic import make_report

    reg = _measured(plate, 0.4, 0.4)
    d = _evaluate(plate, SPEC.format(b="B(M)", c="C(M)"), reg)["circle-2.position"]
    entry = d.to_dict()
    shift = entry["details"]["datum_shift"]
    report = make_report()
    report["characteristics"] = [entry]
    assert (f"datum shift (A | B(M) | C(M)): moved {shift['translation']:.4f} mm (allowed "
            f"{shift['allowance']['B']:.4f}, {shift['allowance']['C']:.4f})") in render_html(report)
    report["characteristics"][0]["decision"] = "fail"
    assert f"datum shift (A | B(M) | C(M)): moved {shift['translation']:.4f} mm" in junit_xml(report)
    # and report.json's schema takes the entry
    schema = json.loads(resources.files("partinspect.reports").joinpath("schemas/report-1.schema.json").read_text())
    jsonschema.validate(json.loads(report_json(report)), schema)


def test_several_views_say_the_shift_is_not_applied(plate):
    from partinspect.tolerances.evaluate import without_datum_shifts

    reg = _measured(plate, 0.4, 0.4)
    chars = [c for c in characteristics_for(parse_spec(SPEC.format(b="B(M)", c="C(M)")), plate[0]) if c.id in PATTERN]
    plain = evaluate(chars, reg, plate[0], datum_shift=False)
    out = without_datum_shifts(plain, "several views")
    for before, after in zip(plain, out):
        assert after.measured == before.measured and decide(after).decision == "fail"
        assert after.details["datum_shift"] == {"datums": "A | B(M) | C(M)", "applied": False, "reason": "several views"}
        assert after.method.endswith("no datum shift applied (several views)")


def test_offsets_are_shrunk_unless_significant():
    from partinspect.tolerances.datum_shift import shrunk_centres

    covs = np.array([np.eye(2) * 1e-4] * 3)  # tr = 2e-4 mm^2: 3 tr = 6e-4
    r = np.array([[0.02, 0.0], [0.0, 0.03], [0.1, 0.0]])
    mu = shrunk_centres(r, covs)
    assert mu[0] == pytest.approx([0.0, 0.0])  # 4e-4 < 6e-4: taken as zero
    assert mu[1] == pytest.approx([0.0, math.sqrt(9e-4 - 6e-4)])
    assert mu[2] == pytest.approx([math.sqrt(0.01 - 6e-4), 0.0])
