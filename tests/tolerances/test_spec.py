"""The tolerance spec file: valid specs, and every kind of mistake with its line number."""

import textwrap

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from partinspect.errors import InputError
from partinspect.tolerances.spec import (
    ToleranceSpec,
    default_spec,
    dump_spec,
    load_spec,
    parse_spec,
    spec_to_dict,
)

DESIGN_EXAMPLE = """\
units: mm
general: ISO2768-mK            # class for everything not toleranced below
decision_rule: iso14253        # or: simple (measured value alone decides)
datums: [line-2, line-5, circle-1]   # features the alignment uses; default all
features:
  circle-3:                    # an id from `inspect features part.step`
    diameter: {upper: 0.05, lower: -0.05}
    position: {tolerance: 0.10}        # diameter of the true-position zone
  edge-near-top:               # any name, with a selector
    at: [45.0, 0.0, 12.0]      # a point on the wanted CAD edge (part frame):
                               # the edge nearest to it is taken
    straightness: {tolerance: 0.02}
distances:
  - {between: [circle-1, circle-3], upper: 0.05, lower: -0.05}
"""


def problem(text, path="part.tol.yaml"):
    """The error line parse_spec gives for ``text``."""
    with pytest.raises(InputError) as e:
        parse_spec(textwrap.dedent(text) if isinstance(text, str) else text, path)
    msg = str(e.value)
    assert "\n" not in msg, "one line on stderr is the rule"
    if path is not None:
        assert msg.startswith(f"{path}: ")
    return msg


def test_design_example_parses():
    spec = parse_spec(DESIGN_EXAMPLE, "part.tol.yaml")
    assert spec.units == "mm"
    assert spec.general == "ISO 2768-mK"
    assert spec.general_class.linear == "m" and spec.general_class.geometrical == "K"
    assert spec.decision_rule == "iso14253"
    assert spec.datums == ("line-2", "line-5", "circle-1")
    c3 = spec.features["circle-3"]
    assert (c3.diameter.upper, c3.diameter.lower) == (0.05, -0.05)
    assert c3.position.tolerance == 0.10
    assert list(c3.characteristics()) == ["diameter", "position"]
    top = spec.features["edge-near-top"]
    assert top.at == (45.0, 0.0, 12.0)
    assert top.straightness.tolerance == 0.02
    assert spec.distances[0].between == ("circle-1", "circle-3")
    assert spec.distances[0].nominal is None
    assert spec.path == "part.tol.yaml"
    assert spec.line_of(("features", "edge-near-top", "straightness")) == 12
    assert spec.line_of(("distances", 0, "upper")) == 14


def test_everything_is_optional():
    spec = parse_spec("units: mm\n")
    assert spec.model_dump() == default_spec().model_dump()
    assert spec.general == "ISO 2768-mK" and spec.decision_rule == "iso14253" and spec.datums is None


def test_empty_sections_written_as_null_are_empty():
    spec = parse_spec("features:\ndistances:\nangles:\n")
    assert spec.features == {} and spec.distances == () and spec.angles == ()


@pytest.mark.parametrize("text, expected", [("ISO 2768-mK", "ISO 2768-mK"), ("mK", "ISO 2768-mK"), ("ISO2768-fH", "ISO 2768-fH"), ("ISO 2768-c", "ISO 2768-c")])
def test_general_forms(text, expected):
    assert parse_spec(f"general: {text}\n").general == expected


def test_numbers_yaml_reads_as_text_are_numbers():
    # PyYAML (YAML 1.1) reads 1e-2 without a dot as a string.
    spec = parse_spec("features:\n  circle-1:\n    position: {tolerance: 1e-2}\n")
    assert spec.features["circle-1"].position.tolerance == 0.01


def test_simple_decision_rule_and_angles():
    spec = parse_spec(
        "decision_rule: simple\nangles:\n  - {between: [line-1, line-2], upper: 0.5, lower: -0.25, nominal: 120}\n"
    )
    assert spec.decision_rule == "simple"
    assert (spec.angles[0].upper, spec.angles[0].lower, spec.angles[0].nominal) == (0.5, -0.25, 120.0)


def test_line_number_of_a_typo():
    text = DESIGN_EXAMPLE.replace("diameter: {upper: 0.05,", "diameter: {upper: abc,")
    assert problem(text) == "part.tol.yaml: line 7: features.circle-3.diameter.upper: expected a number, got 'abc'"


def test_line_number_in_block_style():
    msg = problem(
        """\
        features:
          circle-3:
            diameter:
              upper: 0.05
              lower: -0.05
            position:
              tolerance: -0.1
        """
    )
    assert msg == "part.tol.yaml: line 7: features.circle-3.position.tolerance: expected a positive number, got -0.1"


def test_unknown_characteristic_with_suggestion():
    msg = problem("features:\n  circle-3:\n    diamter: {upper: 0.1, lower: 0}\n")
    assert "line 3: features.circle-3.diamter: unknown characteristic 'diamter'" in msg
    assert "did you mean 'diameter'?" in msg


def test_unknown_top_level_key_with_suggestion():
    msg = problem("units: mm\ngenral: mK\n")
    assert "line 2: genral: unknown key 'genral', expected one of units, general," in msg
    assert "did you mean 'general'?" in msg


def test_unknown_key_inside_limits():
    msg = problem("features:\n  circle-3:\n    diameter: {upper: 0.1, lower: 0, uper: 1}\n")
    assert "line 3: features.circle-3.diameter.uper: unknown key 'uper', expected one of upper, lower (did you mean 'upper'?)" in msg


@pytest.mark.parametrize(
    "body, expected",
    [
        ("diameter: {upper: 0.1, lower: 0.2}", "features.circle-1.diameter: lower 0.2 is above upper 0.1"),
        ("position: {tolerance: -0.1}", "features.circle-1.position.tolerance: expected a positive number, got -0.1"),
        ("position: {tolerance: 0}", "features.circle-1.position: tolerance 0 needs material: MMC or LMC (all of the "
         "zone is then the bonus)"),
        ("position: {tolerance: 0.1, material: MMR}", "features.circle-1.position.material: expected 'MMC' or 'LMC', "
         "got 'MMR'"),
        ("circularity: {tolerance: .nan}", "features.circle-1.circularity.tolerance: expected a finite number, got nan"),
        ("position: {tolerance: yes}", "features.circle-1.position.tolerance: expected a number, got true"),
        ("position: {tolerance: [1]}", "features.circle-1.position.tolerance: expected a number, got a list"),
        ("position: 0.1", "features.circle-1.position: expected a mapping, got 0.1"),
        ("diameter: {upper: 0.1}", "features.circle-1.diameter: missing key 'lower'"),
        ("straightness: {tolerance: 0.1}", "features.circle-1.straightness: straightness does not apply to a circle (a circle takes diameter, radius, position, circularity, profile)"),
        ("radius: {upper: 1, lower: 0}\n    diameter: {upper: 1, lower: 0}", "features.circle-1.radius: give diameter or radius, not both"),
        ("at: [1, 2]", "features.circle-1.at: expected a point [x, y, z] in mm, got a list"),
        ("at: [1, 2, x]", "features.circle-1.at[2]: expected a number, got 'x'"),
    ],
)
def test_feature_mistakes(body, expected):
    msg = problem(f"features:\n  circle-1:\n    {body}\n")
    assert f"line 3: {expected}" in msg


def test_diameter_on_a_line():
    msg = problem("features:\n  line-4:\n    diameter: {upper: 0.1, lower: 0}\n")
    assert msg == "part.tol.yaml: line 3: features.line-4.diameter: diameter does not apply to a line (a line takes straightness, profile)"


def test_circularity_on_an_arc():
    assert "circularity does not apply to a arc" in problem("features:\n  arc-1:\n    circularity: {tolerance: 0.1}\n")


def test_named_feature_needs_a_selector():
    msg = problem("features:\n  top-edge:\n    straightness: {tolerance: 0.1}\n")
    assert "line 2: features.top-edge: 'top-edge' is not a CAD feature id (line-N, circle-N or arc-N) and has no at:" in msg


def test_feature_body_must_be_a_mapping():
    assert "line 2: features.circle-1: expected a mapping, got nothing (null)" in problem("features:\n  circle-1:\n")


@pytest.mark.parametrize(
    "text, expected",
    [
        ("units: inch\n", "line 1: units: expected 'mm', got 'inch'"),
        ("general: mX\n", "line 1: general: expected an ISO 2768 class like 'ISO 2768-mK'"),
        ("decision_rule: strict\n", "line 1: decision_rule: expected 'iso14253' or 'simple', got 'strict'"),
        ("datums: []\n", "line 1: datums: expected at least one feature"),
        ("datums: line-1\n", "line 1: datums: expected a list, got 'line-1'"),
        ("datums: [line-1, line-1]\n", "line 1: datums[1]: 'line-1' is already a datum"),
        ("datums: [hole]\n", "line 1: datums[0]: unknown feature 'hole'"),
        ("features: [circle-1]\n", "line 1: features: expected a mapping, got a list"),
        ("distances: {between: [circle-1, circle-2]}\n", "line 1: distances: expected a list, got a mapping"),
    ],
)
def test_top_level_mistakes(text, expected):
    assert expected in problem(text)


@pytest.mark.parametrize(
    "item, expected",
    [
        ("{between: [circle-1], upper: 0.1, lower: 0}", "distances[0].between: expected two features [a, b], got a list"),
        ("{between: [circle-1, circle-1], upper: 0.1, lower: 0}", "distances[0].between: expected two different features, got 'circle-1' twice"),
        ("{between: [circle-1, circle-2], upper: 0.1, lower: 0.2}", "distances[0]: lower 0.2 is above upper 0.1"),
        ("{between: [circle-1, circle-2], upper: 0.1, lower: 0, nominal: -3}", "distances[0].nominal: expected a distance >= 0, got -3.0"),
        ("{between: [circle-1, hole-2], upper: 0.1, lower: 0}", "distances[0].between[1]: unknown feature 'hole-2'"),
        ("{between: [circle-1, circle-2], upper: 0.1, lower: 0, tol: 1}", "distances[0].tol: unknown key 'tol'"),
        ("{between: [circle-1, 7], upper: 0.1, lower: 0}", "distances[0].between[1]: expected text, got 7"),
    ],
)
def test_distance_mistakes(item, expected):
    assert f"line 2: {expected}" in problem(f"distances:\n  - {item}\n")


def test_same_distance_twice():
    msg = problem(
        "distances:\n  - {between: [circle-1, circle-2], upper: 0.1, lower: 0}\n"
        "  - {between: [circle-2, circle-1], upper: 0.2, lower: 0}\n"
    )
    assert "line 3: distances[1].between: the same pair is already toleranced in distances[0]" in msg


@pytest.mark.parametrize(
    "item, expected",
    [
        ("{between: [line-1, circle-2], upper: 1, lower: -1}", "angles[0].between[1]: angles are between lines, circle-2 is a circle"),
        ("{between: [line-1, line-2], upper: 1, lower: -1, nominal: 180}", "angles[0].nominal: expected an angle in degrees between 0 and 180"),
        ("{between: [line-1, line-2], upper: -1, lower: 1}", "angles[0]: lower 1.0 is above upper -1.0"),
    ],
)
def test_angle_mistakes(item, expected):
    assert f"line 2: {expected}" in problem(f"angles:\n  - {item}\n")


def test_duplicate_keys_are_reported():
    msg = problem(
        """\
        units: mm
        features:
          circle-1:
            diameter: {upper: 0.1, lower: 0}
            diameter: {upper: 0.2, lower: 0}
          circle-1:
            position: {tolerance: 0.1}
        units: mm
        """
    )
    assert "line 5: features.circle-1.diameter: duplicate key 'diameter' (first at line 4)" in msg
    assert "line 6: features.circle-1: duplicate key 'circle-1' (first at line 3)" in msg
    assert "line 8: units: duplicate key 'units' (first at line 1)" in msg


def test_duplicate_key_inside_a_flow_mapping():
    msg = problem("features:\n  circle-1:\n    diameter: {upper: 0.1, lower: 0, upper: 0.3}\n")
    assert "line 3: features.circle-1.diameter.upper: duplicate key 'upper'" in msg


def test_every_mistake_is_reported_in_line_order():
    msg = problem(
        """\
        units: inch
        features:
          circle-3:
            diameter: {upper: abc, lower: 0}
          line-1:
            diameter: {upper: 0.1, lower: 0}
        decision_rule: maybe
        """
    )
    parts = msg.removeprefix("part.tol.yaml: ").split("; ")
    assert [p.split(":")[0] for p in parts] == ["line 1", "line 4", "line 6", "line 7"]


@pytest.mark.parametrize("text", ["", "\n\n", "# only a comment\n", "---\n"])
def test_empty_file(text):
    assert problem(text) == "part.tol.yaml: empty file, expected a mapping with keys units, general, decision_rule, datums, datum_features, features, distances, angles, edge_break"


@pytest.mark.parametrize(
    "text, expected",
    [
        ("features: [unclosed\n", "not valid YAML"),
        ("a: b: c\n", "line 1: not valid YAML"),
        ("units: mm\n\tgeneral: mK\n", "not valid YAML"),
        ("units: mm\n---\nunits: mm\n", "not valid YAML"),
        ("x: !!python/object:os.system {}\n", "line 1: not valid YAML"),
    ],
)
def test_not_yaml(text, expected):
    assert expected in problem(text)


@pytest.mark.parametrize("text, got", [("- line-1\n- line-2\n", "a list"), ("just text\n", "'just text'"), ("42\n", "42")])
def test_yaml_that_is_not_a_mapping(text, got):
    assert problem(text) == f"part.tol.yaml: line 1: expected a mapping with keys units, general, decision_rule, datums, datum_features, features, distances, angles, edge_break, got {got}"


def test_binary_files():
    assert "not UTF-8" in problem(b"units: \xff\xfe\n")
    assert "not a text file" in problem("units: mm\x00\n")


def test_cyclic_alias_is_an_input_error():
    assert "line 1: features.circle-1.circle-1: unknown characteristic" in problem("features: &a {circle-1: *a}\n")
    assert "line 1: datums[0]: expected text, got a list" in problem("datums: &a [*a]\n")


def test_no_path_gives_message_without_prefix():
    with pytest.raises(InputError) as e:
        parse_spec("units: inch\n")
    assert str(e.value) == "line 1: units: expected 'mm', got 'inch'"


def test_load_spec(tmp_path):
    p = tmp_path / "part.tol.yaml"
    p.write_text(DESIGN_EXAMPLE)
    spec = load_spec(p)
    assert spec.path == str(p)
    assert spec.features["circle-3"].diameter.upper == 0.05
    p.write_text(DESIGN_EXAMPLE.replace("upper: 0.05,", "upper: 0.05, upper: 1,", 1))
    with pytest.raises(InputError, match=r"part\.tol\.yaml: line 7: .*duplicate key 'upper'"):
        load_spec(p)


def test_load_spec_missing_and_directory(tmp_path):
    with pytest.raises(InputError, match="tolerance file not found"):
        load_spec(tmp_path / "nope.yaml")
    with pytest.raises(InputError, match="not a regular file"):
        load_spec(tmp_path)


def test_dump_round_trip():
    spec = parse_spec(DESIGN_EXAMPLE)
    again = parse_spec(dump_spec(spec))
    assert again.model_dump() == spec.model_dump()
    assert spec_to_dict(again) == spec_to_dict(spec)


# -- property tests -----------------------------------------------------------

_num = st.floats(min_value=-100, max_value=100, allow_nan=False, allow_infinity=False)
_pos = st.floats(min_value=1e-6, max_value=10, allow_nan=False, allow_infinity=False)


@st.composite
def _limits(draw):
    a, b = draw(_num), draw(_num)
    return {"upper": max(a, b), "lower": min(a, b)}


_zone = st.builds(lambda t: {"tolerance": t}, _pos)
_index = st.integers(min_value=1, max_value=40)


@st.composite
def valid_specs(draw):
    spec = {
        "units": "mm",
        "general": draw(st.sampled_from(["ISO2768-mK", "ISO 2768-fH", "cL", "ISO 2768-v", "mk"])),
        "decision_rule": draw(st.sampled_from(["iso14253", "simple"])),
    }
    features = {}
    for _ in range(draw(st.integers(0, 5))):
        kind = draw(st.sampled_from(["line", "circle", "arc", "named"]))
        body = {}
        if kind == "named":
            name = draw(st.from_regex(r"[a-z][a-z_]{0,8}-?[a-z]{0,5}", fullmatch=True))
            body["at"] = [draw(_num), draw(_num), draw(_num)]
            kind_of_named = draw(st.sampled_from(["line", "circle"]))
            chars = ["straightness", "profile"] if kind_of_named == "line" else ["diameter", "position", "circularity", "profile"]
        else:
            name = f"{kind}-{draw(_index)}"
            chars = {"line": ["straightness", "profile"], "circle": ["diameter", "position", "circularity", "profile"], "arc": ["radius", "position", "profile"]}[kind]
        for c in draw(st.lists(st.sampled_from(chars), unique=True)):
            body[c] = draw(_limits()) if c in ("diameter", "radius") else draw(_zone)
        features[name] = body
    if features:
        spec["features"] = features
        if draw(st.booleans()):
            spec["datums"] = sorted(set(draw(st.lists(st.sampled_from(sorted(features)), min_size=1))))
    pairs = draw(st.lists(st.tuples(_index, _index).filter(lambda p: p[0] < p[1]), unique=True, max_size=3))
    if pairs:
        spec["distances"] = [{"between": [f"circle-{a}", f"line-{b}"], **draw(_limits())} for a, b in pairs]
    lines = draw(st.lists(st.tuples(_index, _index).filter(lambda p: p[0] < p[1]), unique=True, max_size=3))
    if lines:
        spec["angles"] = [{"between": [f"line-{a}", f"line-{b}"], **draw(_limits())} for a, b in lines]
    return spec


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(valid_specs())
def test_random_valid_specs_round_trip(data):
    text = yaml.safe_dump(data, sort_keys=False)
    spec = parse_spec(text, "random.tol.yaml")
    assert isinstance(spec, ToleranceSpec)
    for name, body in data.get("features", {}).items():
        got = spec.features[name]
        for key, value in body.items():
            if key == "at":
                assert list(got.at) == value
            else:
                assert getattr(got, key).model_dump(exclude_none=True) == value
    assert [list(d.between) for d in spec.distances] == [d["between"] for d in data.get("distances", [])]
    again = parse_spec(dump_spec(spec))
    assert again.model_dump() == spec.model_dump()


_yaml_scalars = st.one_of(st.none(), st.booleans(), st.integers(), st.floats(), st.text(max_size=12))
_yaml_values = st.recursive(
    _yaml_scalars,
    lambda kids: st.one_of(st.lists(kids, max_size=4), st.dictionaries(st.one_of(st.text(max_size=10), st.sampled_from(["units", "general", "features", "circle-1", "line-2", "diameter", "upper", "lower", "tolerance", "at", "between", "distances", "angles", "datums"])), kids, max_size=4)),
    max_leaves=20,
)


@settings(max_examples=200, deadline=None)
@given(_yaml_values)
def test_random_structures_raise_only_input_error(value):
    text = yaml.safe_dump(value)
    try:
        parse_spec(text, "garbage.yaml")
    except InputError as e:
        assert "\n" not in str(e)


@settings(max_examples=300, deadline=None)
@given(st.one_of(st.text(max_size=200), st.binary(max_size=200)))
def test_random_text_raises_only_input_error(text):
    try:
        parse_spec(text, "garbage.yaml")
    except InputError as e:
        assert "\n" not in str(e)


@settings(max_examples=100, deadline=None)
@given(valid_specs(), st.data())
def test_one_corrupted_value_is_caught(data, draw):
    """Replacing any number by text makes the spec fail, naming the right line."""
    text = yaml.safe_dump(data, sort_keys=False, default_flow_style=False)
    lines = text.splitlines()
    numeric = [i for i, line in enumerate(lines) if line.rstrip().split(": ")[-1].lstrip("- ").replace(".", "", 1).replace("-", "", 1).replace("e", "", 1).replace("+", "", 1).isdigit() and ": " in line]
    if not numeric:
        return
    i = draw.draw(st.sampled_from(numeric))
    key = lines[i].split(": ")[0]
    lines[i] = f"{key}: not-a-number"
    with pytest.raises(InputError, match=rf"line {i + 1}: "):
        parse_spec("\n".join(lines) + "\n", "x.yaml")
