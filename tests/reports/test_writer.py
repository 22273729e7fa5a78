"""report.json against its schema, junit.xml structure, HTML escaping, atomic writes."""

import json
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
