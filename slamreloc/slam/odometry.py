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


@dataclass(frozen=True)
class DepthSampling:
    """Back-projection of a depth map: every `stride`-th pixel, depths in [min_m, max_m]."""

    stride: int = 4
    min_m: float = 0.2
    max_m: float = 4.0


def depth_camera(camera: Camera, depth_shape: tuple[int, int],
                 depth_intrinsics: tuple[float, float, float, float] | None) -> Camera:
    """The camera that took the depth map: given intrinsics (7-Scenes: 585, 585, 320, 240 at
    640x480), else the RGB camera scaled to the depth size (registered depth)."""
    h, w = depth_shape
    if depth_intrinsics is None:
        return camera.scaled_to(w, h)
    fx, fy, cx, cy = depth_intrinsics
    return Camera(640, 480, fx, fy, cx, cy).scaled_to(w, h)


def backproject(depth: np.ndarray, camera: Camera, sampling: DepthSampling) -> np.ndarray:
    """(N, 3) float64 points in the camera frame (OpenCV axes, metres)."""
    s = sampling.stride
    d = depth[::s, ::s]
    v, u = np.nonzero((d > sampling.min_m) & (d < sampling.max_m))
    z = d[v, u].astype(np.float64)
    x = (u * s - camera.cx) / camera.fx * z
    y = (v * s - camera.cy) / camera.fy * z
    return np.stack([x, y, z], axis=1)


def occupied_fraction(points: np.ndarray, model: np.ndarray, cell_m: float) -> float:
    """Share of `points` falling in a cell of size `cell_m` that holds a `model` point."""
    if len(points) == 0 or len(model) == 0:
        return 0.0
    weights = np.array([1, 1 << 21, 1 << 42])
    occupied = np.unique(np.floor(model / cell_m).astype(np.int64) @ weights)
    q = np.floor(points / cell_m).astype(np.int64) @ weights
    pos = np.clip(np.searchsorted(occupied, q), 0, len(occupied) - 1)
    return float(np.mean(occupied[pos] == q))
