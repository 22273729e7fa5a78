"""inspect batch --refine-rig: each part refined as a single ``inspect --refine-rig`` run refines it.

One half-size plate rendered with its right camera rolled by 1 px after
calibration, inspected three times (a batch with and without the option,
and the single run), each some seconds.
"""

import contextlib
import io
import json
import shutil

import pytest
import sqlalchemy as sa

from partinspect.cli import main

pytestmark = pytest.mark.timeout(600)


def _parts(db):
    engine = sa.create_engine(f"sqlite:///{db}")
    with engine.connect() as conn:
        rows = {r[0]: tuple(r[1:]) for r in conn.execute(sa.text("SELECT serial, status, rig_refined, error FROM parts"))}
    engine.dispose()
    return rows


@pytest.fixture(scope="module")
def rolled(repo, tmp_path_factory):
    """A half-size plate pair whose calibration.yaml states the rig before a 1 px roll, and a manifest of it
    beside a views folder (which cannot be refined)."""
    root = tmp_path_factory.mktemp("refine")
    step = repo / "examples" / "plate" / "part.step"
    assert main(["render", str(step), str(root / "render"), "--size", "1224x1024", "--seed", "5",
                 "--drift", "roll=1", "-q"]) == 0
    shutil.copytree(root / "render" / "images", root / "views" / "view-1")
    manifest = root / "line.csv"
    manifest.write_text(f"serial,step,images\nP-1,{step},render/images\nV-1,{step},views\n")
    return step, root, manifest


def _batch(manifest, out, *more):
    out_text, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out_text), contextlib.redirect_stderr(err):
        code = main(["batch", str(manifest), "-o", str(out), "--workers", "1", *more])
    return code, out_text.getvalue(), err.getvalue()


def test_a_batch_refines_the_rig_as_a_single_run_does_and_records_it(rolled, tmp_path):
    step, root, manifest = rolled
    code, out, err = _batch(manifest, tmp_path / "refined", "--refine-rig")
    assert code == 2  # the views folder could not be run
    parts = _parts(tmp_path / "refined" / "results.sqlite")
    assert parts["P-1"][:2] == ("done", 1)
    assert parts["V-1"][:2] == ("failed", None) and "--refine-rig" in parts["V-1"][2] and "views folder" in parts["V-1"][2]
    assert "rig refined from the part in 1 of 1" in out
    batch = json.loads((tmp_path / "refined" / "P-1" / "report.json").read_text())
    rr = batch["rig_refinement"]
    assert rr["refined"] and rr["significant"] and "rz" in {p["name"] for p in rr["parameters"]}
    assert batch["uncertainty"]["calibration"]["refined_rig"]

    single = tmp_path / "single"
    assert main([str(step), str(root / "render" / "images"), "-o", str(single), "-q", "--refine-rig"]) in (0, 1, 3)
    alone = json.loads((single / "report.json").read_text())
    assert rr == alone["rig_refinement"]
    assert ([(c["id"], c["measured"], c["expanded_uncertainty"], c["decision"]) for c in batch["characteristics"]]
            == [(c["id"], c["measured"], c["expanded_uncertainty"], c["decision"]) for c in alone["characteristics"]])


def test_without_the_option_a_batch_does_not_refine_and_says_nothing_of_it(rolled, tmp_path):
    _, _, manifest = rolled
    code, out, _ = _batch(manifest, tmp_path / "plain")
    parts = _parts(tmp_path / "plain" / "results.sqlite")
    assert parts["P-1"][:2] == ("done", None) and parts["V-1"][1] is None
    assert "rig refined" not in out
    assert "rig_refinement" not in json.loads((tmp_path / "plain" / "P-1" / "report.json").read_text())
