"""Atomic file output: a file appears complete or not at all.

Every output is written to a temporary file in the destination folder and
renamed over the target with ``os.replace``, which is atomic on POSIX and
Windows within one file system; an interrupted run leaves the previous file
intact and no partial file behind.
"""

import os
import tempfile
from pathlib import Path

from partinspect.errors import InputError


def write_bytes_atomic(path, data):
    """Write ``data`` (bytes) to ``path`` atomically; returns the Path."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


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
    try:
        path.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".write-test-", dir=path)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise InputError(path, f"output folder is not writable ({exc.strerror or exc})") from None
    return path
