"""inspect batch on the bundled examples: reports, database rows, exit codes, resume, and a Dask cluster.

Each inspection takes tens of seconds on this machine: the module runs two
(in parallel, on two workers) and resumes one on a local Dask cluster.
"""

import json
import shutil

import pytest
import sqlalchemy as sa

from partinspect.cli import main

pytestmark = pytest.mark.timeout(600)


def _table(path, query):
    engine = sa.create_engine(f"sqlite:///{path}")
    with engine.connect() as conn:
        rows = [tuple(r) for r in conn.execute(sa.text(query))]
    engine.dispose()
    return rows


@pytest.fixture(scope="module")
def batch(repo, tmp_path_factory):
    root = tmp_path_factory.mktemp("batch")
    broken = root / "broken"
    broken.mkdir()
    shutil.copy(repo / "examples" / "plate" / "images" / "calibration.yaml", broken)
    shutil.copy(repo / "examples" / "plate" / "images" / "left.png", broken)   # no right.png
    ex = repo / "examples"
    manifest = root / "line.csv"
    manifest.write_text(
        "serial,step,images,time\n"
        f"P-001,{ex}/plate/part.step,{ex}/plate/images,2026-03-01T08:00:00\n"
        f"B-001,{ex}/bracket/part.step,{ex}/bracket/images,2026-03-01T08:05:00\n"
        f"P-002,{ex}/plate/part.step,broken,2026-03-01T08:10:00\n"
        f"X-001,{ex}/nothing/part.step,{ex}/plate/images,\n")
    out = root / "out"
    import contextlib
    import io

    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        code = main(["batch", str(manifest), "-o", str(out), "--workers", "2", "-q"])
    return {"root": root, "manifest": manifest, "out": out, "code": code, "stderr": err.getvalue()}


def test_every_part_gets_its_report_and_its_rows(batch):
    out, db = batch["out"], batch["out"] / "results.sqlite"
    parts = {r[0]: r[1:] for r in _table(db, "SELECT serial, status, exit_code, verdict, step_sha256, left_sha256 FROM parts")}
    assert set(parts) == {"P-001", "B-001", "P-002"}
    for serial in ("P-001", "B-001"):
        report = json.loads((out / serial / "report.json").read_text())
        status, code, verdict, step_sha, left_sha = parts[serial]
        assert (status, verdict) == ("done", report["verdict"]) and code == {"pass": 0, "fail": 1, "inconclusive": 3}[verdict]
        assert step_sha == next(i["sha256"] for i in report["inputs"] if i["role"] == "part")
        assert left_sha == next(i["sha256"] for i in report["inputs"] if i["role"] == "left image")
        rows = _table(db, "SELECT c.characteristic, c.measured, c.expanded_uncertainty, c.decision FROM characteristics c "
                          f"JOIN parts p ON p.id = c.part_id WHERE p.serial = '{serial}' ORDER BY c.characteristic")
        assert rows == sorted((c["id"], c["measured"], c["expanded_uncertainty"], c["decision"])
                              for c in report["characteristics"])
    assert parts["P-002"][:3] == ("failed", 2, None) and not (out / "P-002").exists()


def test_bad_lines_and_failed_parts_are_one_line_each_and_the_batch_exits_2(batch):
    assert batch["code"] == 2
    lines = batch["stderr"].splitlines()
    assert lines[0].startswith(f"inspect batch: {batch['manifest']}:5: STEP file ")
    assert lines[0].endswith("nothing/part.step not found")
    assert any(line.startswith("inspect batch: P-002: could not be run: ") and "right.png" in line for line in lines)
    assert len(lines) == 2


def test_the_batch_writes_its_spc_page(batch):
    out = batch["out"]
    html = (out / "spc.html").read_text()
    assert "Plotly.newPlot" in html and "plate/part.step: circle-4.diameter" in html
    assert (out / "spc.csv").read_text().count("\n") > 40


def test_resume_on_a_dask_cluster_redoes_only_the_unfinished_part_identically(batch):
    """A part whose transaction never happened (killed mid-way) is redone, on a local Dask cluster, alone."""
    from distributed import LocalCluster

    db = batch["out"] / "results.sqlite"
    query = ("SELECT p.serial, c.characteristic, c.measured, c.standard_uncertainty, c.decision FROM characteristics c "
             "JOIN parts p ON p.id = c.part_id WHERE p.status = 'done' ORDER BY p.serial, c.characteristic")
    before = _table(db, query)
    kept = _table(db, "SELECT id, serial FROM parts WHERE serial = 'B-001'")
    engine = sa.create_engine(f"sqlite:///{db}")
    with engine.begin() as conn:
        pid = conn.execute(sa.text("SELECT id FROM parts WHERE serial = 'P-001'")).scalar_one()
        conn.execute(sa.text(f"DELETE FROM characteristics WHERE part_id = {pid}"))
        conn.execute(sa.text(f"DELETE FROM parts WHERE id = {pid}"))
    engine.dispose()
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=None) as cluster:
        code = main(["batch", str(batch["manifest"]), "-o", str(batch["out"]), "--resume", "-q",
                     "--scheduler", cluster.scheduler_address])
    assert code == 2  # P-002 still cannot be run, X-001 still has no STEP file
    assert _table(db, query) == before                       # the same numbers from the cluster
    assert _table(db, "SELECT id, serial FROM parts WHERE serial = 'B-001'") == kept   # not redone
    assert _table(db, "SELECT count(*) FROM parts") == [(3,)]
    assert _table(db, "SELECT count(*) FROM batches") == [(1,)]
    workers = _table(db, "SELECT serial, worker FROM parts ORDER BY serial")
    assert len({w for _, w in workers}) >= 2  # P-001 ran elsewhere than in the first run


def test_the_batch_exit_code_rule_and_resumed_parts():
    from partinspect.production.batch import BatchResult, batch_exit_code

    assert [batch_exit_code(c) for c in ([0, 0], [0, 3], [3, 1, 0], [1, 2], [])] == [0, 3, 1, 2, 0]
    assert batch_exit_code([0], problems=1) == 2
    # A resumed batch's code covers the parts done before the interruption.
    assert BatchResult(records=[{"exit_code": 0}], skipped={"S1": 1}).exit_code == 1
    assert BatchResult(records=[], skipped={"S1": 3, "S2": 0}).exit_code == 3


def test_a_worker_computes_on_its_share_of_the_cpus(monkeypatch):
    """Two workers on two CPUs: one OpenCV thread each, no forked second process, BLAS pools of one thread."""
    import os
    import subprocess
    import sys

    from partinspect.production.batch import THREAD_VARIABLES, _environment

    code = ("from partinspect.production.worker import share_cpus; share_cpus(1); import cv2; "
            "from partinspect.vision import forked; print(cv2.getNumThreads(), forked.ENABLED, forked.can_fork())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["1", "False", "False"]
    monkeypatch.delenv("OPENBLAS_NUM_THREADS", raising=False)
    monkeypatch.setenv("OMP_NUM_THREADS", "3")  # the user's own setting stays
    with _environment({v: "1" for v in THREAD_VARIABLES}):
        assert os.environ["OPENBLAS_NUM_THREADS"] == "1" and os.environ["OMP_NUM_THREADS"] == "3"
    assert "OPENBLAS_NUM_THREADS" not in os.environ and os.environ["OMP_NUM_THREADS"] == "3"
