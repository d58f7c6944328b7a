"""Typed inputs of the viewer: what the user named, and what was read from it."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from slamreloc.geometry import Rigid3
from slamreloc.types import Camera


@dataclass
class ViewerInputs:
    """What `slamreloc view` was given."""

    map_dir: Path
    trajectories: list[Path] = field(default_factory=list)
    reports: list[Path] = field(default_factory=list)
    dataset: Path | None = None  # default: the dataset recorded in the map / reports
    host: str = "127.0.0.1"
    port: int = 8080
    max_points: int = 500_000  # voxel-downsample the map beyond this
    max_images: int = 512  # frustums shown with an image thumbnail
    thumbnail_width: int = 160
    poses: Path | None = None  # the ground truth shown from this pose file (`--poses`)


@dataclass
class FrameView:
    """A posed image: a training camera, a trajectory frame or a query."""

    name: str
    world_from_cam: Rigid3 | None
    image_path: Path | None = None
    thumbnail: np.ndarray | None = None  # (h, w, 3) uint8, small


@dataclass
class MapView:
    root: Path
    points: np.ndarray  # (N, 3) float32, after downsampling
    colors: np.ndarray  # (N, 3) uint8
    n_points_total: int  # before downsampling
    color_source: str  # "image" | "height"
    frames: list[FrameView]  # training cameras
    camera: Camera | None
    pseudo: np.ndarray | None = None  # (N,) bool: a map update's pseudo-label (None: never
    # updated), provenance source PSEUDO or NEW
    pseudo_frames: list[FrameView] = field(default_factory=list)  # frames an update added
    voxel_size: float = 0.0


@dataclass
class Trajectory:
    """A TUM trajectory file; `truth` and `errors_m` are filled when ground truth is known."""

    name: str
    path: Path | None
    stamps: np.ndarray  # (N,) first column (timestamp or index); names below when it held names
    names: list[str | None]
    poses: list[Rigid3]
    kind: str = "estimate"  # "estimate" | "groundtruth"
    truth: list[Rigid3 | None] = field(default_factory=list)
    image_paths: list[Path | None] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.poses)

    @property
    def positions(self) -> np.ndarray:
        return np.array([p.translation for p in self.poses]).reshape(-1, 3)

    @property
    def errors_m(self) -> np.ndarray | None:
        if not self.truth or all(t is None for t in self.truth):
            return None
        return np.array([np.linalg.norm(p.translation - t.translation) if t is not None
                         else np.nan for p, t in zip(self.poses, self.truth)])


@dataclass
class QueryView:
    name: str
    estimate: Rigid3 | None  # None: not localized (or the pose is not known to the viewer)
    truth: Rigid3 | None
    translation_error_m: float | None  # None: failed
    rotation_error_deg: float | None
    num_inliers: int | None
    image_path: Path | None = None

    @property
    def failed(self) -> bool:
        return self.translation_error_m is None


@dataclass
class EvalReport:
    path: Path
    data: dict
    queries: list[QueryView]
    n_without_pose: int = 0  # localized queries whose estimated pose the viewer could not find


@dataclass
class SlamEvent:
    frame: int | None
    timestamp: float | None
    type: str  # relocalization | loop_closure | kidnap | recovery | tracking_lost | other
    accepted: bool
    position: np.ndarray | None  # (3,) map frame; resolved from the trajectory when absent
    label: str = ""


@dataclass
class GraphEdge:
    type: str  # odometry | loop_closure | relocalization | prior | ...
    a: np.ndarray  # (3,)
    b: np.ndarray  # (3,)
    accepted: bool = True


@dataclass
class SlamReport:
    path: Path
    data: dict
    events: list[SlamEvent]
    edges: list[GraphEdge]
    trajectory: Trajectory | None = None


@dataclass
class PseudoLabelReport:
    path: Path
    data: dict
    frames: list[FrameView]  # the registered frames at their estimated poses


@dataclass
class SceneData:
    """Everything the scene is built from (no viser objects: unit tests can build one)."""

    map: MapView
    trajectories: list[Trajectory] = field(default_factory=list)
    evaluations: list[EvalReport] = field(default_factory=list)
    slams: list[SlamReport] = field(default_factory=list)
    pseudo_labels: list[PseudoLabelReport] = field(default_factory=list)
    max_images: int = 512
    thumbnail_width: int = 160

    def reports(self) -> list[tuple[str, Path, dict]]:
        """(kind, path, data) of every report, for the numbers panel."""
        return ([("evaluate", r.path, r.data) for r in self.evaluations]
                + [("slam", r.path, r.data) for r in self.slams]
                + [("pseudo-label", r.path, r.data) for r in self.pseudo_labels])
