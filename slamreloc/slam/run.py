"""`slamreloc slam`: track a dataset split with the backend and the relocalization plugin,
optionally kidnapping the camera, and score the result (report + TUM trajectory).

With `out`, the session learns its map while it tracks (the live-mapping plugin and a
`LiveMap`, slamreloc.slam.live_map): from nothing, or extending the map it is given (which it
then starts lost in, and never writes); the map is written to `out` every
`save_every_s` seconds, at the end, and on Ctrl-C or SIGTERM."""

from __future__ import annotations

import os
import signal
import threading
import warnings
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from slamreloc.datasets import load_dataset
from slamreloc.datasets.poses import FrameKey
from slamreloc.errors import InputError, Interrupted
from slamreloc.geometry import Rigid3, align_poses
from slamreloc.map.format import check_is_map
from slamreloc.map.joining import check_joining, check_one_camera
from slamreloc.runtime.progress import track
from slamreloc.slam.backend import BackendConfig, SlamBackend
from slamreloc.slam.events import load_plugin
from slamreloc.slam.feed import depth_camera_of, feed_all, read_frames
from slamreloc.slam.kissicp import KissIcpConfig, KissIcpOdometry
from slamreloc.slam.live_map import LiveMap, LiveMapConfig
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
    kidnap_from: int = 0  # processed frames before the first kidnap's count starts
    backend: BackendConfig = field(default_factory=BackendConfig)
    plugin_options: dict = field(default_factory=dict)  # RelocalizationPlugin keyword args
    progress: bool = True
    poses: Path | None = None  # ground truth from this pose file, not the dataset's (--poses)
    live: LiveMapConfig = field(default_factory=LiveMapConfig)  # the map learned with `out`
    save_every_s: float = 30.0  # a learned map is written this often (0: only at the end)


def kidnap_schedule(n_frames: int, every: int, skip: int, start: int = 0
                    ) -> tuple[list[int], list[int]]:
    """(indices of the frames processed, positions in that list where a kidnap landed):
    after every `every` processed frames the next `skip` frames are dropped; with `start`, the
    first kidnap lands after `start` processed frames, the next ones `every` frames apart."""
    kept, jumps, i = [], [], 0
    while i < n_frames:
        kept.append(i)
        i += 1
        after = len(kept) - start
        if every > 0 and after >= 0 and after % every == 0 and i + skip < n_frames:
            i += skip
            jumps.append(len(kept))
    return kept, jumps


TOPIC_PREFIX = "topic:"  # --odometry topic:/NAME: a pose topic of the ROS bag dataset


def make_odometry(name: str, depth_camera: Camera | None,
                  dataset_dir: Path | None = None,
                  frames: list[FrameKey] | None = None) -> Odometry:
    """depth_camera: the camera that took the depth when it is not registered to the image
    (`Frame.depth_camera`, any pixel size: scaled to each depth map), else None; dataset_dir:
    the dataset tracked (a ROS bag, for `topic:/NAME`); frames: the frames tracked, in stream
    order, which a pose file's poses are matched to (`TrajectoryOdometry.from_file`)."""
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
    if not os.path.lexists(name):
        raise InputError(f"`odometry` {name!r}: not auto, kiss-icp, open3d, {TOPIC_PREFIX}/NAME "
                         "or an existing TUM trajectory file")
    if frames is None:
        raise InputError(f"`odometry` {name}: a pose file is matched to a dataset's frames")
    return TrajectoryOdometry.from_file(name, frames)


def _live_plugins(dataset, map_dir: Path | None, out: Path, config: SlamRunConfig) -> list:
    """The live-mapping plugin and the relocalization plugin sharing one `LiveMap`."""
    from slamreloc.map.meta import DatasetMeta
    from slamreloc.map.scene_map import SceneMap

    prior = None if map_dir is None else SceneMap.load(map_dir)
    frames = dataset.frames(config.split)
    held = None
    if prior is not None:
        held = check_joining(prior, map_dir, dataset, frames)
    else:
        check_one_camera(dataset, frames)
    live = LiveMap(config.live, prior=prior, held=held)
    recorded = DatasetMeta(root=str(dataset.root.resolve()), kind=dataset.kind,
                           split=config.split, metric=True, poses="slam")
    return [load_plugin("live_mapping", live_map=live, out=out, dataset=recorded,
                        save_every_s=config.save_every_s),
            load_plugin("relocalization", localizer=live, **config.plugin_options)]


def run_slam(dataset_dir: Path, map_dir: Path | None, config: SlamRunConfig = SlamRunConfig(),
             plugins: list | None = None, out: Path | None = None
             ) -> tuple[dict, SlamBackend, list]:
    """Returns (report, backend, processed frames). `out`: learn the map while tracking and
    write it there (from nothing where `map_dir` is None, else extending that map)."""
    if map_dir is not None:
        check_is_map(map_dir)
    elif out is None:
        raise InputError("`map` or `out` is needed: a map to relocalize in, or one to learn")
    dataset = load_dataset(dataset_dir, config.poses)
    frames = dataset.frames(config.split)
    if not frames:
        raise InputError(f"{dataset_dir}: split '{config.split}' has no frames")
    kept, jumps = kidnap_schedule(len(frames), config.kidnap_every, config.kidnap_skip,
                                  config.kidnap_from)
    if config.kidnap_every > 0 and not jumps:  # asked for, and never happens: said so
        warnings.warn(
            f"{dataset_dir}: split '{config.split}' has {len(frames)} frames, and no kidnap "
            f"fits in them: the first lands after {config.kidnap_from} processed frames and "
            f"skips {config.kidnap_skip}, which needs more than "
            f"{config.kidnap_from + config.kidnap_skip} frames (lower `kidnap_from`, "
            "`kidnap_every` or `kidnap_skip`); tracking without kidnaps", stacklevel=2)
    processed = [frames[i] for i in kept]
    odometry = make_odometry(config.odometry, depth_camera_of(frames), dataset_dir,
                             [FrameKey.of(f, Path(dataset.root)) for f in processed])
    external = odometry.name == "trajectory"
    if out is not None and external:
        raise InputError("a learned map (`out`) needs depth: its rows are lifted from each "
                         "keyframe's depth, which `odometry` from a trajectory does not read")
    if plugins is None and out is not None:
        plugins = _live_plugins(dataset, map_dir, out, config)
    elif plugins is None:  # each frame's depth comes with its camera (FrameData.depth_camera)
        from slamreloc.map.scene_map import SceneMap

        scene_map = SceneMap.load(map_dir)
        plugins = [load_plugin("relocalization", scene_map=scene_map, **config.plugin_options)]
    for plugin in plugins:  # before the run: images its features would not fit in memory for
        localizer = getattr(plugin, "localizer", None)
        if localizer is not None:
            localizer.extractor.check_frames(frames)
    backend = SlamBackend(odometry, plugins, config.backend)
    inputs = read_frames(dataset, processed, image=True, depth=not external)
    mapper = next((p for p in plugins if isinstance(getattr(p, "live_map", None), LiveMap)),
                  None)
    with _sigterm_interrupts(mapper is not None), _learner_stopped(mapper):
        try:
            t_backend = feed_all(backend, track(inputs, "slam", total=len(processed),
                                                enabled=config.progress))
            backend.finish()
            if mapper is not None:
                mapper.live_map.finish()
                written = mapper.save()
                if written is None and mapper.live_map.adds_nothing:
                    raise InputError(
                        f"{mapper.out}: no map written: the session added no keyframe to "
                        f"{map_dir} (it never anchored in it, or saw nothing it lacks): "
                        "track a split that overlaps the map's places and goes beyond them")
                if written is None:
                    raise InputError(
                        f"{mapper.out}: no map written: the session labelled "
                        f"{mapper.live_map.store.n_rows} keypoints with depth in "
                        f"{mapper.live_map.store.n_keyframes} keyframes; a map needs "
                        f"{config.live.learner.min_rows}: track a longer split (`split`) or "
                        "frames with more texture and valid depth")
        except KeyboardInterrupt:
            if mapper is None or mapper.out is None:
                raise
            mapper.live_map.learner.stop()  # the last published model is what is saved
            written = mapper.save(at_once=True)
            raise Interrupted(
                f"{mapper.out}: the session was interrupted after {len(backend.frames)} frames; "
                + ("the map as it stood is saved there" if written else
                   f"no map was written (no keyframe was added to {map_dir})"
                   if mapper.live_map.adds_nothing else
                   "no map was written (no training round had ended)")) from None
    prior = None  # a map a session learned is in that session's frame
    if mapper is not None:
        prior = mapper.live_map.prior
    elif map_dir is not None:  # the plugin's map where it holds one, else read again
        prior = next((p.localizer.map for p in plugins
                      if getattr(getattr(p, "localizer", None), "map", None) is not None), None)
        if prior is None:
            from slamreloc.map.scene_map import SceneMap

            prior = SceneMap.load(map_dir, regressor=False)
    report = build_report(backend, processed, jumps, plugins, config, t_backend,
                          own_frame=mapper is not None and prior is None,
                          map_from_truth=learned_map_frame(prior, dataset))
    report["reference"] = dataset.poses_source  # the ATE's ground truth: "dataset" or --poses
    if mapper is not None:
        report["live_map"] = live_map_report(mapper, t_backend)
    return report, backend, processed


def learned_map_frame(scene_map, dataset) -> Rigid3 | None:
    """map_from_truth for a map a SLAM session learned (`SceneMap.session_frames`): the rigid
    alignment of the dataset's poses onto the map's frames, by name; None for any other map
    (or one whose frames the dataset does not name)."""
    frames = None if scene_map is None else scene_map.session_frames()
    if frames is None:
        return None
    truth = {f.name: f.world_from_cam for f in dataset.frames("all")
             if f.world_from_cam is not None}
    common = [n for n in frames if n in truth]
    if len(common) < 3:
        return None
    return align_poses([truth[n] for n in common], [frames[n] for n in common],
                       with_scale=False).rigid


@contextmanager
def _learner_stopped(mapper):
    """However the session ends, its learner's thread has ended when this block is left
    (`BackgroundLearner.stop`)."""
    try:
        yield
    finally:
        if mapper is not None:
            mapper.live_map.learner.stop()


@contextmanager
def _sigterm_interrupts(enabled: bool):
    """While a learned map is at stake, SIGTERM interrupts as Ctrl-C does (the map is then
    written before the process ends); the previous handler is restored after."""
    if not enabled or threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def live_map_report(mapper, t_backend_s: float) -> dict:
    """What the report says of a learned map: its rows, keyframes and feature links (the
    keyframes' registrations on each other, `LiveMap.link`), each training round
    (start and end in seconds since the session started, rows, from scratch or warm), the
    learner's busy share of the session's wall time, and the writes."""
    live = mapper.live_map
    learner = live.learner
    return {"out": str(mapper.out), "n_rows": live.store.n_rows,
            "n_keyframes": live.store.n_session_keyframes,
            "n_prior_frames": live.store.n_keyframes - live.store.n_session_keyframes,
            "n_feature_links": live.backend.graph.n_links if live.backend is not None else 0,
            "keyframe_rows_s": round(live.t_keyframes_s, 3),
            "rounds": [{"started_s": round(r.started_s, 3), "ended_s": round(r.ended_s, 3),
                        "n_rows": r.n_rows, "scratch": r.scratch,
                        "final_loss_m": None if r.final_loss_m is None
                        else round(r.final_loss_m, 4)} for r in learner.rounds],
            "learner_busy_s": round(learner.busy_s, 3),
            "learner_share": round(learner.busy_s / t_backend_s, 3) if t_backend_s else None,
            "n_writes": mapper.n_saves}
