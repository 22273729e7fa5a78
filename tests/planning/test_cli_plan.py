"""`inspect plan` at the command line: outputs, exit codes, bad input."""

import json
import subprocess
import sys

import pytest

from partinspect.cli import main
from tests.planning.conftest import REPO, SIZE, view_pose

PLATE = REPO / "examples" / "plate" / "part.step"


@pytest.fixture(scope="module")
def rig_file(tmp_path_factory):
    from partinspect.simulate.rig import default_rig
    from partinspect.vision.calibration import write_calibration

    path = tmp_path_factory.mktemp("rig") / "calibration.yaml"
    write_calibration(path, default_rig(SIZE))
    return path


def test_help_imports_nothing_heavy():
    code = ("import sys\nfrom partinspect.cli import main\ntry:\n    main(['plan', '--help'])\nexcept SystemExit:\n    pass\n"
            "print(sorted(m for m in ('cv2', 'embreex', 'cadquery', 'OCP', 'scipy') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert "--rig" in out and "--ratio" in out
    assert out.strip().splitlines()[-1] == "[]"


@pytest.mark.parametrize("args, needle", [
    (["missing.step", "--rig", "RIG"], "missing.step: STEP file not found"),
    (["PLATE", "--rig", "nowhere.yaml"], "nowhere.yaml: calibration file not found"),
    (["PLATE", "--rig", "RIG", "--ratio", "0"], "--ratio must be a number in (0, 1]"),
    (["PLATE", "--rig", "RIG", "--pose", "1,2"], "--pose: expected RX,RY,RZ"),
    (["PLATE", "--rig", "RIG", "--pose", "nowhere.json"], "nowhere.json: pose file not found"),
    (["PLATE", "--rig", "RIG", "--noise", "-1"], "--noise must be a positive number"),
    (["PLATE", "--rig", "RIG", "--tolerances", "none.yaml"], "none.yaml: tolerance file not found"),
    (["PLATE", "--rig", "RIG", "--check", "2"], "--check must be 0 (no check) or at least 3 draws"),
    (["PLATE", "--rig", "RIG", "--check", "3", "--contrast", "50"], "cannot honour a fixed --contrast"),
])
def test_bad_input_is_one_line_and_exit_2(args, needle, rig_file, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    args = [str(PLATE) if a == "PLATE" else str(rig_file) if a == "RIG" else a for a in args]
    assert main(["plan", *args, "-o", str(tmp_path / "out"), "--no-search"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and needle in err, err
    assert not (tmp_path / "out").exists()


def test_plan_names_the_spoiled_characteristic(rig_file, tmp_path, capsys, plate, rig):
    """A render's truth.json as --pose: the front edge along the epipolar lines is named, exit 3."""
    import numpy as np

    pose = tmp_path / "truth.json"
    pose.write_text(json.dumps({"part_to_camera": view_pose(plate, rig, 45.0, 270.0, 0.0).tolist()}))
    out = tmp_path / "plan"
    code = main(["plan", str(PLATE), "--rig", str(rig_file), "--pose", str(pose), "--no-search", "--ratio", "1",
                 "-o", str(out)])
    assert code == 3
    text = capsys.readouterr().out
    line = next(l for l in text.splitlines() if l.startswith("  front-top-edge.straightness:"))
    assert "line-5 runs" in line and "epipolar lines" in line
    data = json.loads((out / "plan.json").read_text())
    assert data["schema"] == "plan/1" and data["start"]["decidable"] == data["best"]["decidable"]
    c = {c["id"]: c for c in data["start"]["characteristics"]}
    assert c["front-top-edge.straightness"]["expanded_uncertainty"] is None
    assert c["circle-4.diameter"]["decidable"] and 0 < c["circle-4.diameter"]["expanded_uncertainty"] < 0.05
    html = (out / "plan.html").read_text()
    assert "front-top-edge.straightness" in html and "epipolar" in html and "<script" not in html
    best = json.loads((out / "best_pose.json").read_text())
    assert np.allclose(best["part_to_camera"], json.loads(pose.read_text())["part_to_camera"])


def test_check_sets_the_prediction_beside_rendered_draws(rig_file, tmp_path, capsys):
    """--check: the proposed pose rendered and measured; U grows only where the spread is beyond chance."""
    import numpy as np

    out = tmp_path / "plan"
    code = main(["plan", str(PLATE), "--rig", str(rig_file), "--no-search", "--check", "3", "--seed", "4",
                 "-o", str(out)])
    text = capsys.readouterr().out
    assert "check of the proposed pose on 3 rendered noise draws (noise 2, seed 4" in text
    data = json.loads((out / "plan.json").read_text())
    chk = data["check"]
    assert chk["draws"] == 3 and chk["seed"] == 4 and not chk["failed"]
    start = {c["id"]: c for c in data["start"]["characteristics"]}
    assert [c["id"] for c in chk["characteristics"]] == list(start)
    ratios = []
    for c in chk["characteristics"]:
        s = start[c["id"]]
        if s["expanded_uncertainty"] is None:
            assert c["verdict"] == "not predicted measurable" and not c["decidable"]
            continue
        if c["verdict"] == "prediction low":
            assert c["expanded_uncertainty"] > s["expanded_uncertainty"]
            assert c["measured_spread"] / c["predicted_noise_u"] > c["chance_interval"][1]
        else:
            assert c["expanded_uncertainty"] == pytest.approx(s["expanded_uncertainty"])
        if c["decidable"]:
            assert s["decidable"] and c["measured_draws"] == 3 and c["ratio"] <= 0.25
        if c["measured_spread"] is not None and c["id"].endswith((".diameter", ".straightness")):
            ratios.append(c["measured_spread"] / c["predicted_noise_u"])
    # Three draws know a spread to +-50 %; the median over the characteristics much better.
    assert len(ratios) >= 10 and 0.5 < np.median(ratios) < 2.0, np.round(ratios, 2)
    assert data["all_decidable"] == chk["all_decidable"] and code == (0 if chk["all_decidable"] else 3)
    html = (out / "plan.html").read_text()
    assert 'id="check"' in html and "<script" not in html


def test_plan_uses_the_pmi_when_no_spec_is_given(rig_file, tmp_path, capsys):
    """NIST CTC 01: the hole's PMI diameter 35 +0/-0.2 mm is the plan's limit (ISO 2768-m would give +-0.3)."""
    from partinspect.cad.features import inventory
    from partinspect.cad.step import load_step
    from partinspect.tolerances.from_pmi import load_pmi_spec

    ctc01 = REPO / "tests" / "data" / "step" / "nist_ctc_01_asme1_ap242-e1.stp"
    out = tmp_path / "plan"
    code = main(["plan", str(ctc01), "--rig", str(rig_file), "--no-search", "-o", str(out)])
    assert code in (0, 3)
    data = json.loads((out / "plan.json").read_text())
    _, ps = load_pmi_spec(ctc01, inventory(load_step(ctc01)))
    c = {c["id"]: c for c in data["start"]["characteristics"]}
    rims = ps.applies_to["dim-4"]
    assert len(rims) == 2 and all(c[f"{r}.diameter"]["tolerance"] == pytest.approx(0.2) for r in rims)
    assert [n["item"] for n in data["not_evaluated"]] == [n.item for n in ps.not_evaluated]
    assert "PMI" in (out / "plan.html").read_text()
    err = capsys.readouterr().err
    assert f"inspect: {ctc01.name} PMI: {len(ps.not_evaluated)} items not evaluated (" in err
    assert err.rstrip().endswith("reasons in plan.json")
