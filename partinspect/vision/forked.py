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

The child can be given one more call after the first (``result.then``): it
receives the first call's value as the child holds it, so that what the
child computed need not be sent back to it, and the parent starts no
second process, which would cost a fork and the copy-on-write faults of
two processes writing to memory they share again. The follow-up's function
and arguments are pickled on the way in (plain module-level functions and
data).

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
        process when ``result()`` is first called. ``result.forked`` says
        whether a child was started. ``result.then(func2, *args2,
        **kwargs2)`` (once, after ``result()``) runs ``func2(value, *args2,
        **kwargs2)`` in the same child, ``value`` being the child's own copy
        of the first call's value, and returns a callable like ``result``;
        made here where the child cannot (none started, it died, the
        arguments do not pickle).

    Notes
    -----
    Leaving the block before ``result()`` has collected the child (an
    exception, a KeyboardInterrupt, or simply not calling it) kills and
    reaps the child: none is ever left behind. A child that has sent its
    outcome waits for a follow-up until the block is left.

    Examples
    --------
    >>> with forked(sum, [1, 2, 3]) as total:
    ...     here = sum([4, 5])
    ...     there = total()
    ...     doubled = total.then(pow, 2)()
    >>> here, there, doubled
    (9, 6, 36)
    """
    child = None
    result = _Result(lambda: child, "out", func, args, kwargs)
    with contextlib.ExitStack() as stack:
        if can_fork():
            stack.enter_context(_one_thread_each())
            child = _start_held(stack, func, args, kwargs)
            if child is None:
                stack.close()  # no child: the thread counts back at once
        result.forked = child is not None
        yield result


@contextlib.contextmanager
def _one_thread_each():
    """OpenCV and BLAS on one thread each while parent and child compute side by side; restored on leaving.

    ``cv2.setNumThreads(1)`` also joins OpenCV's workers, whose pool a
    forked child could block on (module notes).
    """
    threads, blas = cv2.getNumThreads(), None
    cv2.setNumThreads(1)
    try:
        blas = one_blas_thread()
        yield
    finally:
        cv2.setNumThreads(threads)
        if blas is not None:
            blas.restore_original_limits()


def _start_held(stack, func, args, kwargs):
    """:func:`_start` with SIGINT held back until the child's stop is on ``stack``: a Ctrl-C then cannot lose it."""
    held = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        child = _start(func, args, kwargs)
        if child is not None:
            stack.callback(_stop, child)
        return child
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, held)


class _Result:
    """The callable :func:`forked` yields: one call's outcome from the child's pipe ``pipe``, or made here.

    ``child`` returns the child's state (None: no child). The follow-up
    (``then``) is one more of these, on the child's ``"then"`` pipe.
    """

    def __init__(self, child, pipe, func, args, kwargs):
        self._child, self._pipe, self._call, self._outcome = child, pipe, (func, args, kwargs), []
        self.forked = False

    def __call__(self):
        if not self._outcome:
            self._outcome.append(self._collect() or _here(*self._call))
        return _unpack(self._outcome[0])

    def _collect(self):
        """The child's outcome, or None (no child, or its outcome lost: it is then sent no follow-up)."""
        child = self._child()
        if child is None:
            return None
        got = _collect(child, self._pipe)
        if got is None:
            child["lost"] = True
        return got

    def then(self, func, *args, **kwargs):
        """``func(value, *args, **kwargs)`` in the child that made the first call; a callable for its outcome."""
        value = self()
        child = self._child()
        sent = child is not None and not child.get("lost") and _send(child, (func, args, kwargs))
        return _Result((lambda: child) if sent else (lambda: None), "then", func, (value, *args), kwargs)


def _here(func, args, kwargs):
    """The call made in this process, as an outcome: its exception raised as it comes."""
    return True, func(*args, **kwargs), ()


def _unpack(outcome):
    ok, value, caught = outcome
    if not ok:
        raise value
    for message, category, filename, lineno in caught:
        warnings.warn_explicit(message, category, filename, lineno)
    return value


def _start(func, args, kwargs):
    """Fork a child that runs the call and writes its pickled outcome to a pipe; its state, or None if none started.

    Three pipes: the first outcome (child to parent), a follow-up call
    (parent to child) and its outcome (child to parent). Each message is
    sent with its length, so that its end is known even where another
    process forked meanwhile holds a copy of the pipe's writing end.
    """
    prctl = _pdeathsig_setter()
    _release_free_heap()
    parent = os.getpid()
    pipes = []
    try:
        for _ in range(3):
            pipes.append(os.pipe())
    except OSError:
        _close(fd for pair in pipes for fd in pair)
        return None
    (out_r, out_w), (cmd_r, cmd_w), (then_r, then_w) = pipes
    try:
        with warnings.catch_warnings():
            # Python 3.12+ warns on fork() in a process with threads; the
            # threads here are OpenCV's and OpenBLAS's workers (module notes).
            warnings.simplefilter("ignore", DeprecationWarning)
            pid = os.fork()
    except OSError:  # EAGAIN, ENOMEM: a process or memory limit
        _close(fd for pair in pipes for fd in pair)
        return None
    if pid == 0:
        # The child: whatever happens, it must never return into the
        # parent's code, so every way out is os._exit.
        try:
            _close((out_r, cmd_w, then_r))
            _run_child(out_w, cmd_r, then_w, parent, prctl, func, args, kwargs)
        finally:
            os._exit(0)
    _close((out_w, cmd_r, then_w))
    return {"pid": pid, "out": out_r, "cmd": cmd_w, "then": then_r, "reaped": False}


def _run_child(out, cmd, then, parent, prctl, func, args, kwargs):
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    if prctl is not None:
        prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    if os.getppid() != parent:  # the parent died before that was set
        return
    ok, value = _call_and_send(out, func, args, kwargs)
    if not ok:
        return
    data = _read_message(cmd)  # None when the parent leaves the block without a follow-up
    if data:
        func2, args2, kwargs2 = pickle.loads(data)
        _call_and_send(then, func2, (value,) + tuple(args2), kwargs2)


def _call_and_send(w, func, args, kwargs):
    """Make the call, write its pickled outcome to the pipe ``w`` and close it; (ok, value)."""
    value = None
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
    _write_message(w, data)
    return outcome[0] and bool(data), value


def _send(child, call):
    """Write a follow-up call to the child and close the pipe; whether it went."""
    try:
        _write_message(child["cmd"], pickle.dumps(call, protocol=pickle.HIGHEST_PROTOCOL))
    except Exception:  # does not pickle, or the child is gone (EPIPE)
        return False
    finally:
        _close((child["cmd"],))
        child["cmd"] = None
    return True


def _collect(child, which):
    """The child's outcome (ok, value, warnings) from pipe ``which``, or None when it sent none."""
    data = _read_message(child[which])
    try:
        return pickle.loads(data) if data else None
    except Exception:
        return None


def _stop(child):
    """Kill the child unless it has been reaped (its pid may be another process's by then), reap it, close the pipes."""
    if not child["reaped"]:
        try:
            os.kill(child["pid"], signal.SIGKILL)
        except ProcessLookupError:
            pass
        _reap(child)
    _close(child[k] for k in ("out", "cmd", "then"))


def _write_message(fd, data):
    with open(fd, "wb", closefd=False) as pipe:
        pipe.write(len(data).to_bytes(8, "little") + data)


def _read_message(fd):
    """The bytes of one message, or None if the pipe ended first (the writer died or left)."""
    with open(fd, "rb", closefd=False) as pipe:
        head = pipe.read(8)
        if len(head) < 8:
            return None
        size = int.from_bytes(head, "little")
        data = pipe.read(size)
    return data if len(data) == size else None


def _close(fds):
    for fd in fds:
        if fd is not None:
            try:
                os.close(fd)
            except OSError:
                pass


def _reap(child):
    try:
        os.waitpid(child["pid"], 0)
    except ChildProcessError:  # not ours to wait for any more
        pass
    child["reaped"] = True


def _libc(name):
    """Function ``name`` of the C library on Linux, else None."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        import ctypes

        return getattr(ctypes.CDLL(None, use_errno=True), name)
    except (ImportError, OSError, AttributeError):
        return None


def _pdeathsig_setter():
    """``prctl`` of the C library on Linux (to have the child killed with its parent), else None."""
    return _libc("prctl")


def _release_free_heap():
    """Hand the heap's free pages back to the OS before forking (glibc's ``malloc_trim``).

    After a fork both processes share every page copy-on-write, and the
    heap's free blocks are where the next large arrays are made (glibc
    serves an array from the heap once one of its size has been freed):
    each process's first write to each of their pages then copies the page.
    Handed back first, those pages come fresh, zero-filled on first write,
    and in huge pages where the kernel has them. Figures: docs/validation.md.

    References
    ----------
    .. [1] malloc_trim(3) and mallopt(3) (``M_MMAP_THRESHOLD``'s dynamic
           adjustment), Linux man-pages project.
    """
    trim = _libc("malloc_trim")  # glibc only; other C libraries have none
    if trim is not None:
        trim(0)
