"""Content digests of input files: what a report records and what keys a cache."""

import hashlib


def sha256_file(path):
    """SHA-256 hex digest of a file's bytes, read in 1 MiB blocks.

    Raises
    ------
    OSError
        If the file cannot be read.
    """
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()
