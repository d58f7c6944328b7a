"""Odometry from another system: a trajectory (a pose file, a ROS bag's pose topic), looked up
by frame (a file, matched as `--poses`) or by timestamp (a topic)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from slamreloc.datasets.poses import MAX_DT, FrameKey, match_poses, read_poses
from slamreloc.errors import InputError
from slamreloc.geometry import Rigid3, nearest_stamps
from slamreloc.slam.odometry import Odometry, OdometryStep


class TrajectoryOdometry(Odometry):
    """`odom_from_cam` of each frame is the trajectory's pose of that frame; the trajectory's
    frame is the odometry frame. It cannot be reset. A trajectory of stamps alone (a ROS bag's
    pose topic) is looked up at the nearest timestamp (within `max_dt` seconds); a file is
    matched to the tracked frames as `--poses` is (`from_file`), and looked up by the frame's
    index in the stream."""

    name = "trajectory"

    def __init__(self, stamps: np.ndarray, poses: list[Rigid3], source: str,
                 max_dt: float = 0.01, by_frame: bool = False):
        """stamps: seconds; poses: camera-to-odometry-frame; source: what errors name (the
        file, or the bag and its topic); by_frame: the poses are the tracked frames' own, one
        for each, in stream order (`stamps` unused)."""
        self.stamps = np.asarray(stamps, dtype=np.float64)
        self.poses = poses
        self.source = source
        self.max_dt = max_dt
        self.by_frame = by_frame

    @classmethod
    def from_file(cls, path: str | Path, keys: list[FrameKey]) -> TrajectoryOdometry:
        """The poses of the tracked frames `keys` (in stream order) in a pose file, read and
        matched by `--poses`' one rule (`datasets.poses`: a TUM file with its names sidecar
        where there is one, a named file or a COLMAP model; by name, else by timestamp, a
        stamp that is a frame of two sequences refused), camera-to-world."""
        matched = match_poses(read_poses(path), keys)
        missing = next((i for i, pose in enumerate(matched) if pose is None), None)
        if missing is not None:  # said before any work, not when the stream reaches it
            key = keys[missing]
            raise InputError(f"{path}: no pose for frame {key.name} (timestamp "
                             f"{key.timestamp or 0.0:.6f}), number {missing + 1} of the "
                             f"{len(keys)} tracked; odometry needs a pose of every frame")
        return cls(np.array([k.timestamp or 0.0 for k in keys]), matched, str(path),
                   MAX_DT, by_frame=True)

    def step(self, depth, camera, image=None, timestamp=0.0, index=0) -> OdometryStep:
        if self.by_frame:
            if not 0 <= index < len(self.poses):
                raise InputError(f"{self.source}: no pose for frame number {index + 1}: it "
                                 f"was matched to {len(self.poses)} frames")
            return OdometryStep(self.poses[index])
        i = int(nearest_stamps(self.stamps, np.array([timestamp]), self.max_dt)[0])
        if i < 0:
            raise InputError(f"{self.source}: no pose within {self.max_dt} s of frame "
                             f"{index} (timestamp {timestamp:.6f})")
        return OdometryStep(self.poses[i])
