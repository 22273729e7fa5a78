"""Where a run's time goes: wall-clock seconds per named stage.

``inspect --timings`` prints them on stderr and report.json records them,
so that a slower release is visible in the reports it writes.
"""

import time
from contextlib import contextmanager


class Timings:
    """Wall-clock seconds of named stages, in the order they ran.

    A stage entered twice (an adaptive re-run, say) adds to its first entry.
    ``start`` is taken when the object is made; `total` counts from there,
    so the stages' sum falls short of it by whatever ran between them.
    """

    def __init__(self, start=None):
        self.start = time.perf_counter() if start is None else start
        self.seconds = {}

    @contextmanager
    def stage(self, name):
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - t0

    def total(self):
        """Seconds since ``start``."""
        return time.perf_counter() - self.start

    def to_dict(self):
        """report.json's ``timings``: stages in run order, seconds to the millisecond."""
        return {"stages": [{"stage": k, "seconds": round(v, 3)} for k, v in self.seconds.items()],
                "total_seconds": round(self.total(), 3)}

    def table(self):
        """The stages as text lines, one per stage, then the total."""
        width = max([len(k) for k in self.seconds] + [5])
        lines = [f"{k:<{width}}  {v:7.3f} s" for k, v in self.seconds.items()]
        return "\n".join(lines + [f"{'total':<{width}}  {self.total():7.3f} s"])

