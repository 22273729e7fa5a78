"""Atomic file output: a file appears complete or not at all.

Every output is written to a temporary file in the destination folder and
renamed over the target with ``os.replace``, which is atomic on POSIX and
Windows within one file system; an interrupted run leaves the previous file
intact and no partial file behind.
"""

import contextlib
import os
import signal
import tempfile
import threading
import uuid
from pathlib import Path

from partinspect.errors import InputError


def _write_temp(path, data):
    """``data`` in a new temporary file beside ``path``, synced; returns its name."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644)
    except BaseException:
        os.unlink(tmp)
        raise
    return tmp


@contextlib.contextmanager
def deferred_signals(signums=(signal.SIGINT, signal.SIGTERM)):
    """Hold SIGINT and SIGTERM until the block is done, then act on them.

    For a few renames that belong together: Ctrl-C between two of them
    would leave a report set mixed from two runs. Outside the main thread
    (where Python cannot set handlers) it does nothing.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received = []
    previous = {s: signal.signal(s, lambda signum, frame: received.append(signum)) for s in signums}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, signal.SIG_DFL if handler is None else handler)
        for s in dict.fromkeys(received):
            signal.raise_signal(s)


def write_bytes_atomic(path, data):
    """Write ``data`` (bytes) to ``path`` atomically; returns the Path."""
    return write_files_atomic({path: data})[0]


def write_files_atomic(files):
    """Write several files atomically, replacing them together.

    Every file is first written to a temporary file beside its target; only
    when all are complete are they renamed over their targets, one after
    the other with SIGINT and SIGTERM held off, so an interrupted run leaves
    the previous set or the new one, never a mix, and no temporary file.
    (A power cut between two renames can still mix them.)

    Parameters
    ----------
    files : mapping of str or Path to bytes

    Returns
    -------
    list of Path
    """
    done, tmps = [], []
    try:
        for path, data in files.items():
            path = Path(path)
            tmps.append(_write_temp(path, data))
            done.append(path)
        with deferred_signals():
            for tmp, path in zip(tmps, done):
                os.replace(tmp, path)
    except BaseException:
        for tmp in tmps:
            if os.path.exists(tmp):
                os.unlink(tmp)
        raise
    return done


def write_text_atomic(path, text):
    """Write ``text`` as UTF-8 to ``path`` atomically; returns the Path."""
    return write_bytes_atomic(path, text.encode("utf-8"))


def check_output_dir(path):
    """Check, without creating anything, that ``path`` can become the output folder.

    Raises
    ------
    InputError
        When it is not a folder, or neither it nor its nearest existing
        parent is writable.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise InputError(path, "output path exists and is not a folder")
    existing = path
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir():
        raise InputError(path, f"cannot create the output folder: {existing} is not a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise InputError(path, f"output folder is not writable ({existing} refuses writes)")
    return path


def remove_stale_temporaries(folder):
    """Remove the temporary files and write probes a killed writer left in ``folder`` (SIGKILL skips cleanups).

    Only for a folder no other process writes into at the time: a batch
    calls it before it redoes a part whose earlier try was killed.
    Returns the number of files removed.
    """
    removed = 0
    folder = Path(folder)
    for tmp in [*folder.glob(".*.tmp"), *folder.glob(".write-test-*")]:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
            removed += 1
    return removed


def prepare_output_dir(path):
    """Create the output folder if needed and check it is writable.

    Raises
    ------
    InputError
        When the folder cannot be created or written (named in the message).
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise InputError(path, "output path exists and is not a folder")
    # The probe's name is fixed before it exists, so an interrupt (SIGINT)
    # at any point after its creation still removes it in the finally.
    probe = path / f".write-test-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    try:
        path.mkdir(parents=True, exist_ok=True)
        try:
            os.close(os.open(probe, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600))
        finally:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(probe)
    except OSError as exc:
        raise InputError(path, f"output folder is not writable ({exc.strerror or exc})") from None
    return path
