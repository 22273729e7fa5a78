"""A part whose measured features are symmetric and whose CAD model is not: judged where it can be.

Issue 46's flange with a clocking hole drilled into its underside: the
cameras above see a bolt circle of six like holes, a hub and a bore, all
symmetric under turns of 60 degrees, so six poses explain them equally
well, and only the unseen hole would tell which. Which bolt hole is which
is unknown, so their characteristics are inconclusive; the disc, hub and
bore are the same edges under every pose and are judged.
"""

import json
from importlib import resources

import jsonschema
import pytest

from partinspect.cli import main

SCHEMA = json.loads(resources.files("partinspect.reports").joinpath("schemas/report-1.schema.json").read_text())

TOLERANCES = """\
units: mm
general: ISO2768-mK
features:
  circle-11:
    position: {tolerance: 0.3}
  circle-2:
    position: {tolerance: 0.3}
distances:
  - {between: [circle-2, circle-20], upper: 0.1, lower: -0.1}
  - {between: [circle-11, circle-9], upper: 0.1, lower: -0.1}
"""


@pytest.fixture(scope="module")
def clocked_flange(tmp_path_factory):
    """The flange with a 5 mm clocking hole 5 mm deep underneath, rendered at a quarter size, noise 2."""
    from partinspect.simulate.folder import render_to_folder
    from partinspect.simulate.parts import flange, write_part

    d = tmp_path_factory.mktemp("clocked")
    write_part(flange(clocking=(5.0, 5.0)), d / "part.step")
    (d / "part.tol.yaml").write_text(TOLERANCES)
    render_to_folder(d / "part.step", d, image_size=(612, 512), noise=2.0, seed=7)
    out = d / "out"
    code = main([str(d / "part.step"), str(d / "images"), "-o", str(out), "-q"])
    return code, json.loads((out / "report.json").read_text()), (out / "report.html").read_text()


def test_the_run_goes_on_and_only_what_depends_on_the_pose_is_inconclusive(clocked_flange):
    code, report, html = clocked_flange
    jsonschema.validate(report, SCHEMA)
    # Nothing fails on the nominal part; the ambiguous ones make it inconclusive, not a pass (it stopped with 2).
    assert code == 3 and report["verdict"] == "inconclusive"
    amb = report["registration"]["ambiguity"]
    assert len(amb["competing"]) == 5
    assert sorted(round(c["angle_deg"]) for c in amb["competing"]) == [60, 60, 120, 120, 180]
    # The clocking hole's two rims would tell, and neither was measured.
    assert amb["deciding_features"] == ["circle-17", "circle-18"]
    measured = {f["id"] for f in report["features"] if f["measured"] is not None}
    assert not measured & {"circle-17", "circle-18"}
    assert all("it would tell which of the poses that fit is right" in f["reason"] for f in report["features"]
               if f["id"] in ("circle-17", "circle-18"))
    bolts = {f"circle-{k}" for k in (2, 4, 6, 14, 16, 20)}  # the bolt holes' top rims
    central = {"circle-8", "circle-9", "circle-10", "circle-11"}  # disc, hub foot, bore top rim
    for c in amb["competing"]:
        assert set(c["assignment_differs"]) <= bolts and not set(c["assignment_differs"]) & central

    by_id = {c["id"]: c for c in report["characteristics"]}
    ambiguous = {cid for cid, c in by_id.items() if c["decision_reason"].startswith("depends on which of 6 poses (")}
    assert ambiguous, by_id
    for cid in ambiguous:
        c = by_id[cid]
        assert c["decision"] == "inconclusive" and c["measured"] is not None
        assert ("the measured features are symmetric, the CAD model is not (circle-17, circle-18, which would tell, "
                "were not measured)") in c["reason"]
        assert set(c["features"]) & bolts, cid
        assert len(c["details"]["ambiguity"]) == 6
    # Every bolt hole's characteristic depends on the pose, the distance between two of them and a position too.
    assert {c["id"] for c in report["characteristics"] if set(c["features"]) & bolts and c["measured"] is not None} \
        == ambiguous
    assert {"circle-2.diameter", "circle-2.position", "distance(circle-2,circle-20)"} <= ambiguous
    # The disc's, hub's and bore's characteristics are judged: the bore's position agrees across the poses,
    # as does the distance between two edges on the axis.
    judged = {cid for cid, c in by_id.items() if c["decision"] in ("pass", "fail")}
    assert {"circle-8.diameter", "circle-9.diameter", "circle-10.diameter", "circle-11.diameter",
            "circle-11.position", "distance(circle-11,circle-9)"} <= judged
    assert all(by_id[cid]["decision"] == "pass" for cid in judged)
    assert not {cid for cid in judged if set(by_id[cid]["features"]) & bolts}
    # The report's registration section shows it.
    assert "pose ambiguous" in html and "competing pose 5" in html and "circle-17, circle-18" in html


def test_a_view_of_a_views_folder_whose_pose_is_ambiguous_is_left_out(tmp_path, capsys):
    """Fusion places each view's features by one pose: an ambiguous view is left out, saying why
    (both views here, so the run stops as before, with one line)."""
    from partinspect.simulate.folder import render_views_to_folder
    from partinspect.simulate.parts import flange, write_part

    write_part(flange(clocking=(5.0, 5.0)), tmp_path / "part.step")
    render_views_to_folder(tmp_path / "part.step", tmp_path / "views", [(0, 0, 0), (0, 0, 90)],
                           image_size=(612, 512), noise=2.0, seed=7)
    capsys.readouterr()
    code = main([str(tmp_path / "part.step"), str(tmp_path / "views"), "-o", str(tmp_path / "out"), "-q"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1, err
    assert "view-1: cannot align the CAD model to the images: alignment is ambiguous: 6 poses" in err
    assert "(a view is fused under one pose)" in err
