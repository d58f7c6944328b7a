"""Odometry from another system: a trajectory (a TUM file, a ROS bag's pose topic), looked up
by frame timestamp."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from slamreloc.errors import InputError
from slamreloc.geometry import Rigid3, nearest_stamps
from slamreloc.slam.odometry import Odometry, OdometryStep
from slamreloc.slam.trajectory import read_tum


class TrajectoryOdometry(Odometry):
    """`odom_from_cam` of each frame is the trajectory's pose at the nearest timestamp (within
    `max_dt` seconds); the trajectory's frame is the odometry frame. It cannot be reset."""

    name = "trajectory"

    def __init__(self, stamps: np.ndarray, poses: list[Rigid3], source: str,
                 max_dt: float = 0.01):
        """stamps: seconds; poses: camera-to-odometry-frame; source: what errors name (the
        file, or the bag and its topic)."""
        self.stamps = np.asarray(stamps, dtype=np.float64)
        self.poses = poses
        self.source = source
        self.max_dt = max_dt

    @classmethod
    def from_file(cls, path: str | Path, max_dt: float = 0.01) -> TrajectoryOdometry:
        """A TUM trajectory file (`stamp tx ty tz qx qy qz qw`, camera-to-world)."""
        return cls(*read_tum(Path(path)), str(path), max_dt)

    def step(self, depth, camera, image=None, timestamp=0.0, index=0) -> OdometryStep:
        i = int(nearest_stamps(self.stamps, np.array([timestamp]), self.max_dt)[0])
        if i < 0:
            raise InputError(f"{self.source}: no pose within {self.max_dt} s of frame "
                             f"{index} (timestamp {timestamp:.6f})")
        return OdometryStep(self.poses[i])
