"""Sequence smoothing of registered poses with depth odometry and the SLAM backend's pose graph.

Single-image registrations (PnP on inherited labels) are each a few centimetres off, and those
errors change from frame to frame; depth odometry is precise over short stretches. The SLAM
backend fuses both: odometry between-factors plus every registration as a robust (Cauchy) prior
in the map frame, optimised as a whole. Frames that could not be registered on their own get
their pose from the odometry through them.
"""

from __future__ import annotations

from dataclasses import dataclass

from slamreloc.datasets import Dataset, read_depth, read_image
from slamreloc.geometry import Rigid3
from slamreloc.progress import track
from slamreloc.slam.backend import SlamBackend, TrackState
from slamreloc.slam.events import Event, EventKind, FrameData
from slamreloc.slam.poses import final_trajectory
from slamreloc.slam.run import make_odometry
from slamreloc.types import Frame


class RegistrationPriors:
    """Backend plugin: hands each frame's registered pose to the graph (anchor, then priors)."""

    name = "registration-priors"

    def __init__(self, poses: list[Rigid3 | None]):
        self.poses = poses

    def attach(self, backend: SlamBackend) -> None:
        self.backend = backend

    def on_event(self, event: Event, frame: FrameData) -> None:
        pose = self.poses[frame.index] if event.kind == EventKind.FRAME else None
        if pose is None:
            return
        if self.backend.state == TrackState.TRACKING:
            self.backend.add_loop_closure(frame.index, pose)
        else:
            self.backend.anchor(frame.index, pose)


@dataclass
class SmoothingResult:
    world_from_cam: list[Rigid3 | None]  # per frame, map frame; None on never-anchored tracks
    n_tracking_lost: int


def smooth_poses(dataset: Dataset, frames: list[Frame], poses: list[Rigid3 | None],
                 progress: bool = True) -> SmoothingResult | None:
    """Fuse registered `poses` (world_from_cam or None, per frame of `frames`, in sequence
    order) with depth odometry; None when the frames have no depth."""
    if any(f.depth_path is None for f in frames):
        return None
    depth_k = dataset.depth_intrinsics
    backend = SlamBackend(make_odometry("auto", depth_k), [RegistrationPriors(poses)])
    for f in track(frames, "smoothing with odometry", enabled=progress):
        image = read_image(f.image_path) if dataset.depth_registered else None  # hybrid odometry
        backend.process(image, read_depth(f.depth_path, dataset.depth_units_per_metre), f.camera,
                        timestamp=f.timestamp)
    backend.finish()
    lost = sum(e.kind == EventKind.TRACKING_LOST for e in backend.event_log)
    return SmoothingResult(final_trajectory(backend), lost)
