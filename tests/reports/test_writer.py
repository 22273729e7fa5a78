"""report.json against its schema, junit.xml structure, HTML escaping, atomic writes."""

import json
import re
import xml.etree.ElementTree as ET
from importlib import resources

import jsonschema
import pytest

from partinspect.reports.html import render_html
from partinspect.reports.junit import junit_xml
from partinspect.reports.writer import REPORT_FILES, write_reports

SCHEMA = json.loads(resources.files("partinspect.reports").joinpath("schemas/report-1.schema.json").read_text())


def char(cid, decision, measured=12.013, **kw):
    c = {
        "id": cid, "feature": cid.split(".")[0], "type": cid.split(".")[1], "nominal": 12.0,
        "measured": measured, "deviation": None if measured is None else measured - 12.0,
        "standard_uncertainty": None if measured is None else 0.003,
        "expanded_uncertainty": None if measured is None else 0.006,
        "lower_limit": 11.95, "upper_limit": 12.05, "decision": decision,
    }
    c.update(kw)
    return c


def make_report(chars, part="part.step", verdict="fail"):
    return {
        "schema": "report/1", "part": part, "units": "mm", "verdict": verdict,
        "created": "2026-11-22T10:00:00+00:00",
        "inputs": [{"role": "part", "path": part, "sha256": "0" * 64}],
        "images": {"width": 2448, "height": 2048, "bit_depth": 8},
        "tolerances": {"file": None, "general": "ISO2768-mK", "decision_rule": "iso14253"},
        "registration": {"part_to_camera": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 400], [0, 0, 0, 1]], "rms": 0.004},
        "features": [
            {"id": "circle-3", "kind": "circle", "nominal": {"center": [1, 2, 3], "normal": [0, 0, 1], "radius": 6.0},
             "measured": {"center": [1, 2, 3.01], "normal": [0, 0, 1], "radius": 6.006,
                          "covariance": [[1e-6, 0, 0], [0, 1e-6, 0], [0, 0, 4e-6]], "radius_std": 0.003}},
            {"id": "line-2", "kind": "line", "nominal": {"start": [0, 0, 0], "end": [10, 0, 0]}, "measured": None,
             "status": "not measured", "reason": "hidden"},
        ],
        "characteristics": chars,
        "summary": {"features": 2, "features_measured": 1, "characteristics": len(chars),
                    **{d: sum(c["decision"] == d for c in chars) for d in ("pass", "fail", "inconclusive")}},
    }


CHARS = [char("circle-3.diameter", "pass"), char("circle-4.diameter", "fail", 12.2),
         char("circle-5.diameter", "inconclusive", None, reason="not measured")]


def test_report_matches_schema_and_schema_rejects_nonsense():
    report = make_report(CHARS)
    jsonschema.validate(report, SCHEMA)
    bad = make_report([char("circle-3.diameter", "maybe")])
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(bad, SCHEMA)
    bad = make_report(CHARS)
    bad["features"][0]["nominal"].pop("radius")
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(bad, SCHEMA)


def test_junit_one_case_per_characteristic():
    root = ET.fromstring(junit_xml(make_report(CHARS)))
    suite = root.find("testsuite")
    cases = suite.findall("testcase")
    assert [c.get("name") for c in cases] == [c["id"] for c in CHARS]
    assert suite.get("tests") == "3" and suite.get("failures") == "1" and suite.get("skipped") == "1"
    failure = cases[1].find("failure")
    assert "measured 12.2000" in failure.get("message") and "limits [11.9500, 12.0500]" in failure.get("message")
    assert cases[2].find("skipped").get("message").startswith("circle-5.diameter: not measured")
    assert cases[0].find("failure") is None and cases[0].find("skipped") is None


def test_junit_never_empty():
    root = ET.fromstring(junit_xml(make_report([], verdict="inconclusive")))
    cases = root.iter("testcase")
    assert [c.find("skipped") is not None for c in cases] == [True]


def test_html_escapes_user_strings_and_puts_failures_first():
    nasty = '<script>alert("x")</script>'
    html = render_html(make_report([char("circle-3.diameter", "pass"), char(f"{nasty}.diameter", "fail", 12.2)], part=nasty))
    assert nasty not in html
    assert "&lt;script&gt;" in html
    assert html.index("&lt;script&gt;alert(&#34;x&#34;)&lt;/script&gt;.diameter") < html.index("circle-3.diameter")
    assert 'class="badge fail"' in html


def test_write_reports_atomic_and_replaces(tmp_path):
    write_reports(tmp_path, make_report(CHARS))
    first = (tmp_path / "report.json").read_text()
    write_reports(tmp_path, make_report(CHARS[:1], verdict="pass"))
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(REPORT_FILES)
    assert json.loads((tmp_path / "report.json").read_text())["verdict"] == "pass" != json.loads(first)["verdict"]


def test_failed_render_leaves_previous_reports(tmp_path):
    write_reports(tmp_path, make_report(CHARS))
    before = {n: (tmp_path / n).read_bytes() for n in REPORT_FILES}
    broken = make_report(CHARS)
    broken["characteristics"][0]["measured"] = float("nan")  # not JSON: must be refused
    with pytest.raises(ValueError):
        write_reports(tmp_path, broken)
    assert {n: (tmp_path / n).read_bytes() for n in REPORT_FILES} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(REPORT_FILES)


# --- JUnit schema, ordering, escaping, units, registration (synthetic run of tests/reports/synthetic.py)

import math  # noqa: E402

import xmlschema  # noqa: E402

from partinspect.reports.html import registration_summary, sort_characteristics, tolerance_bar  # noqa: E402
from tests.reports import synthetic  # noqa: E402

JUNIT_XSD = xmlschema.XMLSchema(str(resources.files("partinspect.reports").joinpath("schemas/junit.xsd")))


def test_junit_validates_against_the_xsd():
    nasty = 'a<b>&"c\'\x7f'
    reports = [
        synthetic.make_report(),
        make_report(CHARS),
        make_report([], verdict="inconclusive"),
        synthetic.make_report([synthetic.char(f"{nasty}.diameter", "fail", 12.2, reason=nasty)], part=nasty),
    ]
    for report in reports:
        JUNIT_XSD.validate(junit_xml(report))
    # The schema is not a rubber stamp: the old root's skipped count, a case without name, a word count are refused.
    for bad in ('<testsuites skipped="1"/>', '<testsuites><testsuite name="a" tests="1" failures="0" errors="0">'
                '<testcase classname="x"/></testsuite></testsuites>',
                '<testsuites><testsuite name="a" tests="one" failures="0" errors="0"/></testsuites>'):
        assert not JUNIT_XSD.is_valid(bad), bad


def test_junit_messages_carry_numbers_units_and_reasons():
    root = ET.fromstring(junit_xml(synthetic.make_report()))
    suite = root.find("testsuite")
    cases = {c.get("name"): c for c in suite.findall("testcase")}
    fail = cases["circle-3.diameter"].find("failure")
    assert fail.get("message").startswith("circle-3.diameter: measured 12.2100 +- 0.0100 (U, k=2), nominal 12.0000, "
                                          "limits [12.0000, 12.0500] mm: fail")
    assert "deviation +0.2100 mm" in fail.text and "tolerance from part.tol.yaml line 9" in fail.text
    skipped = cases["circle-3.position"].find("skipped").get("message")
    assert "measured 0.0950 +- 0.0120" in skipped and "straddles a specification limit" in skipped
    assert cases["circle-5.diameter"].find("skipped").get("message").startswith("circle-5.diameter: not measured;")
    assert "limits [89.5000, 90.5000] deg" in junit_xml(synthetic.make_report(
        [synthetic.char("line-1.angle", "fail", 91.0, 90.0, 89.5, 90.5, 0.04, unit="deg")]))
    props = {p.get("name"): p.get("value") for p in suite.find("properties")}
    assert props == {"verdict": "fail", "part": "part.step", "schema": "report/1"}
    assert suite.find("system-out").text.startswith("FAIL: 4 pass, 1 fail, 2 inconclusive of 7")
    assert root.get("skipped") is None and suite.get("skipped") == "2"


def test_characteristics_fail_first_then_inconclusive_then_pass_in_report_order():
    ordered = sort_characteristics(synthetic.CHARS)
    decisions = [c["decision"] for c in ordered]
    assert decisions == ["fail", "inconclusive", "inconclusive", "pass", "pass", "pass", "pass"]
    assert [c["id"] for c in ordered if c["decision"] == "pass"] == [
        c["id"] for c in synthetic.CHARS if c["decision"] == "pass"]
    html = render_html(synthetic.make_report())
    rows = re.findall(r'<tr class="(\w+)" data-decision="\w+">\s*<td><span class="mono id">([^<]+)</span>', html)
    assert [d for d, _ in rows] == decisions and [i for _, i in rows] == [c["id"] for c in ordered]


def test_every_user_string_is_escaped():
    nasty = '<script>alert("x")</script>'
    report = synthetic.make_report(part=nasty)
    report["inputs"][1]["path"] = f"/data/{nasty}/left.png"
    report["features"][0]["id"] = nasty
    report["features"][1]["reason"] = nasty
    report["characteristics"][0]["reason"] = nasty
    report["characteristics"][0]["rule"] = nasty
    report["tolerances"]["file"] = nasty
    report["registration"]["datums"] = [nasty]
    report["not_inspected"][0]["reason"] = nasty
    html = render_html(report)
    assert nasty not in html and "<script>alert" not in html
    assert html.count("&lt;script&gt;alert(&#34;x&#34;)&lt;/script&gt;") >= 9
    assert html.count("<script") == 1  # the report's own, hash-pinned by the page's CSP
    csp = re.search(r'http-equiv="Content-Security-Policy" content="([^"]+)"', html).group(1)
    rules = dict(d.strip().split(" ", 1) for d in csp.split(";"))
    assert rules["default-src"] == "'none'" and re.fullmatch(r"'sha256-[A-Za-z0-9+/]{43}='", rules["script-src"])


def test_angles_are_shown_in_degrees():
    from partinspect.tolerances.evaluate import Evaluation
    from partinspect.tolerances.resolve import Characteristic

    c = Characteristic("angle(line-1,line-2)", "angle", ("line-1", "line-2"), math.radians(90), math.radians(89.5),
                       math.radians(90.5), "spec", "part.tol.yaml line 20", unit="rad")
    d = Evaluation(c, math.radians(90.02), math.radians(0.02), math.radians(0.01), math.radians(0.02)).to_dict()
    d.update(decision="pass", reason=None)
    assert d["unit"] == "deg" and math.isclose(d["measured"], 90.02) and math.isclose(d["upper_limit"], 90.5)
    html = render_html(synthetic.make_report([d]))
    row = re.search(r'<tr class="pass".*?</tr>', html, flags=re.S).group(0)
    assert ">90.0200<" in row and "89.5000<br>90.5000" in row and ">deg<" in row and "+0.0200" in row
    jsonschema.validate(synthetic.make_report([d]), SCHEMA)


def test_tolerance_bar_places_the_measured_value_inside_or_outside_the_zone():
    def xs(svg):
        zone = [float(v) for v in re.findall(r'<line x1="([0-9.]+)" x2="\1" y1="2"', svg)]
        dot = float(re.search(r'<circle cx="([0-9.]+)"', svg).group(1)) if "<circle" in svg else None
        return zone, dot

    zone, dot = xs(str(tolerance_bar(synthetic.char("c.diameter", "pass", 12.01, 12.0, 11.95, 12.05, 0.006))))
    assert len(zone) == 2 and zone[0] < dot < zone[1]
    zone, dot = xs(str(tolerance_bar(synthetic.char("c.diameter", "fail", 12.2, 12.0, 11.95, 12.05, 0.01))))
    assert dot > zone[1]
    one_sided = str(tolerance_bar(synthetic.char("l.straightness", "pass", 0.004, 0.0, None, 0.02, 0.003)))
    zone, dot = xs(one_sided)
    assert len(zone) == 1 and dot < zone[0]
    unmeasured = str(tolerance_bar(synthetic.char("c.diameter", "inconclusive", None)))
    assert "not measured" in unmeasured and "<circle" not in unmeasured
    assert str(tolerance_bar({"decision": "pass", "nominal": None, "lower_limit": None, "upper_limit": None,
                              "measured": None})) == ""
    ET.fromstring(one_sided)  # well-formed


def test_registration_summary_and_section():
    s = registration_summary(synthetic.make_report()["registration"])
    assert math.isclose(s["rms"], 0.0042) and s["datums"] == ["line-1", "line-2", "circle-3"]
    assert math.isclose(s["rotation_deg"], 160.05, abs_tol=0.01) and s["translation"] == [-40.0, 25.0, 420.0]
    html = render_html(synthetic.make_report())
    assert 'id="registration"' in html and "0.0042 mm" in html and "χ² 12.60 on 11 degrees of freedom" in html
    assert registration_summary(None) is None
    assert 'id="registration"' not in render_html(synthetic.make_report(registration=False))


def test_synthetic_report_and_extended_schema():
    report = synthetic.make_report()
    jsonschema.validate(report, SCHEMA)
    jsonschema.Draft202012Validator.check_schema(SCHEMA)
    bad = synthetic.make_report()
    bad["not_inspected"][0].pop("reason")
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(bad, SCHEMA)
    bad = synthetic.make_report()
    bad["characteristics"][0]["unit"] = "rad"  # angles are reported in degrees
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(bad, SCHEMA)
    bad = synthetic.make_report()
    bad["registration"]["dof"] = -1
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(bad, SCHEMA)


def test_write_reports_with_figures_keeps_json_and_junit_unchanged(tmp_path):
    report = synthetic.make_report()
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    write_reports(tmp_path / "a", report)
    write_reports(tmp_path / "b", report, synthetic.make_figures(seed=5, width=612, height=512, n_pts=30))
    for name in ("report.json", "junit.xml"):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()
    assert 'id="fig-images"' in (tmp_path / "b" / "report.html").read_text()
    assert 'id="figures"' not in (tmp_path / "a" / "report.html").read_text()


def test_adaptive_rounds_and_advice_are_shown_escaped():
    report = synthetic.make_report()
    assert 'id="adaptive"' not in render_html(report)  # no section without adaptive data
    report["adaptive"] = {
        "rounds": [
            {"round": 1, "params": {"sigma": 1.0}, "kept": True,
             "situations": [{"name": "expected edges missing", "step": "matching", "detail": "<script>x</script> line-5"}]},
            {"round": 2, "params": {"sigma": 1.5}, "kept": False, "situations": [],
             "after": {"situation": "expected edges missing", "change": {"sigma": 1.5}}},
            {"round": 3, "params": {"sigma": 1.5, "min_points": 8}, "kept": True, "situations": [],
             "added": ["circle-3<i>"], "after": {"situation": "expected edges missing", "change": {"min_points": 8}}},
        ],
        "advice": [{"situation": "expected edges missing", "step": "matching", "detail": "line-5 missing",
                    "advice": "turn the part"}],
    }
    html = render_html(report)
    assert 'id="adaptive"' in html and "3 rounds" in html and "turn the part" in html
    assert "<script>x</script>" not in html and "&lt;script&gt;x&lt;/script&gt;" in html
    assert "added: circle-3&lt;i&gt;" in html  # what a re-run added to the kept features


def test_features_left_out_of_the_alignment_are_named_escaped_and_valid():
    report = synthetic.make_report()
    assert "left out of the alignment" not in render_html(report)
    report["registration"]["outliers"] = [{"feature": "line-4<b>", "chi2": 12222.238, "residuals": 4}]
    jsonschema.validate(report, SCHEMA)
    html = render_html(report)
    assert "left out of the alignment" in html and "(χ² 12222.2 on 4)" in html
    assert "line-4<b>" not in html and "line-4&lt;b&gt;" in html
    report["registration"]["outliers"] = [{"feature": "line-4", "chi2": -1.0, "residuals": 4}]
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(report, SCHEMA)


def test_registration_names_the_pmi_datums_it_used():
    report = synthetic.make_report()
    report["registration"]["datum_reference"] = {
        "source": "part.stp PMI datums A|B", "applied": True,
        "frame": [{"datum": "A", "features": ["line-1", "line-2", "line-9"], "fitted": ["line-1", "line-2"]},
                  {"datum": "B", "features": ["circle-3"], "fitted": ["circle-3"]}]}
    jsonschema.validate(report, SCHEMA)
    html = render_html(report)
    assert "datums from part.stp PMI datums A|B</span>" in html
    assert "A: line-1, line-2 (of 3); B: circle-3 (of 1)" in html
    report["registration"]["datum_reference"].update(applied=False, reason="they leave the pose free")
    for d in report["registration"]["datum_reference"]["frame"]:
        d["fitted"] = []
    html = render_html(report)
    assert "not applied: they leave the pose free" in html and "A: none measured (of 3)" in html
    report["registration"]["datum_reference"].pop("applied")
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(report, SCHEMA)


def test_features_measured_on_a_broken_edge_say_where_escaped_and_valid():
    report = make_report(CHARS)
    circle, line = report["features"]
    line["measured"] = {"point": [5, 0, 0], "direction": [1, 0, 0], "start": [0, 0, 0], "end": [10, 0, 0],
                        "covariance": [[1e-6, 0, 0], [0, 1e-6, 0], [0, 0, 1e-6]]}
    line.pop("reason")
    line["status"] = "measured"
    circle["edge_break"] = {"measured_at": "predicted band place", "break_size": 0.1, "band_place": 0.31,
                            "band_place_standard_uncertainty": 0.15, "offset": 0.031,
                            "offset_px": [[-0.41, 0.36], None], "standard_uncertainty": 0.0163,
                            "band_standard_uncertainty": 0.08165}
    line["edge_break"] = {"measured_at": "apparent edge", "break_size": 0.1, "offset": -0.0837,
                          "offset_px": [[-0.38, -0.35], [-0.44, -0.43]], "towards_face": "face-<1>",
                          "standard_uncertainty": 0.08165, "reason": "its place is <b>predicted</b> no better"}
    jsonschema.validate(report, SCHEMA)
    html = render_html(report)
    rows = re.findall(r'<div class="sub small edge-break">(.*?)</div>', html)
    assert len(rows) == 2
    moved, kept = rows if "moved" in rows[0] else rows[::-1]
    assert "moved onto the sharp edge by its predicted band place" in moved
    assert "+0.0310 mm" in moved and "left -0.41 to 0.36 px" in moved and "right" not in moved
    assert "band place 0.31 ± 0.15" in moved and "Type B 0.0163 mm per point (the whole band&#39;s 0.0817)" in moved
    assert "measured at the apparent edge, the band carried as Type B 0.0817 mm per point" in kept
    assert "−0.0837 mm from the sharp edge towards face-&lt;1&gt;" in kept
    assert "&lt;b&gt;predicted&lt;/b&gt;" in kept and "<b>predicted" not in html and "face-<1>" not in html
    for bad in ({"measured_at": "moved", "standard_uncertainty": 0.01},
                {"measured_at": "apparent edge", "standard_uncertainty": -0.01},
                {"measured_at": "predicted band place", "standard_uncertainty": 0.01, "band_place": 1.5}):
        circle["edge_break"] = bad
        with pytest.raises(jsonschema.ValidationError):
            jsonschema.validate(report, SCHEMA)
    circle.pop("edge_break")
    line["edge_break"] = {"measured_at": "apparent edge", "standard_uncertainty": 0.08}
    assert len(re.findall('class="sub small edge-break"', render_html(report))) == 1
