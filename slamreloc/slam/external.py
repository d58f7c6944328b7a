"""Odometry from another system: a TUM trajectory file, looked up by frame timestamp."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from slamreloc.errors import InputError
from slamreloc.geometry import nearest_stamps
from slamreloc.slam.odometry import Odometry, OdometryStep
from slamreloc.slam.trajectory import read_tum


class TrajectoryOdometry(Odometry):
    """`odom_from_cam` of each frame is the file's pose at the nearest timestamp (within
    `max_dt` seconds); the file's frame is the odometry frame. It cannot be reset."""

    name = "trajectory"

    def __init__(self, path: str | Path, max_dt: float = 0.01):
        self.path = Path(path)
        self.stamps, self.poses = read_tum(self.path)
        self.max_dt = max_dt

    def step(self, depth, camera, image=None, timestamp=0.0, index=0) -> OdometryStep:
        i = int(nearest_stamps(self.stamps, np.array([timestamp]), self.max_dt)[0])
        if i < 0:
            raise InputError(f"{self.path}: no pose within {self.max_dt} s of frame "
                             f"{index} (timestamp {timestamp:.6f})")
        return OdometryStep(self.poses[i])
