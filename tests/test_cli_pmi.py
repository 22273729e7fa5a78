"""`inspect features --pmi` and `inspect spec` (NIST CTC 01, and a part without PMI)."""

from pathlib import Path

import pytest

from partinspect.cli import main
from partinspect.tolerances.spec import load_spec

REPO = Path(__file__).resolve().parents[1]
CTC_01 = REPO / "tests" / "data" / "step" / "nist_ctc_01_asme1_ap242-e1.stp"
PLATE = REPO / "examples" / "plate" / "part.step"


def test_features_pmi_lists_items_and_their_features(capsys):
    assert main(["features", str(CTC_01), "--pmi"]) == 0
    out = capsys.readouterr().out
    # ctc_01: 12 semantic dimensions, 6 tolerances, datums A B C (tests/cad/test_pmi.py says where from).
    assert "12 dimensions, 6 geometric tolerances, 3 datums" in out
    row = next(line for line in out.splitlines() if line.startswith("dim-4 "))
    assert "diameter 35 +0/-0.2 mm" in row and "circle-" in row
    assert "not evaluated: a surface profile" in out


def test_features_pmi_without_pmi(capsys):
    assert main(["features", str(PLATE), "--pmi"]) == 0
    assert "no semantic PMI" in capsys.readouterr().out


def test_spec_writes_a_spec_that_loads_back(tmp_path, capsys):
    out = tmp_path / "part.tol.yaml"
    assert main(["spec", str(CTC_01), "-o", str(out)]) == 0
    assert "wrote" in capsys.readouterr().out
    spec = load_spec(out)
    text = out.read_text()
    # The diameters of the PMI are in it, each with its PMI item named in a comment.
    diam = {k: v.diameter for k, v in spec.features.items() if v.diameter is not None}
    assert len(diam) == 14 and sum((d.upper, d.lower) == (0.0, -0.2) for d in diam.values()) == 2
    assert "PMI dim-4 (diameter 35 +0/-0.2 mm" in text
    assert "# not evaluated by edge measurement:" in text and "gtol-3 (profile_of_surface)" in text
    assert "PMI datum(s) A." in text and spec.datums  # ctc_01: only A is attached to a face
    assert list(tmp_path.iterdir()) == [out]  # atomic: no temporary left


def test_spec_without_pmi_is_refused(tmp_path, capsys):
    out = tmp_path / "x.yaml"
    assert main(["spec", str(PLATE), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "part.step" in err[0] and "no semantic PMI" in err[0]
    assert not out.exists()


@pytest.mark.parametrize("where", ["missing/dir/x.yaml", "step"])
def test_spec_bad_output(tmp_path, capsys, where):
    target = tmp_path / where if where != "step" else tmp_path / "copy.stp"
    if where == "step":
        target.write_bytes(CTC_01.read_bytes())
    before = target.read_bytes() if target.exists() else None
    assert main(["spec", str(target if where == "step" else CTC_01), "-o", str(target)]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
    assert (target.read_bytes() if target.exists() else None) == before


def test_report_lists_pmi_not_evaluated_escaped():
    from partinspect.reports.html import render_html
    from tests.reports.synthetic import make_report

    report = make_report()
    report["tolerances"] = dict(report.get("tolerances") or {}, file=None, general="ISO 2768-mK",
                                decision_rule="iso14253",
                                not_evaluated=[{"item": "gtol-3", "type": "profile_of_surface",
                                                "reason": "a surface profile <needs> the surface"}])
    html = render_html(report)
    assert 'id="not-evaluated"' in html and "gtol-3" in html
    assert "&lt;needs&gt;" in html and "<needs>" not in html
    del report["tolerances"]["not_evaluated"]
    assert 'id="not-evaluated"' not in render_html(report)


def test_pmi_problems_line():
    from partinspect.cad.features import inventory
    from partinspect.cad.step import load_step
    from partinspect.tolerances.from_pmi import NotEvaluated, load_pmi_spec
    from partinspect.tolerances.pmi_text import pmi_problems_line

    path = CTC_01.with_name("nist_ctc_03_asme1_ap242-e2.stp")
    _, ps = load_pmi_spec(path, inventory(load_step(path)))
    line = pmi_problems_line(path.name, ps.not_evaluated)
    # ctc_03: 16 items not evaluated, the per-area flatness OCCT drops among them
    assert line.startswith(f"{path.name} PMI: 16 items not evaluated (1 not read by OCCT; ")
    assert "3 profile of surface" in line and line.endswith("reasons in report.json")
    assert pmi_problems_line("p.stp", []) is None
    broken = NotEvaluated("p.stp", "PMI", "the PMI could not be used (boom); the spec and ISO 2768 apply instead")
    assert pmi_problems_line("p.stp", [broken]) == f"p.stp: {broken.reason}"


@pytest.mark.parametrize("quiet", [False, True])
def test_inspect_sums_up_pmi_problems_on_stderr(quiet, tmp_path, capsys, monkeypatch):
    import partinspect.pipeline as pipeline

    summary = {"pass": 1, "fail": 0, "inconclusive": 0, "characteristics": 1, "features_measured": 1, "features": 1}
    report = {"verdict": "pass", "summary": summary, "tolerances": {"not_evaluated": [
        {"item": "gtol-3", "type": "profile_of_surface", "reason": "a surface profile needs the surface"},
        {"item": "gtol-4", "type": "profile_of_surface", "reason": "a surface profile needs the surface"},
        {"item": "Flatness.1", "type": "flatness", "reason": "not read by OCCT (the file's FLATNESS_TOLERANCE)"}]}}
    monkeypatch.setattr(pipeline, "run_inspection",
                        lambda *a, **k: pipeline.InspectionResult("pass", report, tmp_path / "out"))
    code = main([str(CTC_01), str(tmp_path), "-o", str(tmp_path / "out")] + (["--quiet"] if quiet else []))
    assert code == 0
    err = capsys.readouterr().err
    if quiet:
        assert "PMI" not in err
    else:
        assert err.strip().splitlines() == [f"inspect: {CTC_01.name} PMI: 3 items not evaluated (1 not read by OCCT; "
                                            "2 profile of surface); reasons in report.json"]
