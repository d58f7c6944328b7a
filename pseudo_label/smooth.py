"""Sequence smoothing of registered poses with depth odometry and the SLAM backend's pose graph.

Single-image registrations (PnP on inherited labels) are each a few centimetres off, and those
errors change from frame to frame; depth odometry is precise over short stretches but drifts
over long ones. The SLAM backend fuses both: odometry between-factors plus every registration
as a robust (Cauchy) prior in the map frame, each with its own sigma scale (how much it is
trusted), optimised as a whole. Frames that could not be registered on their own get their pose
from the odometry through them.
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


@dataclass(frozen=True)
class Prior:
    """A registration of one frame in the map frame; `sigma_scale` times the graph's
    relocalization sigmas (GraphConfig.reloc_sigma_m / _rad)."""

    world_from_cam: Rigid3
    sigma_scale: float = 1.0


class RegistrationPriors:
    """Backend plugin: hands each frame's registered pose to the graph (anchor, then priors)."""

    name = "registration-priors"

    def __init__(self, priors: list[Prior | None]):
        self.priors = priors

    def attach(self, backend: SlamBackend) -> None:
        self.backend = backend

    def on_event(self, event: Event, frame: FrameData) -> None:
        prior = self.priors[frame.index] if event.kind == EventKind.FRAME else None
        if prior is None:
            return
        if self.backend.state == TrackState.TRACKING:
            self.backend.add_loop_closure(frame.index, prior.world_from_cam, prior.sigma_scale)
        else:
            self.backend.anchor(frame.index, prior.world_from_cam)


@dataclass
class SmoothingResult:
    world_from_cam: list[Rigid3 | None]  # per frame, map frame; None on never-anchored tracks
    n_tracking_lost: int


def smooth_poses(dataset: Dataset, frames: list[Frame], priors: list[Prior | None],
                 progress: bool = True) -> SmoothingResult | None:
    """Fuse registered poses (a Prior or None per frame of `frames`, in sequence order) with
    depth odometry; None when the frames have no depth."""
    if any(f.depth_path is None for f in frames):
        return None
    depth_k = dataset.depth_intrinsics
    backend = SlamBackend(make_odometry("auto", depth_k), [RegistrationPriors(priors)])
    for f in track(frames, "smoothing with odometry", enabled=progress):
        image = read_image(f.image_path) if dataset.depth_registered else None  # hybrid odometry
        backend.process(image, read_depth(f.depth_path, dataset.depth_units_per_metre), f.camera,
                        timestamp=f.timestamp)
    backend.finish()
    lost = sum(e.kind == EventKind.TRACKING_LOST for e in backend.event_log)
    return SmoothingResult(final_trajectory(backend), lost)
