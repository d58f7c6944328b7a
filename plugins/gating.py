"""Consistency gating of relocalizations: when a relocalization is trusted.

A candidate is a relocalized frame with its map-frame pose, PnP inlier count and regressor
confidence. Two candidates *agree* when the odometry between their frames carries one pose
onto the other within (agree_m, agree_deg); a candidate *fits the track* when it is within
(track_m, track_deg) of the backend's current pose of that frame. Candidates that agree with
each other but not with the track prove the track wrong; a lone disagreeing one is rejected.
"""

from __future__ import annotations

from dataclasses import dataclass

from slamreloc.geometry import Rigid3, pose_error


@dataclass(frozen=True)
class GateConfig:
    """Distances in metres, angles in degrees."""

    min_inliers: int = 30
    min_confidence: float = 0.2  # median regressor confidence of the PnP inliers
    agree_m: float = 0.10
    agree_deg: float = 5.0
    track_m: float = 0.15
    track_deg: float = 7.0
    window: int = 6  # a candidate older than this many frames can no longer be confirmed
    # relocalizations that must agree to anchor a lost track. Two consecutive frames in a poorly
    # mapped area can agree on the same wrong pose (a false anchor with 2 on RedKitchen); three
    # did not in any run (BENCHMARKS.md, "SLAM backend")
    votes: int = 3
    # ... and to re-anchor a track that odometry still calls healthy: a second hypothesis
    # against a track with no sign of trouble needs more evidence than one for a lost track
    reanchor_votes: int = 4


@dataclass
class Candidate:
    frame: int
    world_from_cam: Rigid3
    num_inliers: int
    confidence: float
    injected: bool = False  # the test harness replaced this result by a wrong pose
    # a map the session builds: the keyframe the result's inliers mostly came from
    # (`slamreloc.slam.live_map.Reference`, or None where none is known)
    live: bool = False
    reference: object | None = None


def good_quality(c: Candidate, config: GateConfig) -> bool:
    return c.num_inliers >= config.min_inliers and c.confidence >= config.min_confidence


def within(a: Rigid3, b: Rigid3, max_m: float, max_deg: float) -> bool:
    dt, dr = pose_error(a, b)
    return dt <= max_m and dr <= max_deg


def agree(a: Candidate, b: Candidate, backend, config: GateConfig) -> bool:
    """a's pose carried to b's frame by odometry lands within the agreement gate of b's."""
    a_from_b = backend.odometry_between(a.frame, b.frame)
    if a_from_b is None:
        return False
    return within(a.world_from_cam @ a_from_b, b.world_from_cam, config.agree_m,
                  config.agree_deg)


def fits_track(c: Candidate, backend, config: GateConfig) -> bool | None:
    """None when the backend has no map-frame pose for the frame."""
    pose = backend.pose_of(c.frame)
    if pose is None:
        return None
    return within(c.world_from_cam, pose, config.track_m, config.track_deg)


def find_agreeing(new: Candidate, pending: list[Candidate], backend,
                  config: GateConfig) -> list[Candidate]:
    """Pending candidates (inside the window) that agree with `new`."""
    return [c for c in pending if new.frame - c.frame <= config.window
            and agree(c, new, backend, config)]
