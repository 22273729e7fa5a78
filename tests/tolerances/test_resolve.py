"""Resolving a spec against a CAD inventory, and the general tolerances that fill the rest."""

import math
from pathlib import Path

import numpy as np
import pytest

from partinspect.cad.features import Feature, Inventory
from partinspect.frames import reference_direction
from partinspect.errors import InputError
from partinspect.tolerances.geometry import feature_distance, line_angle, line_gap
from partinspect.tolerances.resolve import (
    Characteristic,
    ResolvedSpec,
    characteristics_for,
    general_characteristics,
    resolve_spec,
    select_edge,
)
from partinspect.tolerances.spec import default_spec, load_spec, parse_spec

REPO = Path(__file__).resolve().parents[2]
Z = np.array([0.0, 0.0, 1.0])


def line(i, a, b):
    a, b = np.array(a, float), np.array(b, float)
    return Feature(f"line-{i}", "line", float(np.linalg.norm(b - a)), (), start=a, end=b)


def circle(i, c, r):
    return Feature(f"circle-{i}", "circle", 2 * math.pi * r, (), center=np.array(c, float), normal=Z, radius=float(r))


def arc(i, c, r, a0, a1):
    c = np.array(c, float)
    x = reference_direction(Z)
    y = np.cross(Z, x)

    def at(t):
        return c + r * (math.cos(t) * x + math.sin(t) * y)

    return Feature(f"arc-{i}", "arc", r * (a1 - a0), (), start=at(a0), end=at(a1), center=c, normal=Z, radius=float(r), angle_start=a0, angle_end=a1)


@pytest.fixture(scope="module")
def inv():
    """An 80 x 60 plate outline at z = 0 with two holes, a quarter arc and a 120-degree corner."""
    s = math.sqrt(3.0) / 2
    feats = (
        line(1, (0, 0, 0), (80, 0, 0)),
        line(2, (0, 60, 0), (80, 60, 0)),
        line(3, (0, 0, 0), (0, 60, 0)),
        line(4, (80, 0, 0), (80, 60, 0)),
        line(5, (100, 0, 0), (110, 0, 0)),
        line(6, (100 - 5, 10 * s, 0), (100, 0, 0)),  # ends at the vertex: orientation must not matter
        circle(1, (20, 30, 0), 5.0),
        circle(2, (60, 30, 0), 3.0),
        arc(1, (100, 50, 0), 4.0, 0.0, math.pi / 2),
    )
    return Inventory(feats, ())


def resolve(text, inv, path="part.tol.yaml"):
    return resolve_spec(parse_spec(text, path), inv)


def failure(text, inv, path="part.tol.yaml"):
    with pytest.raises(InputError) as e:
        resolve(text, inv, path)
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(f"{path}: ")
    return msg


def by_id(chars):
    return {c.id: c for c in chars}


# -- spec characteristics -------------------------------------------------------


def test_sizes_and_geometrical_tolerances(inv):
    r = resolve(
        "features:\n"
        "  circle-1:\n"
        "    diameter: {upper: 0.05, lower: -0.02}\n"
        "    position: {tolerance: 0.1}\n"
        "  arc-1:\n"
        "    radius: {upper: 0.1, lower: 0}\n"
        "  line-1:\n"
        "    straightness: {tolerance: 0.02}\n"
        "    profile: {tolerance: 0.2}\n",
        inv,
    )
    assert isinstance(r, ResolvedSpec)
    c = by_id(r.characteristics)
    d = c["circle-1.diameter"]
    assert (d.type, d.features, d.nominal, d.source, d.unit) == ("diameter", ("circle-1",), 10.0, "spec", "mm")
    assert d.lower_limit == pytest.approx(9.98) and d.upper_limit == pytest.approx(10.05)
    assert d.rule == "part.tol.yaml line 3"
    pos = c["circle-1.position"]
    assert (pos.nominal, pos.lower_limit, pos.upper_limit) == (0.0, None, 0.1)
    rad = c["arc-1.radius"]
    assert (rad.nominal, rad.lower_limit, rad.upper_limit) == (4.0, 4.0, 4.1)
    assert c["line-1.straightness"].upper_limit == 0.02
    assert c["line-1.profile"].upper_limit == 0.2
    assert [x.id for x in r.characteristics] == ["circle-1.diameter", "circle-1.position", "arc-1.radius", "line-1.straightness", "line-1.profile"]


def test_to_dict_matches_the_report_schema(inv):
    r = resolve("features:\n  circle-1:\n    diameter: {upper: 0.05, lower: -0.05}\n", inv)
    d = r.characteristics[0].to_dict()
    assert d == {
        "id": "circle-1.diameter",
        "feature": "circle-1",
        "features": ["circle-1"],
        "type": "diameter",
        "nominal": 10.0,
        "lower_limit": 9.95,
        "upper_limit": 10.05,
        "unit": "mm",
        "source": "spec",
        "rule": "part.tol.yaml line 3",
    }


def test_distances(inv):
    r = resolve(
        "distances:\n"
        "  - {between: [circle-1, circle-2], upper: 0.05, lower: -0.05}\n"
        "  - {between: [line-1, circle-1], upper: 0.1, lower: -0.1}\n"
        "  - {between: [line-1, line-2], upper: 0.2, lower: 0}\n"
        "  - {between: [line-3, line-4], upper: 0.2, lower: 0, nominal: 80.1}\n",
        inv,
    )
    c = by_id(r.characteristics)
    assert c["distance(circle-1,circle-2)"].nominal == pytest.approx(40.0)
    assert c["distance(circle-1,circle-2)"].features == ("circle-1", "circle-2")
    assert c["distance(line-1,circle-1)"].nominal == pytest.approx(30.0)
    assert c["distance(line-1,line-2)"].nominal == pytest.approx(60.0)
    assert c["distance(line-1,line-2)"].upper_limit == pytest.approx(60.2)
    assert c["distance(line-3,line-4)"].nominal == 80.1  # a given nominal within the tolerance of the CAD's 80
    assert c["distance(line-1,line-2)"].to_dict()["feature"] == "line-1,line-2"


def test_angles_are_radians_inside_degrees_in_the_report(inv):
    r = resolve(
        "angles:\n"
        "  - {between: [line-1, line-3], upper: 0.5, lower: -0.5}\n"
        "  - {between: [line-5, line-6], upper: 1, lower: 0}\n",
        inv,
    )
    c = by_id(r.characteristics)
    right = c["angle(line-1,line-3)"]
    assert right.unit == "rad" and right.nominal == pytest.approx(math.pi / 2)
    assert right.upper_limit == pytest.approx(math.pi / 2 + math.radians(0.5))
    d = right.to_dict()
    assert (d["nominal"], d["lower_limit"], d["upper_limit"], d["unit"]) == (90.0, 89.5, 90.5, "deg")
    assert math.degrees(c["angle(line-5,line-6)"].nominal) == pytest.approx(120.0)


def test_line_angle_ignores_edge_orientation():
    a = ((0, 0, 0), (10, 0, 0))
    b = ((0, 0, 0), (-5, 5 * math.sqrt(3), 0))
    for a0, a1 in (a, a[::-1]):
        for b0, b1 in (b, b[::-1]):
            assert math.degrees(line_angle(a0, a1, b0, b1)) == pytest.approx(120.0)
    # Lines that do not touch: the vertex is where they would meet.
    assert math.degrees(line_angle((2, 0, 0), (10, 0, 0), (-1, math.sqrt(3), 0), (-3, 3 * math.sqrt(3), 0))) == pytest.approx(120.0)
    with pytest.raises(ValueError, match="parallel"):
        line_angle((0, 0, 0), (1, 0, 0), (0, 1, 0), (3, 1, 0))


def test_line_angle_of_skew_lines_is_between_their_directions():
    # ftc_10's perpendicularity gtol-8: an edge of the toleranced face across z, one of datum A across z,
    # 72 mm apart. Rays from the common perpendicular's midpoint to the far ends made 103.49 degrees.
    face, datum = ((55, 0, 34.5), (55, 23, 34.5)), ((-70, 0, -37.5), (70, 0, -37.5))
    assert math.degrees(line_angle(*face, *datum)) == pytest.approx(90.0, abs=1e-12)
    assert line_gap(*face, *datum) == pytest.approx(72.0)
    # where a measured segment ends does not change it
    assert math.degrees(line_angle(*face, (-40, 0, -37.5), (60, 0, -37.5))) == pytest.approx(90.0, abs=1e-12)
    # a 120 degree corner lifted 30 mm off its partner's plane stays 120, the leg towards each far end
    a = ((0, 0, 0), (10, 0, 0))
    b = ((0, 0, 30), (-5, 5 * math.sqrt(3), 30))
    for a0, a1 in (a, a[::-1]):
        for b0, b1 in (b, b[::-1]):
            assert math.degrees(line_angle(a0, a1, b0, b1)) == pytest.approx(120.0)
    assert math.degrees(line_angle((0, 0, 0), (10, 0, 0), (-5, 5 * math.sqrt(3), 30), (-2, 2 * math.sqrt(3), 30))) \
        == pytest.approx(120.0)
    with pytest.raises(ValueError, match="parallel"):
        line_gap((0, 0, 0), (1, 0, 0), (0, 1, 0), (3, 1, 0))


def test_feature_distance_refuses_crossing_lines(inv):
    lines = {f.id: f for f in inv.features}
    with pytest.raises(ValueError, match="not parallel"):
        feature_distance(lines["line-1"], lines["line-3"])


def test_datums_default_to_all_and_resolve_names(inv):
    assert resolve("units: mm\n", inv).datums == tuple(f.id for f in inv.features)
    r = resolve("datums: [line-1, hole]\nfeatures:\n  hole:\n    at: [20, 35, 0]\n", inv)
    assert r.datums == ("line-1", "circle-1")
    assert dict(r.features) == {"hole": "circle-1"}
    assert r.general == "ISO 2768-mK" and r.decision_rule == "iso14253"


# -- at: selectors --------------------------------------------------------------


@pytest.mark.parametrize(
    "point, expected",
    [
        ((40, 60.3, 0.2), "line-2"),
        ((40, -0.5, 0), "line-1"),
        ((20, 25.2, 0), "circle-1"),  # on the rim, not the centre
        ((63, 30, 0.1), "circle-2"),
        ((100 + 4 * math.cos(0.7), 50 + 4 * math.sin(0.7), 0), "arc-1"),
        ((0.4, 30, 0), "line-3"),
    ],
)
def test_at_picks_the_nearest_edge(inv, point, expected):
    assert select_edge(inv, point).id == expected
    r = resolve(f"features:\n  that:\n    at: [{point[0]}, {point[1]}, {point[2]}]\n    profile: {{tolerance: 0.1}}\n", inv)
    assert dict(r.features) == {"that": expected}
    assert r.characteristics[0].id == "that.profile" and r.characteristics[0].features == (expected,)


def test_at_outside_the_arc_span_is_not_on_the_arc(inv):
    # Opposite the quarter arc: the full circle would be 0 mm away, the arc is not.
    with pytest.raises(ValueError, match="no edge within 1 mm"):
        select_edge(inv, (96, 50, 0))


def test_at_tie_fails(inv):
    msg = failure("features:\n  corner:\n    at: [0, 0, 0]\n    profile: {tolerance: 0.1}\n", inv)
    assert "line 3: features.corner.at:" in msg
    assert "line-1" in msg and "line-3" in msg and "; " not in msg.split(": ", 1)[1]


def test_at_far_from_every_edge_fails(inv):
    msg = failure("features:\n  nothing:\n    at: [40, 30, 0]\n    profile: {tolerance: 0.1}\n", inv)
    assert "line 3: features.nothing.at: no edge within 1 mm of [40, 30, 0] (nearest:" in msg


def test_at_on_an_id_must_agree(inv):
    assert dict(resolve("features:\n  line-2:\n    at: [40, 60, 0]\n", inv).features) == {"line-2": "line-2"}
    msg = failure("features:\n  line-2:\n    at: [40, 0, 0]\n", inv)
    assert "line 3: features.line-2.at: the edge nearest to [40, 0, 0] is line-1, not line-2" in msg


def test_named_feature_gets_kind_checked_after_selection(inv):
    msg = failure("features:\n  top:\n    at: [40, 60, 0]\n    diameter: {upper: 0.1, lower: 0}\n", inv)
    assert "line 4: features.top.diameter: diameter does not apply to line-2, a line" in msg


# -- mistakes only the CAD model reveals ---------------------------------------


def test_unknown_id_suggests_a_close_one(inv):
    msg = failure("features:\n  circle-7:\n    diameter: {upper: 0.1, lower: 0}\n", inv)
    assert msg.startswith("part.tol.yaml: line 2: features.circle-7: no feature circle-7 in the CAD model (did you mean circle-")


def test_unknown_id_without_a_close_one_lists_the_kinds():
    holes = Inventory((circle(1, (0, 0, 0), 5.0), circle(2, (20, 0, 0), 5.0)), ())
    msg = failure("features:\n  line-5:\n    straightness: {tolerance: 0.1}\n", holes)
    assert "line 2: features.line-5: no feature line-5 in the CAD model (the model has 2 circles)" in msg


def test_unknown_datum_and_references(inv):
    msg = failure(
        "datums: [line-1, line-77]\n"
        "distances:\n"
        "  - {between: [circle-1, circle-9], upper: 0.1, lower: 0}\n"
        "angles:\n"
        "  - {between: [line-1, line-99], upper: 1, lower: -1}\n",
        inv,
    )
    assert "line 1: datums[1]: no feature line-77 in the CAD model" in msg
    assert "line 3: distances[0].between[1]: no feature circle-9" in msg
    assert "line 5: angles[0].between[1]: no feature line-99" in msg


def test_same_characteristic_twice_through_a_name(inv):
    msg = failure(
        "features:\n  circle-1:\n    diameter: {upper: 0.1, lower: 0}\n  hole:\n    at: [25, 30, 0]\n    radius: {upper: 0.1, lower: 0}\n",
        inv,
    )
    assert "line 6: features.hole.radius: circle-1 already has its size toleranced in features.circle-1.diameter" in msg


def test_distance_and_angle_mistakes(inv):
    msg = failure(
        "features:\n  bottom:\n    at: [40, 0, 0]\n"
        "distances:\n"
        "  - {between: [line-1, line-3], upper: 0.1, lower: 0}\n"
        "  - {between: [circle-1, circle-2], upper: 0.1, lower: -0.1, nominal: 45}\n"
        "  - {between: [bottom, line-1], upper: 0.1, lower: 0}\n"
        "angles:\n"
        "  - {between: [line-1, line-2], upper: 1, lower: -1, nominal: 30}\n"
        "  - {between: [line-5, line-6], upper: 1, lower: -1, nominal: 60}\n"
        "  - {between: [line-1, bottom], upper: 1, lower: -1}\n",
        inv,
    )
    assert "line 5: distances[0]: no distance between line-1 and line-3: the lines are not parallel (90 degrees apart)" in msg
    assert "line 6: distances[1]: nominal 45 mm disagrees with the CAD model (40 mm) by more than the tolerance" in msg
    assert "line 7: distances[2].between: bottom and line-1 are the same edge line-1" in msg
    # parallel lines: an angle is a parallelism, nominal 0
    assert "line 9: angles[0]: nominal 30 degrees disagrees with the CAD model: the lines are parallel (0 degrees)" in msg
    assert "line 10: angles[1]: nominal 60 degrees disagrees with the CAD model (120 degrees" in msg
    assert "line 11: angles[2].between: line-1 and bottom are the same edge line-1" in msg


def test_angle_on_a_named_circle(inv):
    msg = failure(
        "features:\n  hole:\n    at: [25, 30, 0]\nangles:\n  - {between: [line-1, hole], upper: 1, lower: -1}\n", inv
    )
    assert "line 5: angles[0].between[1]: angles are between lines, circle-1 is a circle" in msg


def test_spec_path_is_used_by_default(inv, tmp_path):
    p = tmp_path / "x.tol.yaml"
    p.write_text("features:\n  circle-9:\n    position: {tolerance: 0.1}\n")
    with pytest.raises(InputError, match=r"^.*x\.tol\.yaml: line 2: features\.circle-9: no feature"):
        resolve_spec(load_spec(p), inv)


# -- general tolerances ---------------------------------------------------------


def test_general_tolerances_fill_every_feature(inv):
    chars = by_id(general_characteristics(inv, default_spec()))
    assert set(chars) == {
        *(f"line-{i}.straightness" for i in range(1, 7)),
        "circle-1.diameter", "circle-1.circularity",
        "circle-2.diameter", "circle-2.circularity",
        "arc-1.radius",
    }
    d = chars["circle-1.diameter"]  # 10 mm, class m, over 6 up to 30: +-0.2
    assert (d.nominal, d.lower_limit, d.upper_limit) == (10.0, pytest.approx(9.8), pytest.approx(10.2))
    assert d.source == "ISO 2768-mK (general tolerance)"
    assert d.rule == "ISO 2768-1 table 1, class m, over 6 up to 30 mm"
    d2 = chars["circle-2.diameter"]  # 6 mm: over 3 up to 6, +-0.1
    assert (d2.lower_limit, d2.upper_limit) == (pytest.approx(5.9), pytest.approx(6.1))
    # Circularity: the diameter tolerance, at most the K run-out 0.2 mm.
    assert chars["circle-1.circularity"].upper_limit == pytest.approx(0.2)
    assert chars["circle-2.circularity"].upper_limit == pytest.approx(0.2)
    assert chars["circle-1.circularity"].lower_limit is None
    r = chars["arc-1.radius"]  # 4 mm: over 3 up to 6, +-0.1
    assert (r.nominal, r.lower_limit, r.upper_limit) == (4.0, pytest.approx(3.9), pytest.approx(4.1))
    assert chars["line-1.straightness"].upper_limit == 0.2  # 80 mm, K, over 30 up to 100
    assert chars["line-5.straightness"].upper_limit == 0.05  # 10 mm, K, up to 10
    assert chars["line-1.straightness"].rule == "ISO 2768-2 table 1, class K, over 30 up to 100 mm"


def test_general_tolerances_skip_what_the_spec_gives(inv):
    spec = parse_spec(
        "general: ISO 2768-fH\n"
        "features:\n"
        "  circle-1:\n    diameter: {upper: 0.02, lower: -0.01}\n"
        "  circle-2:\n    position: {tolerance: 0.1}\n    circularity: {tolerance: 0.01}\n"
        "  edge:\n    at: [40, 60, 0]\n    straightness: {tolerance: 0.01}\n"
    )
    chars = by_id(general_characteristics(inv, spec))
    assert "circle-1.diameter" not in chars and "line-2.straightness" not in chars and "circle-2.circularity" not in chars
    # The spec's diameter tolerance (0.03 wide) sets the circularity, under H's 0.1 run-out.
    assert chars["circle-1.circularity"].upper_limit == pytest.approx(0.03)
    # A position does not tolerance the size: circle-2's diameter stays general, class f: +-0.05.
    assert (chars["circle-2.diameter"].lower_limit, chars["circle-2.diameter"].upper_limit) == (pytest.approx(5.95), pytest.approx(6.05))
    assert chars["line-1.straightness"].upper_limit == 0.1  # H, over 30 up to 100
    assert chars["line-1.straightness"].source == "ISO 2768-fH (general tolerance)"


def test_linear_only_class_gives_no_form_tolerances(inv):
    chars = general_characteristics(inv, parse_spec("general: ISO 2768-c\n"))
    assert {c.type for c in chars} == {"diameter", "radius"}
    assert by_id(chars)["circle-1.diameter"].upper_limit == pytest.approx(10.5)  # c, over 6 up to 30


def test_radius_spec_sets_circularity_from_twice_its_width(inv):
    spec = parse_spec("features:\n  circle-1:\n    radius: {upper: 0.01, lower: -0.01}\n")
    assert by_id(general_characteristics(inv, spec))["circle-1.circularity"].upper_limit == pytest.approx(0.04)


def test_tiny_hole_needs_a_spec():
    tiny = Inventory((circle(1, (0, 0, 0), 0.2), line(1, (5, 0, 0), (9, 0, 0))), ())
    with pytest.raises(InputError) as e:
        general_characteristics(tiny, default_spec(), "p.tol.yaml")
    assert str(e.value) == (
        "p.tol.yaml: circle-1 (diameter 0.4 mm): ISO 2768-1 sets no general tolerance below 0.5 mm; give one in the spec"
    )
    spec = parse_spec("features:\n  circle-1:\n    diameter: {upper: 0.01, lower: 0}\n")
    assert {c.id for c in general_characteristics(tiny, spec)} == {"circle-1.circularity", "line-1.straightness"}


def test_a_run_lists_what_no_tolerance_covers_and_evaluates_the_rest():
    from partinspect.tolerances.loading import load_characteristics
    from partinspect.tolerances.pmi_text import general_gaps_line, pmi_problems_line
    from partinspect.tolerances.resolve import GENERAL_GAP

    tiny = Inventory((circle(1, (0, 0, 0), 0.2), line(1, (5, 0, 0), (9, 0, 0))), ())
    gaps = []
    chars = general_characteristics(tiny, default_spec(), "p.tol.yaml", gaps=gaps)
    assert {c.id for c in chars} == {"line-1.straightness"}
    assert [item for item, _ in gaps] == ["circle-1.diameter"]
    assert "ISO 2768-1 sets no general tolerance below 0.5 mm" in gaps[0][1]
    resolved, chars = load_characteristics(tiny, None)
    assert {c.id for c in chars} == {"line-1.straightness"}
    assert [(n.item, n.type) for n in resolved.not_evaluated] == [("circle-1.diameter", GENERAL_GAP)]
    said = general_gaps_line("p.stp", resolved.not_evaluated)
    assert said.startswith("p.stp: 1 characteristic without a tolerance (ISO 2768 sets none for it: circle-1.diameter")
    assert pmi_problems_line("p.stp", resolved.not_evaluated) is None  # not a PMI item


def test_characteristics_for_is_spec_then_general_with_unique_ids(inv):
    spec = parse_spec("features:\n  circle-1:\n    diameter: {upper: 0.1, lower: 0}\n")
    chars = characteristics_for(spec, inv)
    assert chars[0].id == "circle-1.diameter" and chars[0].source == "spec"
    ids = [c.id for c in chars]
    assert len(ids) == len(set(ids))
    assert all(isinstance(c, Characteristic) for c in chars)


# -- the example parts ----------------------------------------------------------


def _example_tol_files():
    return sorted((REPO / "examples").glob("*/part.tol.yaml"))


@pytest.mark.parametrize("tol", _example_tol_files(), ids=lambda p: p.parent.name)
def test_example_specs_load_and_resolve(tol):
    pytest.importorskip("cadquery")
    from partinspect.cad.features import inventory
    from partinspect.cad.step import load_step

    inv = inventory(load_step(tol.with_name("part.step")))
    spec = load_spec(tol)
    chars = characteristics_for(spec, inv, tol)
    assert chars
    assert len({c.id for c in chars}) == len(chars)


@pytest.fixture(scope="module")
def plate():
    step = REPO / "examples" / "plate" / "part.step"
    if not step.is_file():
        pytest.skip("examples/plate/part.step not made yet")
    pytest.importorskip("cadquery")
    from partinspect.cad.features import inventory
    from partinspect.cad.step import load_step

    return inventory(load_step(step))


def test_real_plate_selectors_and_general_tolerances(plate):
    ids = {f.id for f in plate.features}
    spec = parse_spec(
        "features:\n"
        "  top-back:\n    at: [40.0, 60.0, 10.2]\n    straightness: {tolerance: 0.02}\n"
        "distances:\n  - {between: [circle-1, circle-3], upper: 0.05, lower: -0.05}\n"
    )
    r = resolve_spec(spec, plate)
    picked = r.features["top-back"]
    assert picked in ids
    f = next(f for f in plate.features if f.id == picked)
    assert f.kind == "line" and {f.start[1], f.end[1], f.start[2], f.end[2]} == {60.0, 10.0}
    c1, c3 = (next(f for f in plate.features if f.id == i) for i in ("circle-1", "circle-3"))
    assert r.characteristics[1].nominal == pytest.approx(float(np.linalg.norm(c1.center - c3.center)))
    general = general_characteristics(plate, r)
    covered = {c.features[0] for c in general}
    # Every edge gets a general characteristic, except the one line whose only one the spec gives.
    assert covered == ids - {picked}
    assert all(c.source == "ISO 2768-mK (general tolerance)" for c in general)
