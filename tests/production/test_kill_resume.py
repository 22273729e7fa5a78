"""`inspect batch` killed mid-way (SIGKILL, then Ctrl-C) and resumed: no finished part lost, none duplicated.

A real process group is needed: the signal comes from the kernel, and a
killed batch's workers die with it. The batch runs four parts of the
bundled plate (its one image pair under three serials, so nothing is
rendered) on two workers; the test waits until the database records a
finished part, signals the group, then runs ``--resume`` and compares the
database and the report folders with what the killed run left.
"""

import hashlib
import json
import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.timeout(600)

REPO = Path(__file__).resolve().parents[2]
PLATE = REPO / "examples" / "plate"
N = 3
REPORT_FILES = {"report.json", "report.html", "junit.xml"}


@pytest.fixture(scope="module")
def manifest(tmp_path_factory):
    path = tmp_path_factory.mktemp("kill") / "line.csv"
    path.write_text("serial,step,images\n" + "".join(
        f"K-{i:03d},{PLATE / 'part.step'},{PLATE / 'images'}\n" for i in range(1, N + 1)))
    return path


def _batch(manifest, out, *extra):
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    env.pop("PARTINSPECT_DEBUG", None)
    return subprocess.Popen([sys.executable, "-m", "partinspect", "batch", str(manifest), "-o", str(out),
                             "--workers", "2", *extra], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=REPO, env=env, start_new_session=True)


def _query(db, sql):
    con = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=30)
    try:
        return con.execute(sql).fetchall()
    finally:
        con.close()


def _done(db):
    try:
        return _query(db, "SELECT count(*) FROM parts WHERE status = 'done'")[0][0]
    except sqlite3.Error:  # not created yet, or its schema not yet committed
        return 0


def _state(db, out):
    """Each part's row, its characteristics' rows, and its report files' bytes, by serial."""
    parts = _query(db, "SELECT serial, id, status, measured_at, worker, seconds, exit_code FROM parts ORDER BY serial")
    chars = _query(db, "SELECT p.serial, c.characteristic, c.measured, c.standard_uncertainty, c.decision "
                       "FROM characteristics c JOIN parts p ON p.id = c.part_id ORDER BY p.serial, c.characteristic")
    files = {}
    for serial, *_ in parts:
        folder = out / serial
        files[serial] = {p.name: (hashlib.sha256(p.read_bytes()).hexdigest(), p.stat().st_mtime_ns)
                         for p in folder.iterdir()} if folder.is_dir() else {}
    return ({r[0]: r[1:] for r in parts}, {s: [c[1:] for c in chars if c[0] == s] for s, *_ in parts}, files)


@pytest.mark.parametrize("signum", [signal.SIGKILL, signal.SIGINT], ids=["SIGKILL", "SIGINT"])
def test_a_killed_batch_resumes_without_losing_or_repeating_a_part(manifest, tmp_path, signum):
    out = tmp_path / "out"
    db = out / "results.sqlite"
    proc = _batch(manifest, out)
    try:
        deadline = time.monotonic() + 300
        while _done(db) < 1:
            assert proc.poll() is None, f"the batch ended before a part was recorded: {proc.communicate()}"
            assert time.monotonic() < deadline, "no part recorded in 300 s"
            time.sleep(0.1)
        os.killpg(proc.pid, signum)  # the whole group, workers included, as a terminal's Ctrl-C or a kill -9 -PGID
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    if signum == signal.SIGINT:
        assert proc.returncode == 130
        assert err.strip().splitlines()[-1] == "inspect: interrupted; earlier outputs are left as they were"
    else:
        assert proc.returncode == -signal.SIGKILL
    parts, chars, files = _state(db, out)
    finished = {s for s, row in parts.items() if row[1] == "done"}
    assert 1 <= len(finished) < N, parts  # killed mid-way: some done, some not
    assert set(parts) == finished  # a part is recorded whole when done, or not at all

    resumed = _batch(manifest, out, "--resume")
    stdout, err = resumed.communicate(timeout=600)
    assert resumed.returncode == 3, err  # the plate's three inconclusive characteristics
    assert f"BATCH INCONCLUSIVE: {N - len(finished)} part(s) inspected" in stdout
    assert f"{len(finished)} already done" in stdout

    parts2, chars2, files2 = _state(db, out)
    serials = {f"K-{i:03d}" for i in range(1, N + 1)}
    assert set(parts2) == serials and all(row[1] == "done" for row in parts2.values())
    assert _query(db, "SELECT count(*) FROM batches") == [(1,)]
    # No duplicate rows: one part row per serial, one row per characteristic of it.
    assert _query(db, "SELECT count(*) FROM parts") == [(N,)]
    assert _query(db, "SELECT count(*) FROM (SELECT part_id, characteristic FROM characteristics "
                      "GROUP BY part_id, characteristic HAVING count(*) > 1)") == [(0,)]
    # The parts finished before the kill were not redone: same rows (id, time
    # stamp, worker, seconds), same characteristics, same report files untouched.
    for s in finished:
        assert parts2[s] == parts[s] and chars2[s] == chars[s] and files2[s] == files[s]
    redone = serials - finished
    first_workers = {parts[s][3] for s in finished}
    assert not {parts2[s][3] for s in redone} & first_workers  # new worker processes did them
    # Every report folder complete (no temporary file left), and equal to its rows.
    for s in serials:
        assert set(files2[s]) == REPORT_FILES, files2[s]
        report = json.loads((out / s / "report.json").read_text())
        assert chars2[s] == sorted((c["id"], c["measured"], c["standard_uncertainty"], c["decision"])
                                   for c in report["characteristics"])
    # Every part of the plate measures the same from the same images, resumed or not.
    assert len({tuple(chars2[s]) for s in serials}) == 1
    assert _query(db, "PRAGMA integrity_check") == [("ok",)]
    assert _query(db, "PRAGMA foreign_key_check") == []
    assert (out / "spc.html").is_file()


def test_a_redone_part_starts_without_the_killed_try_s_temporaries(tmp_path):
    from partinspect.atomic import remove_stale_temporaries, write_bytes_atomic

    write_bytes_atomic(tmp_path / "report.json", b"{}")
    for name in (".report.json.k2j4_x.tmp", ".write-test-123-abcdef01"):
        (tmp_path / name).write_bytes(b"half")
    assert remove_stale_temporaries(tmp_path) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report.json"]
    assert remove_stale_temporaries(tmp_path / "missing") == 0
