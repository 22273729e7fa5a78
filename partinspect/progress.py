"""Progress lines on stderr: shown in a terminal, quiet in CI or with --quiet."""

import os
import sys
import time


class Progress:
    """Callable that prints ``[  1.2 s] message`` lines to stderr.

    Parameters
    ----------
    enabled : bool or None
        None decides from the environment: on when stderr is a terminal and
        the ``CI`` variable is unset.
    stream : file, optional
        Where to print; stderr by default.
    """

    def __init__(self, enabled=None, stream=None):
        self.stream = stream or sys.stderr
        if enabled is None:
            enabled = self.stream.isatty() and not os.environ.get("CI")
        self.enabled = bool(enabled)
        self.t0 = time.perf_counter()

    def __call__(self, message):
        if self.enabled:
            print(f"[{time.perf_counter() - self.t0:6.1f} s] {message}", file=self.stream, flush=True)


def quiet(message):
    """A progress callback that prints nothing."""
