"""Per-stage wall-clock timers (milliseconds) for the SLAM report."""

from __future__ import annotations

import time
from array import array
from collections import defaultdict
from contextlib import contextmanager

import numpy as np


class Timer:
    """Every sample is kept (the report's medians), as 8-byte doubles: a long run holds
    8 bytes per stage call, not a Python float object and a list slot (32)."""

    def __init__(self):
        self.samples: dict[str, array] = defaultdict(lambda: array("d"))

    @contextmanager
    def __call__(self, stage: str):
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.samples[stage].append(1000 * (time.perf_counter() - t0))

    def summary(self) -> dict[str, dict[str, float]]:
        """stage -> {calls, median_ms, total_ms}."""
        return {k: {"calls": len(v), "median_ms": float(np.median(v)),
                    "total_ms": float(np.sum(v))} for k, v in self.samples.items() if v}
