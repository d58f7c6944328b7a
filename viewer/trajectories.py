"""Trajectories the viewer draws: TUM files, and the ground truth of their poses (by frame
name, by timestamp within a dataset sequence, or from a ground-truth trajectory file)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from slamreloc.datasets.poses import poses_by_name
from slamreloc.errors import InputError
from slamreloc.geometry import nearest_stamps, read_named_trajectory
from slamreloc.io.fileio import open_regular
from slamreloc.viewer.data import Trajectory
from slamreloc.viewer.images import frames_by_name

GT_NAME = re.compile(r"(^|[^a-z])(gt|groundtruth|ground_truth|ground-truth)([^a-z]|$)", re.I)

def read_trajectory(path: str | Path, kind: str | None = None,
                    allow_empty: bool = False) -> Trajectory:
    """A TUM file `stamp tx ty tz qx qy qz qw` (camera-to-world), read by the core's
    `read_named_trajectory`: the first column may also be a frame name (older `evaluate`
    files), and the sidecar `<stem>.names.txt` that `evaluate --trajectory` writes names
    numeric stamps. `allow_empty`: a file of no poses is a trajectory of none (a slam
    session that never anchored writes one), else an error."""
    path = Path(path)
    # missing, or there and not a regular file (a named pipe, a device, a folder): one line
    # naming its kind, checked without blocking (`open_regular`)
    open_regular(path, "trajectory").close()
    tum = read_named_trajectory(path)
    poses_by_name(path, tum.names, tum.poses)  # one pose per frame, as every pose reader
    if not tum.poses and not allow_empty:
        raise InputError(f"{path}: no poses in the trajectory file")
    if kind is None:
        kind = "groundtruth" if GT_NAME.search(path.stem) else "estimate"
    return Trajectory(path.stem, path, tum.stamps, tum.names, tum.poses, kind)


def attach_truth(traj: Trajectory, dataset) -> None:
    """Ground truth and images for each pose: by frame name, else by timestamp within the
    dataset sequence that matches most of the trajectory's stamps. Sequences often share
    their timestamps (frame index / rate); among equally good ones the sequence whose poses
    lie nearest the trajectory's (median distance) is taken."""
    if dataset is None:
        return
    by_name = frames_by_name(dataset)
    matched = [by_name.get(n) if n else None for n in traj.names]
    if sum(m is not None for m in matched) < len(traj) / 2:
        best, best_key = None, (0, 0.0)
        for frames in dataset.sequences.values():
            j = nearest_stamps([f.timestamp for f in frames], traj.stamps, 1e-3)
            cand = [frames[k] if k >= 0 else None for k in j]
            key = (int((j >= 0).sum()), -_median_distance(traj, cand))
            if key > best_key:
                best, best_key = cand, key
        if best is not None and best_key[0] >= len(traj) / 2:
            matched = best
    traj.truth = [m.world_from_cam if m is not None else None for m in matched]
    traj.image_paths = [m.image_path if m is not None else None for m in matched]
    if not any(n for n in traj.names):
        traj.names = [m.name if m is not None else None for m in matched]


def _median_distance(traj: Trajectory, frames: list) -> float:
    """Median distance (m) between the trajectory's camera centres and those frames' (where
    known); inf when none is."""
    d = [np.linalg.norm(p.translation - f.world_from_cam.translation)
         for p, f in zip(traj.poses, frames) if f is not None and f.world_from_cam is not None]
    return float(np.median(d)) if d else float("inf")


def truth_by_stamp(traj: Trajectory, truth: Trajectory, max_dt: float = 0.02) -> None:
    """Ground truth from a ground-truth trajectory file: the nearest stamp within max_dt."""
    if len(truth) == 0:
        return
    j = nearest_stamps(truth.stamps, traj.stamps, max_dt)
    traj.truth = [truth.poses[k] if k >= 0 else None for k in j]
    if truth.image_paths:
        traj.image_paths = [truth.image_paths[k] if k >= 0 else None for k in j]


def truth_trajectory(est: Trajectory) -> Trajectory | None:
    """The ground truth of an estimate's frames, as its own (green) trajectory."""
    keep = [i for i, t in enumerate(est.truth) if t is not None]
    if not keep:
        return None
    return Trajectory(f"{est.name} (ground truth)", None, est.stamps[keep],
                      [est.names[i] for i in keep], [est.truth[i] for i in keep], "groundtruth",
                      [est.truth[i] for i in keep], [est.image_paths[i] for i in keep])
