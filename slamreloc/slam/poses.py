"""Whole-run trajectories from a backend: the optimised map-frame trajectory and the
odometry-only baseline (the same odometry chained from the same first map-frame pose)."""

from __future__ import annotations

from slamreloc.geometry import Rigid3
from slamreloc.slam.events import EventKind


def _fill(poses: list[Rigid3 | None], motions: list[Rigid3]) -> list[Rigid3 | None]:
    """Fill gaps by chaining per-frame motions (cam_prev_from_cam) forwards, then backwards."""
    out = list(poses)
    for i in range(1, len(out)):
        if out[i] is None and out[i - 1] is not None:
            out[i] = out[i - 1] @ motions[i]
    for i in range(len(out) - 2, -1, -1):
        if out[i] is None and out[i + 1] is not None:
            out[i] = out[i + 1] @ motions[i + 1].inverse()
    return out


def final_trajectory(backend) -> list[Rigid3 | None]:
    """world_from_cam of every frame after the last optimisation; frames on a track that was
    never anchored are dead-reckoned from their neighbours (None if nothing was anchored)."""
    return _fill([backend.pose_of(i) for i in range(len(backend.frames))],
                 [f.motion for f in backend.frames])


def odometry_only_trajectory(backend) -> list[Rigid3 | None]:
    """Odometry motions chained from the first map-frame pose the backend produced."""
    first = next((e for e in backend.event_log if e.kind == EventKind.TRACKING_RECOVERED), None)
    poses: list[Rigid3 | None] = [None] * len(backend.frames)
    if first is None:
        return poses
    poses[first.frame] = first.world_from_cam
    return _fill(poses, [f.motion for f in backend.frames])
