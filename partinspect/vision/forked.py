"""One function call run in a forked child process while the caller goes on.

:func:`partinspect.vision.stereo.measure_stereo` measures the two images of a
pair independently, and each image's 2D chain spends most of its time in
Python code, so threads would only take turns holding the GIL; a second
process runs truly alongside. A *forked* child starts at once with
everything the parent has imported and computed (nothing is pickled on the
way in, only the result on the way back) and needs no ``__main__`` guard in
the caller's script.

Outcomes are the caller's: the child's return value comes back by pickle
(the same bits), an exception raised in the child is raised again in the
parent (its traceback from the child attached as a note). Where no child
can run the call (no ``os.fork``, fewer than two CPUs, ``fork`` refused by
a resource limit) or its outcome cannot come back (the child was killed,
the result does not pickle), the parent makes the call itself: only
slower, never different.

Fork safety: a forked child inherits the library worker threads' mutexes
and condition variables in whatever state they were, but not the threads.
OpenBLAS shuts its workers down around a fork itself; OpenCV's pthreads
pool does not, and a child can block on it forever, so the parent stops
OpenCV's workers before forking (``cv2.setNumThreads(1)`` joins them) and
restores the count when the block is left. While parent and child compute
side by side each runs OpenCV and BLAS on one thread (threadpoolctl), all
the CPUs two processes have on a two-CPU machine; neither library's results
depend on its thread count. The child ignores SIGINT (a Ctrl-C reaches the whole process
group); the parent kills it when it leaves the block early, and on Linux
it is killed if the parent dies (``PR_SET_PDEATHSIG``).
"""

import contextlib
import os
import pickle
import signal
import sys
import traceback
import warnings

import cv2

from partinspect.vision.blas import one_blas_thread

__all__ = ["available_cpus", "idle_cpus", "can_fork", "forked"]

ENABLED = True
"""Set False to make every :func:`forked` call in the caller's process."""
MIN_IDLE_CPUS = 0.5
"""A child is started only when at least this many CPUs are idle (:func:`idle_cpus`)."""


def available_cpus():
    """CPUs this process may run on (its affinity mask where the OS has one)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def idle_cpus():
    """CPUs not busy on average over the last minute (the 1-minute load average
    counts this process too), or all of them where the OS keeps no load average."""
    try:
        load = os.getloadavg()[0]
    except (AttributeError, OSError):
        return available_cpus()
    return available_cpus() - load


def can_fork():
    """Whether :func:`forked` would start a child: ``os.fork`` exists, it is
    enabled, there are 2+ CPUs and about one of them is idle.

    With the CPUs already busy with other work a second process only
    shares this one's slice, and the two images take longer side by side
    than one after the other.
    """
    return ENABLED and hasattr(os, "fork") and available_cpus() >= 2 and idle_cpus() >= MIN_IDLE_CPUS


@contextlib.contextmanager
def forked(func, *args, **kwargs):
    """Run ``func(*args, **kwargs)`` in a forked child process while the block runs.

    Parameters
    ----------
    func : callable
        Runs in the child on a copy of the parent's memory: it must not
        rely on side effects in the parent, and its result (or exception)
        should pickle.
    *args, **kwargs
        Its arguments (not pickled: the child has them already).

    Yields
    ------
    result : callable
        ``result()`` waits for the child and returns the call's value, or
        raises its exception. Where no child was started, or its outcome
        did not come back (see the module notes), the call is made in this
        process when ``result()`` is first called.

    Notes
    -----
    Leaving the block before ``result()`` has collected the child (an
    exception, a KeyboardInterrupt, or simply not calling it) kills and
    reaps the child: none is ever left behind.

    Examples
    --------
    >>> with forked(sum, [1, 2, 3]) as total:
    ...     here = sum([4, 5])
    ...     there = total()
    >>> here, there
    (9, 6)
    """
    child, threads, blas, outcome = None, None, None, []

    def result():
        if not outcome:
            got = _collect(child) if child is not None else None
            # No child, or its outcome is lost: the same call, here.
            outcome.append(got if got is not None else (True, func(*args, **kwargs), ()))
        ok, value, caught = outcome[0]
        if not ok:
            raise value
        for message, category, filename, lineno in caught:
            warnings.warn_explicit(message, category, filename, lineno)
        return value

    try:
        if can_fork():
            threads = cv2.getNumThreads()
            cv2.setNumThreads(1)  # stops OpenCV's workers (module notes)
            blas = one_blas_thread()
            # A Ctrl-C between the fork and the assignment would lose track
            # of the child: SIGINT is held back until ``child`` is set.
            held = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
            try:
                child = _start(func, args, kwargs)
            finally:
                signal.pthread_sigmask(signal.SIG_SETMASK, held)
            if child is None:
                cv2.setNumThreads(threads)
                threads = None
                blas.restore_original_limits()
                blas = None
        yield result
    finally:
        if child is not None:
            _stop(child)
        if threads is not None:
            cv2.setNumThreads(threads)
        if blas is not None:
            blas.restore_original_limits()


def _start(func, args, kwargs):
    """Fork a child that runs the call and writes its pickled outcome to a pipe; its state, or None if none started."""
    prctl = _pdeathsig_setter()
    parent = os.getpid()
    try:
        r, w = os.pipe()
    except OSError:
        return None
    try:
        with warnings.catch_warnings():
            # Python 3.12+ warns on fork() in a process with threads; the
            # threads here are OpenCV's and OpenBLAS's workers (module notes).
            warnings.simplefilter("ignore", DeprecationWarning)
            pid = os.fork()
    except OSError:  # EAGAIN, ENOMEM: a process or memory limit
        os.close(r)
        os.close(w)
        return None
    if pid == 0:
        # The child: whatever happens, it must never return into the
        # parent's code, so every way out is os._exit.
        try:
            os.close(r)
            _run_child(w, parent, prctl, func, args, kwargs)
        finally:
            os._exit(0)
    os.close(w)
    return {"pid": pid, "fd": r, "reaped": False}


def _run_child(w, parent, prctl, func, args, kwargs):
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    if prctl is not None:
        prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    if os.getppid() != parent:  # the parent died before that was set
        return
    try:
        with warnings.catch_warnings(record=True) as caught:
            value = func(*args, **kwargs)
        outcome = (True, value, [(m.message, m.category, m.filename, m.lineno) for m in caught])
    except BaseException as exc:
        exc.add_note(f"(raised in a child process: {traceback.format_exc().rstrip()})")
        outcome = (False, exc, ())
    try:
        data = pickle.dumps(outcome, protocol=pickle.HIGHEST_PROTOCOL)
        if not outcome[0]:
            # An exception whose __init__ takes other arguments than its
            # args pickles but does not unpickle: found here, and then the
            # parent makes the call itself and raises it first-hand.
            pickle.loads(data)
    except BaseException:
        data = b""
    with open(w, "wb") as pipe:
        pipe.write(data)


def _collect(child):
    """The child's outcome (ok, value, warnings), or None when it sent none; reaps the child."""
    with open(child["fd"], "rb", closefd=False) as pipe:
        data = pipe.read()
    _reap(child)
    try:
        return pickle.loads(data) if data else None
    except Exception:
        return None


def _stop(child):
    """Kill the child unless it has been reaped (its pid may be another process's by then), reap it, close the pipe."""
    if not child["reaped"]:
        try:
            os.kill(child["pid"], signal.SIGKILL)
        except ProcessLookupError:
            pass
        _reap(child)
    os.close(child["fd"])


def _reap(child):
    try:
        os.waitpid(child["pid"], 0)
    except ChildProcessError:  # not ours to wait for any more
        pass
    child["reaped"] = True


def _pdeathsig_setter():
    """``prctl`` of the C library on Linux (to have the child killed with its parent), else None."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        import ctypes

        return ctypes.CDLL(None, use_errno=True).prctl
    except (ImportError, OSError, AttributeError):
        return None
