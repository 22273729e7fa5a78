"""Where a run's time goes: stages in order, added up when entered again, in report.json and on --timings."""

import json
import time

from partinspect.cli import main
from partinspect.timings import Timings


def test_stages_add_up_in_run_order():
    t = Timings()
    for name in ("a", "b", "a"):
        with t.stage(name):
            time.sleep(0.02)
    d = t.to_dict()
    assert [s["stage"] for s in d["stages"]] == ["a", "b"]
    a, b = (s["seconds"] for s in d["stages"])
    # Lower bounds only: a sleep never ends early, but a loaded machine may wake it late.
    assert a >= 0.04 - 1e-3 and b >= 0.02 - 1e-3
    assert d["total_seconds"] >= a + b - 0.002
    assert t.table().splitlines()[-1].startswith("total")


def test_a_stage_that_raises_is_still_timed():
    t = Timings()
    try:
        with t.stage("x"):
            raise ValueError
    except ValueError:
        pass
    assert "x" in t.seconds


def test_run_records_its_stages_and_prints_them_on_request(repo, tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("SOURCE_DATE_EPOCH", raising=False)
    out = tmp_path / "out"
    code = main([str(repo / "examples/plate/part.step"), str(repo / "examples/plate/images"), "-o", str(out),
                 "--quiet", "--timings"])
    assert code in (0, 1, 3)
    report = json.loads((out / "report.json").read_text())
    stages = {s["stage"]: s["seconds"] for s in report["timings"]["stages"]}
    for name in ("loading the CAD model", "measuring the images", "registering", "visibility", "evaluating", "report"):
        assert stages[name] > 0
    assert sum(stages.values()) <= report["timings"]["total_seconds"]
    err = capsys.readouterr().err.splitlines()
    assert err[-1].startswith("total") and any(line.startswith("measuring the images") for line in err)


def test_reproducible_reports_leave_the_timings_out(repo, tmp_path, monkeypatch):
    from partinspect.reports.assemble import with_timings

    monkeypatch.setenv("SOURCE_DATE_EPOCH", "0")
    assert "timings" not in with_timings({"a": 1}, Timings())
    monkeypatch.delenv("SOURCE_DATE_EPOCH")
    assert "timings" in with_timings({"a": 1}, Timings())
