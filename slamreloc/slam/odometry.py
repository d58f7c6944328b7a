"""Odometry front ends: each frame -> `odom_from_cam` (camera pose in the odometry frame, metres)
plus the registration measures that tracking-health checks read.

Neither kiss-icp nor open3d says whether tracking is healthy; every front end therefore reports
`fitness` (share of the frame's points that landed on the model after registration) and the
motion it estimated, and `slamreloc.slam.health` judges them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from slamreloc.geometry import Rigid3
from slamreloc.types import Camera


@dataclass
class OdometryStep:
    """One frame's result. `fitness` is None when the front end cannot measure it."""

    odom_from_cam: Rigid3
    fitness: float | None = None
    n_points: int = 0
    extra: dict = field(default_factory=dict)


class Odometry:
    """Base class: `step` one RGB-D frame at a time; `reset` after tracking loss (the next
    frame starts a new odometry frame at the identity)."""

    name = "odometry"

    def step(self, depth: np.ndarray | None, camera: Camera, image: np.ndarray | None = None,
             timestamp: float = 0.0, index: int = 0) -> OdometryStep:
        raise NotImplementedError

    def reset(self) -> None:
        """Forget the model; external odometry (a trajectory file) cannot be reset: no-op."""


def occupied_fraction(points: np.ndarray, model: np.ndarray, cell_m: float) -> float:
    """Share of `points` falling in a cell of size `cell_m` that holds a `model` point."""
    if len(points) == 0 or len(model) == 0:
        return 0.0
    weights = np.array([1, 1 << 21, 1 << 42])
    occupied = np.unique(np.floor(model / cell_m).astype(np.int64) @ weights)
    q = np.floor(points / cell_m).astype(np.int64) @ weights
    pos = np.clip(np.searchsorted(occupied, q), 0, len(occupied) - 1)
    return float(np.mean(occupied[pos] == q))
