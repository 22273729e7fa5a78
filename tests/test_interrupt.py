"""Ctrl-C during a run: exit 130, one line, the previous reports intact, no temporary files.

A real process is needed: SIGINT is delivered by the kernel, not by a call.
PARTINSPECT_PROGRESS=1 makes the run print its stages on a pipe, so the
signal is sent once the run is known to be under way rather than after a
guessed sleep.
"""

import hashlib
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from partinspect.atomic import deferred_signals, write_files_atomic

REPO = Path(__file__).resolve().parents[1]
PLATE = REPO / "examples" / "plate"
PROGRESS = re.compile(r"^\[\s*\d+\.\d s\] ")
PREVIOUS = {"report.json": b'{"schema": "report/1", "verdict": "fail"}\n', "junit.xml": b"<testsuites/>\n", "report.html": b"<html>previous</html>\n"}


def digest(folder):
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir())}


@pytest.fixture
def work(tmp_path):
    d = tmp_path / "plate"
    shutil.copytree(PLATE, d, ignore=shutil.ignore_patterns("truth.json", "make_part.py"))
    out = tmp_path / "inspection"
    out.mkdir()
    for name, data in PREVIOUS.items():
        (out / name).write_bytes(data)
    return d, out


# `python -m partinspect` that forks the right image's chain whatever the machine's load
# (vision.forked.MIN_IDLE_CPUS), as the tests' own process does (tests/conftest.py).
FORKING_CLI = ("import sys; from partinspect.vision import forked; forked.MIN_IDLE_CPUS = float('-inf'); "
               "from partinspect.cli import main; sys.exit(main(sys.argv[1:]))")


def interrupted_run(part, images, out, stage, *, delay=0.0, new_session=False, force_fork=False):
    """Start `python -m partinspect`, send SIGINT ``delay`` s after it reports ``stage``;
    (code, stderr lines, stdout, pid). ``new_session``: the run gets a session (so a
    process group) of its own, whose id is its pid. ``force_fork``: the run forks its
    right image's chain even on a busy machine."""
    env = dict(os.environ, PARTINSPECT_PROGRESS="1", PYTHONUNBUFFERED="1")
    env.pop("PARTINSPECT_DEBUG", None)
    entry = ["-c", FORKING_CLI] if force_fork else ["-m", "partinspect"]
    proc = subprocess.Popen(
        [sys.executable, *entry, str(part), str(images), "-o", str(out)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=REPO,
        start_new_session=new_session,
    )
    seen = []
    try:
        for line in proc.stderr:
            seen.append(line)
            if stage in line:
                time.sleep(delay)
                proc.send_signal(signal.SIGINT)
                break
        else:
            pytest.fail(f"the run never reported {stage!r}: {''.join(seen)}")
        rest_out, rest_err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return proc.returncode, seen + rest_err.splitlines(keepends=True), rest_out, proc.pid


def test_sigint_while_loading_the_part_keeps_previous_reports(work):
    plate, out = work
    before = digest(out)
    inputs = {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in plate.rglob("*") if p.is_file()}
    # "loading part.step" comes before seconds of importing cadquery and reading the STEP file.
    code, err, stdout, _ = interrupted_run(plate / "part.step", plate / "images", out, "loading part.step")
    messages = [line for line in err if not PROGRESS.match(line)]
    assert code == 130, "".join(err)
    assert messages == ["inspect: interrupted; earlier outputs are left as they were\n"], "".join(err)
    assert "Traceback" not in "".join(err)
    assert stdout == ""
    assert digest(out) == before  # byte-identical, and nothing else there (no temporary files)
    assert {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in plate.rglob("*") if p.is_file()} == inputs


def test_sigint_while_writing_leaves_one_complete_set(work):
    # The signal lands while rendering or while the files are replaced: either
    # way the folder holds one complete set, the previous or the new, never a mix.
    plate, out = work
    code, err, _, _ = interrupted_run(plate / "part.step", plate / "images", out, "writing reports")
    assert code in (130, 3), "".join(err)
    assert sorted(p.name for p in out.iterdir()) == sorted(PREVIOUS)
    old = [(out / name).read_bytes() == data for name, data in PREVIOUS.items()]
    assert all(old) or not any(old), old
    if code == 130:
        assert [line for line in err if not PROGRESS.match(line)] == [
            "inspect: interrupted; earlier outputs are left as they were\n"
        ]


def test_deferred_signals_hold_sigint_until_the_block_ends():
    order = []
    with pytest.raises(KeyboardInterrupt):
        with deferred_signals():
            os.kill(os.getpid(), signal.SIGINT)
            order.append("after the signal, still inside")
        order.append("never: the held signal is raised on leaving")
    assert order == ["after the signal, still inside"]
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_interrupted_multi_file_write_leaves_no_temporary_files(tmp_path):
    # A generator that is interrupted half-way through producing the files:
    # nothing is replaced and no temporary file stays.
    for name, data in PREVIOUS.items():
        (tmp_path / name).write_bytes(data)

    class Files(dict):
        def items(self):
            yield tmp_path / "report.json", b"new json"
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        write_files_atomic(Files())
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == PREVIOUS


def test_sigint_while_measuring_leaves_no_child_process(work):
    # The right image's 2D chain runs in a forked child (vision.forked): a
    # Ctrl-C in the middle of it ends the run as usual and leaves no process
    # behind (the run gets a session of its own, so whatever it forked is
    # found by its group even after the parent is gone).
    plate, out = work
    # 0.3 s after the left chain starts, the child has started too (the left chain takes longer).
    code, err, _, pid = interrupted_run(plate / "part.step", plate / "images", out, "edges and segments: left image",
                                        delay=0.3, new_session=True, force_fork=True)
    assert code == 130, "".join(err)
    deadline = time.monotonic() + 5
    while True:
        try:
            os.killpg(pid, 0)
        except ProcessLookupError:
            break  # no process of the run's group is left
        assert time.monotonic() < deadline, "a process of the interrupted run is still there"
        time.sleep(0.05)
