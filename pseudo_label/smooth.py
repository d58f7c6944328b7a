"""Sequence smoothing of registered poses with depth odometry and the SLAM backend's pose graph.

Single-image registrations (PnP on inherited labels) are each a few centimetres off, and those
errors change from frame to frame; depth odometry is precise over short stretches but drifts
over long ones. The SLAM backend fuses both: odometry between-factors plus every registration
as a robust (Cauchy) prior in the map frame, each with its own sigma scale (how much it is
trusted), optimised as a whole. Frames that could not be registered on their own get their pose
from the odometry through them.

The priors (`smooth_states`): a registered frame's registration on the map's own labels alone,
where it holds, else its chain registration (through the sequence's own pseudo-labels) with
`RegistrationConfig.chain_prior_sigma_scale` times the sigmas. Every frame then takes the fused
pose and inherits the map labels that fit it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slamreloc.datasets import Dataset
from slamreloc.geometry import Rigid3, pose_error
from slamreloc.runtime.progress import track
from slamreloc.pseudo_label.register import (Database, FrameState, RegistrationConfig,
                                             label_at_pose, register_on)
from slamreloc.map.scene_map import MapDatabase
from slamreloc.slam.backend import SlamBackend, TrackState
from slamreloc.slam.events import Event, EventKind, FrameData
from slamreloc.slam.feed import depth_camera_of, feed_all, read_frames
from slamreloc.slam.poses import final_trajectory
from slamreloc.slam.run import make_odometry
from slamreloc.types import Features, Frame


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
    depth_camera = depth_camera_of(frames)  # None: depth registered to the images
    backend = SlamBackend(make_odometry("auto", depth_camera), [RegistrationPriors(priors)])
    # images only for open3d's hybrid odometry (registered depth): no plugin here reads them
    inputs = read_frames(dataset, frames, image=depth_camera is None, depth=True)
    feed_all(backend, track(inputs, "smoothing with odometry", total=len(frames),
                            enabled=progress))
    backend.finish()
    lost = sum(e.kind == EventKind.TRACKING_LOST for e in backend.event_log)
    return SmoothingResult(final_trajectory(backend), lost)


def smooth_states(frames: list[Frame], feats: list[Features], states: list[FrameState],
                  base: MapDatabase, anchored: np.ndarray, smoother, rc: RegistrationConfig,
                  progress: bool = False) -> tuple[list[FrameState], int] | None:
    """Each registered frame is registered again on the map's own labels alone; where that
    holds (enough inliers, near the chain's pose) it becomes a prior of the odometry pose graph,
    independent of the chain (registrations through the sequence's own pseudo-labels drift with
    the chain that made them). The other registered frames give their chain pose as a prior
    `rc.chain_prior_sigma_scale` times less certain: beyond the map the chain drifts less than
    long stretches of odometry. Every frame then takes the graph's pose and inherits only map
    labels that fit it. Returns (states, number of map priors), or None without a smoother.
    `progress`: a bar over the frames' matching with the map."""
    if smoother is None:
        return None
    rows = np.flatnonzero(anchored)
    db = Database(base.descriptors[rows].astype(np.float32), base.points[rows], rows)
    corr, on_map = [], []  # correspondences for priors and labels; priors on the map alone
    for s, f, frame in track(list(zip(states, feats, frames)), "matching with the map",
                             enabled=progress):
        corr.append(db.correspondences(f.descriptors, rc))
        on_map.append(map_prior(s, f, frame.camera, corr[-1], rc) if s.registered else None)
    n_priors = sum(p is not None for p in on_map)
    priors = [graph_prior(p, s, rc) for p, s in zip(on_map, states)]
    poses = smoother(priors) if n_priors else None
    if poses is None:
        return None
    out = []
    for f, s, pose, frame, c in zip(feats, states, poses, frames, corr):
        pose = pose if pose is not None else s.world_from_cam  # off the graph: keep the chain's
        if pose is None:
            out.append(FrameState.empty(len(f)))
            continue
        new = label_at_pose(f, frame.camera, pose, c, rc)
        new.via = s.via if s.registered else "odometry"
        out.append(new)
    return out, n_priors


def map_prior(state: FrameState, f: Features, camera, corr: tuple,
              rc: RegistrationConfig) -> Rigid3 | None:
    """The frame's registration on its correspondences with the map's labels alone, if it has
    `anchor_inliers` and lies near the chain's pose; else None."""
    on_map = register_on(corr, f, camera, rc)
    if on_map is None or on_map.num_inliers < rc.anchor_inliers:
        return None
    dt, dr = pose_error(on_map.world_from_cam, state.world_from_cam)
    ok = dt <= rc.prior_agreement_m and dr <= rc.prior_agreement_deg
    return on_map.world_from_cam if ok else None


def graph_prior(on_map: Rigid3 | None, state: FrameState, rc: RegistrationConfig
                ) -> Prior | None:
    """The frame's prior in the pose graph: its registration on the map's labels, else its
    chain registration with `chain_prior_sigma_scale` times the sigmas (0: none)."""
    if on_map is not None:
        return Prior(on_map)
    if state.registered and rc.chain_prior_sigma_scale > 0:
        return Prior(state.world_from_cam, rc.chain_prior_sigma_scale)
    return None
