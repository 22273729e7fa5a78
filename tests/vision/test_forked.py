"""A call run in a forked child: its outcome as if made here, no child ever left behind."""

import os
import signal
import subprocess
import sys
import textwrap
import time
import warnings
from pathlib import Path

import pytest

from partinspect.errors import InputError
from partinspect.vision import forked as F

REPO = Path(__file__).resolve().parents[2]
needs_fork = pytest.mark.skipif(not F.can_fork(), reason="no os.fork or fewer than 2 CPUs: every call is made here")


class Odd(Exception):
    """An exception type of the caller's own."""


def whose():
    return os.getpid()


def raises(kind, *args):
    raise kind(*args)


def pid_then_sleep(path, seconds):
    with open(path, "w") as f:
        f.write(str(os.getpid()))
    time.sleep(seconds)


def gone(pid):
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    return False


def wait_for_pid(path, timeout=30.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if path.exists() and path.read_text():
            return int(path.read_text())
        time.sleep(0.01)
    raise AssertionError("the child never started")


@needs_fork
def test_result_comes_from_a_child_while_the_caller_goes_on():
    with F.forked(whose) as result:
        here = os.getpid()
        there = result()
    assert there != here
    assert result() == there  # collected once


@needs_fork
@pytest.mark.parametrize("kind, args", [(ValueError, ("bad image",)), (Odd, ("odd", 3)),
                                        (InputError, ("left.png", "unreadable"))])
def test_exceptions_come_back_with_their_type_and_message(kind, args):
    # InputError's __init__ takes (path, problem), not its args: it does not
    # unpickle, and the call is repeated here instead; the others come back.
    with pytest.raises(kind) as info:
        with F.forked(raises, kind, *args) as result:
            result()
    assert str(info.value) == str(kind(*args))


@needs_fork
def test_child_traceback_is_attached():
    with pytest.raises(ValueError) as info:
        with F.forked(raises, ValueError, "x") as result:
            result()
    assert any("raised in a child process" in n and "raises" in n for n in getattr(info.value, "__notes__", []))


@needs_fork
def test_warnings_of_the_child_are_issued_here():
    def warn():
        warnings.warn("careful", RuntimeWarning)
        return 1

    with pytest.warns(RuntimeWarning, match="careful"):
        with F.forked(warn) as result:
            assert result() == 1


STATE = {}


def remember(value):
    STATE["value"] = value  # in the process that makes the call only
    return os.getpid()


def recall(pid, extra):
    return pid, os.getpid(), STATE.get("value"), extra


@needs_fork
def test_a_follow_up_runs_in_the_same_child_with_its_value(monkeypatch):
    fork, forks = os.fork, []
    monkeypatch.setattr(os, "fork", lambda: forks.append(1) or fork())
    with F.forked(remember, "child's") as result:
        assert result.forked
        pid = result()
        then = result.then(recall, [1.5, 2])
        assert then() == (pid, pid, "child's", [1.5, 2])
    assert pid != os.getpid() and len(forks) == 1
    assert "value" not in STATE


@needs_fork
def test_a_follow_up_raises_as_made_here():
    with pytest.raises(Odd, match="then"):
        with F.forked(whose) as result:
            result.then(raise_after, Odd, "then")()


def raise_after(pid, kind, message):
    raise kind(message)


def test_a_follow_up_without_a_child_is_made_here(monkeypatch):
    monkeypatch.setattr(F, "ENABLED", False)
    with F.forked(remember, "here") as result:
        assert not result.forked
        assert result.then(recall, 3)() == (os.getpid(), os.getpid(), "here", 3)
    STATE.clear()


@needs_fork
def test_a_follow_up_after_the_child_died_is_made_here():
    with F.forked(whose) as result:
        pid = result()
        assert result.then(die_unless_in, os.getpid())() == ("made here", pid)


def die_unless_in(pid, parent):
    if os.getpid() != parent:
        os.kill(os.getpid(), signal.SIGKILL)
    return "made here", pid


@pytest.mark.parametrize("how", ["disabled", "one cpu", "fork refused"])
def test_no_child_means_the_call_is_made_here(monkeypatch, how):
    if how == "disabled":
        monkeypatch.setattr(F, "ENABLED", False)
    elif how == "one cpu":
        monkeypatch.setattr(F, "available_cpus", lambda: 1)
    else:
        def refuse():
            raise BlockingIOError(11, "Resource temporarily unavailable")
        monkeypatch.setattr(F, "available_cpus", lambda: 2)
        monkeypatch.setattr(os, "fork", refuse, raising=False)
    with F.forked(whose) as result:
        assert result() == os.getpid()
    with pytest.raises(Odd):
        with F.forked(raises, Odd, "here too") as result:
            result()


@needs_fork
def test_a_child_that_dies_is_replaced_by_the_call_here():
    parent = os.getpid()

    def die_unless_parent():
        if os.getpid() != parent:
            os.kill(os.getpid(), signal.SIGKILL)
        return "made here"

    with F.forked(die_unless_parent) as result:
        assert result() == "made here"


@needs_fork
@pytest.mark.parametrize("exc", [RuntimeError, KeyboardInterrupt])
def test_leaving_the_block_early_kills_the_child(tmp_path, exc):
    path = tmp_path / "pid"
    t = time.monotonic()
    with pytest.raises(exc):
        with F.forked(pid_then_sleep, path, 60):
            pid = wait_for_pid(path)
            raise exc()
    assert time.monotonic() - t < 30
    assert gone(pid)


@needs_fork
def test_sigint_in_the_parent_leaves_no_child(tmp_path):
    # A real Ctrl-C delivered to the parent while the child runs: the parent
    # exits with KeyboardInterrupt and the child is gone (not orphaned).
    path = tmp_path / "pid"
    script = textwrap.dedent(f"""
        import time
        from partinspect.vision import forked as F
        from partinspect.vision.forked import forked
        from tests.vision.test_forked import pid_then_sleep
        F.MIN_IDLE_CPUS = float("-inf")  # fork whatever the load (the suite's own may be high)
        try:
            with forked(pid_then_sleep, {str(path)!r}, 60) as result:
                print("started", flush=True)
                time.sleep(60)
        except KeyboardInterrupt:
            print("interrupted", flush=True)
    """)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True, env=env)
    try:
        assert proc.stdout.readline() == "started\n"
        pid = wait_for_pid(path)
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert out == "interrupted\n"
    assert gone(pid)


def test_no_child_while_the_cpus_are_busy(monkeypatch):
    # At load 3.5-4 on two CPUs a second process only shares this one's slice.
    monkeypatch.setattr(F, "MIN_IDLE_CPUS", 0.5)
    monkeypatch.setattr(F, "available_cpus", lambda: 2)
    monkeypatch.setattr(F.os, "getloadavg", lambda: (3.6, 3.0, 2.5))
    assert not F.can_fork()
    with F.forked(whose) as pid:
        assert pid() == os.getpid()
    monkeypatch.setattr(F.os, "getloadavg", lambda: (0.9, 1.0, 1.0))
    assert F.can_fork() == hasattr(os, "fork")
