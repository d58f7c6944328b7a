"""`slamreloc slam`: track a dataset split with the backend and the relocalization plugin,
optionally kidnapping the camera, and score the result (report + TUM trajectory)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from slamreloc.datasets import load_dataset
from slamreloc.errors import InputError
from slamreloc.map.format import check_is_map
from slamreloc.runtime.progress import track
from slamreloc.slam.backend import BackendConfig, SlamBackend
from slamreloc.slam.events import load_plugin
from slamreloc.slam.feed import depth_camera_of, feed_all, read_frames
from slamreloc.slam.kissicp import KissIcpConfig, KissIcpOdometry
from slamreloc.slam.odometry import Odometry
from slamreloc.slam.report import build_report
from slamreloc.types import Camera


@dataclass
class SlamRunConfig:
    split: str = "test"
    # auto | kiss-icp | open3d | path to a TUM trajectory file | topic:/NAME (a pose topic of
    # the ROS bag being tracked). auto: kiss-icp on depth that is not registered to the image
    # (best drift on RedKitchen), open3d's hybrid RGB-D odometry on registered depth (best on
    # the synthetic scene, whose flat walls make geometry-only ICP slide); see BENCHMARKS.md
    odometry: str = "auto"
    kidnap_every: int = 0  # 0: no kidnapping
    kidnap_skip: int = 20
    backend: BackendConfig = field(default_factory=BackendConfig)
    plugin_options: dict = field(default_factory=dict)  # RelocalizationPlugin keyword args
    progress: bool = True
    poses: Path | None = None  # ground truth from this pose file, not the dataset's (--poses)


def kidnap_schedule(n_frames: int, every: int, skip: int) -> tuple[list[int], list[int]]:
    """(indices of the frames processed, positions in that list where a kidnap landed):
    after every `every` processed frames the next `skip` frames are dropped."""
    kept, jumps, i = [], [], 0
    while i < n_frames:
        kept.append(i)
        i += 1
        if every > 0 and len(kept) % every == 0 and i + skip < n_frames:
            i += skip
            jumps.append(len(kept))
    return kept, jumps


TOPIC_PREFIX = "topic:"  # --odometry topic:/NAME: a pose topic of the ROS bag dataset


def make_odometry(name: str, depth_camera: Camera | None,
                  dataset_dir: Path | None = None) -> Odometry:
    """depth_camera: the camera that took the depth when it is not registered to the image
    (`Frame.depth_camera`, any pixel size: scaled to each depth map), else None; dataset_dir:
    the dataset tracked (a ROS bag, for `topic:/NAME`)."""
    if name == "auto":
        name = "kiss-icp" if depth_camera is not None else "open3d"
    if name == "kiss-icp":
        return KissIcpOdometry(KissIcpConfig(depth_camera=depth_camera))
    if name == "open3d":
        from slamreloc.slam.open3d_odometry import Open3dConfig, Open3dOdometry

        return Open3dOdometry(Open3dConfig(depth_camera=depth_camera))
    from slamreloc.slam.external import TrajectoryOdometry

    if name.startswith(TOPIC_PREFIX):
        from slamreloc.datasets.rosbag import bag_trajectory

        topic = name[len(TOPIC_PREFIX):]
        if dataset_dir is None:
            raise InputError(f"`odometry` {name}: a topic is read from a ROS bag dataset")
        stamps, poses = bag_trajectory(dataset_dir, topic)
        return TrajectoryOdometry(stamps, poses, f"{dataset_dir}: topic {topic}")
    return TrajectoryOdometry.from_file(name)


def run_slam(dataset_dir: Path, map_dir: Path, config: SlamRunConfig = SlamRunConfig(),
             plugins: list | None = None) -> tuple[dict, SlamBackend, list]:
    """Returns (report, backend, processed frames)."""
    check_is_map(map_dir)
    dataset = load_dataset(dataset_dir, config.poses)
    frames = dataset.frames(config.split)
    if not frames:
        raise InputError(f"{dataset_dir}: split '{config.split}' has no frames")
    odometry = make_odometry(config.odometry, depth_camera_of(frames), dataset_dir)
    external = odometry.name == "trajectory"
    if plugins is None:  # each frame's depth comes with its camera (FrameData.depth_camera)
        plugins = [load_plugin("relocalization", map_dir=map_dir, **config.plugin_options)]
    for plugin in plugins:  # before the run: images its features would not fit in memory for
        localizer = getattr(plugin, "localizer", None)
        if localizer is not None:
            localizer.extractor.check_frames(frames)
    backend = SlamBackend(odometry, plugins, config.backend)
    kept, jumps = kidnap_schedule(len(frames), config.kidnap_every, config.kidnap_skip)
    processed = [frames[i] for i in kept]
    inputs = read_frames(dataset, processed, image=True, depth=not external)
    t_backend = feed_all(backend, track(inputs, "slam", total=len(processed),
                                        enabled=config.progress))
    backend.finish()
    report = build_report(backend, processed, jumps, plugins, config, t_backend)
    report["reference"] = dataset.poses_source  # the ATE's ground truth: "dataset" or --poses
    return report, backend, processed
