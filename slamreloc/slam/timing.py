"""Per-stage wall-clock timers (milliseconds) for the SLAM report."""

from __future__ import annotations

import time
from collections import defaultdict
from contextlib import contextmanager

import numpy as np


class Timer:
    def __init__(self):
        self.samples: dict[str, list[float]] = defaultdict(list)

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
