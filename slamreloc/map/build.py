"""`build_map`: features -> scene-coordinate labels -> trained regressor -> map folder."""

from __future__ import annotations

import hashlib
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from slamreloc.datasets import Dataset
from slamreloc.errors import InputError
from slamreloc.features.extract import extract_with_pictures
from slamreloc.features import make_extractor
from slamreloc.io.outputs import check_outputs
from slamreloc.map.augment import AugmentConfig, augmented_rows
from slamreloc.map.joining import check_one_camera
from slamreloc.map.labels import LabelConfig, LabelSet, build_labels
from slamreloc.map.format import SURFACE, is_map
from slamreloc.map.lock import map_write_lock
from slamreloc.map.meta import (CameraMeta, DatasetMeta, FeatureMeta, MapMeta, RegressorMeta,
                                SurfaceMeta)
from slamreloc.map.write import check_map_target, save_map
from slamreloc.runtime.progress import console
from slamreloc.regressor.checkpoint import check_settings, checkpoint_path, run_settings
from slamreloc.regressor.model import RegressorConfig, SceneCoordinateRegressor
from slamreloc.regressor.train import TrainConfig, resolve_device, train_regressor
from slamreloc.rgbd import registered_depths
from slamreloc.map.scene_map import MapDatabase, SceneMap
from slamreloc.map.surface import SurfaceConfig, dataset_surface
from slamreloc.types import Features, Frame


@dataclass
class MapConfig:
    features: str = "sift"
    feature_options: dict = field(default_factory=dict)  # e.g. {"weights": path} for superpoint
    arch: str = "wide"
    labels: LabelConfig = field(default_factory=LabelConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    device: str = "auto"
    surface: SurfaceConfig | None = field(default_factory=SurfaceConfig)  # None: no surface
    augment: AugmentConfig = field(default_factory=AugmentConfig)  # simulated views (training)


def labelled_database(frames: list[Frame], feats: list[Features], labels: LabelSet,
                      pictures: list[str] | None = None) -> MapDatabase:
    """The labelled rows of `frames` (their `pictures`, `io.images.picture_digest`, where
    known)."""
    keep = [~np.isnan(p[:, 0]) for p in labels.points]
    return MapDatabase(
        descriptors=np.concatenate([f.descriptors[k] for f, k in zip(feats, keep)]),
        points=np.concatenate([p[k] for p, k in zip(labels.points, keep)]),
        keypoints=np.concatenate([f.keypoints[k] for f, k in zip(feats, keep)]),
        frame_index=np.concatenate([np.full(k.sum(), i) for i, k in enumerate(keep)]),
        frame_names=[f.name for f in frames],
        world_from_cam=np.stack([f.world_from_cam.matrix() for f in frames]),
        frame_pictures=list(pictures or ()))


def _shaping(config: MapConfig) -> dict:
    """The settings that shape a map (what a resumed run must share with the interrupted
    one): all but where and how precisely it trains (device, precision, checkpoint period)."""
    shaping = asdict(config)
    del shaping["device"]
    shaping["train"] = {k: v for k, v in shaping["train"].items()
                        if k not in ("precision", "checkpoint_every_s")}
    return shaping


def depth_labels(dataset: Dataset, config: MapConfig) -> bool:
    """Whether depth labels keypoints (else tracks are triangulated from the poses alone).
    Only with the dataset's own poses: a depth sensor's poses were made from that depth and
    share its frame and scale. Poses from elsewhere (`--poses`, e.g. SfM, metric to ~1 %) need
    not: their labels come from triangulation, which agrees with the poses by construction
    (BENCHMARKS.md, "Localization on RedKitchen, against both references")."""
    return config.labels.use_depth and dataset.poses_source == "dataset"


def build_map(dataset: Dataset, out: Path, split: str = "train", config: MapConfig = MapConfig(),
              progress: bool = True, resume: bool = False) -> SceneMap:
    """Map a split of `dataset` into the folder `out` (written atomically). Training state is
    checkpointed beside `out`; `resume` continues an interrupted run from it.

    The write lock of `out` is held for the whole run, not only while saving: a second writer
    of the same map (and its checkpoint) fails at once instead of after its work."""
    _check_target(dataset, Path(out))  # before the lock, which is written beside `out`
    with map_write_lock(out):
        return _build_map(dataset, Path(out), split, config, progress, resume)


def _check_target(dataset: Dataset, out: Path) -> None:
    poses_file = None if dataset.poses_source == "dataset" else dataset.poses_source
    check_outputs({"the map": out}, {"the dataset": dataset.root, "`poses`": poses_file},
                  folders={"the map": (is_map, "a slamreloc map")})


def _build_map(dataset: Dataset, out: Path, split: str, config: MapConfig, progress: bool,
               resume: bool) -> SceneMap:
    _check_target(dataset, out)
    check_map_target(out)  # fail before the work, not after it
    try:
        resolve_device(config.device)  # a device that is not there: now, not after features
    except ValueError as err:
        raise InputError(str(err)) from None
    ckpt = checkpoint_path(out)
    if resume and not ckpt.is_file():
        raise InputError(f"{out}: `resume`: no interrupted training of this map to resume "
                         "(training cut short leaves one; leave `resume` out to start anew)")
    frames = dataset.frames(split)
    if not frames:
        raise InputError(f"{dataset.root}: split '{split}' has no frames")
    check_one_camera(dataset, frames)  # a map holds one camera
    unposed = [f.name for f in frames if f.world_from_cam is None]
    if unposed:
        raise InputError(f"{dataset.poses_origin}: frame {unposed[0]} has no pose; mapping "
                         "needs poses")
    settings = run_settings(
        dataset=str(dataset.root), poses=str(dataset.poses_origin), split=split,
        frames=hashlib.sha256("\n".join(f.name for f in frames).encode()).hexdigest()[:16],
        config=_shaping(config))
    if resume:
        check_settings(ckpt, settings)  # now, not after the features and labels
    extractor = make_extractor(config.features, **config.feature_options)
    timings = {}
    t0 = time.perf_counter()
    feats, pictures = extract_with_pictures(frames, extractor, progress)
    timings["features_s"] = time.perf_counter() - t0
    depths = registered_depths(dataset, frames) if depth_labels(dataset, config) else None
    t0 = time.perf_counter()
    labels = build_labels(frames, feats, depths, config.labels, progress)
    timings["labels_s"] = time.perf_counter() - t0
    db = labelled_database(frames, feats, labels, pictures)
    if len(db.points) < 100:
        raise InputError(f"{dataset.root}: only {len(db.points)} keypoints could be labelled; "
                         "are the poses and intrinsics right?")
    console.print(f"labels: {labels.stats['n_labelled']} of {labels.stats['n_keypoints']} keypoints "
                  f"({100 * labels.stats['labelled_fraction']:.1f} %), median reprojection error "
                  f"{labels.stats['median_reproj_error_px'] or 0:.2f} px, "
                  f"{labels.stats['n_depth_labels']} from depth")
    t0 = time.perf_counter()
    surface = None if config.surface is None else dataset_surface(dataset, frames,
                                                                  config.surface, progress)
    timings["surface_s"] = time.perf_counter() - t0
    descriptors, points = db.descriptors, db.points
    if config.augment.views:
        t0 = time.perf_counter()
        more_d, more_p = augmented_rows(frames, feats, labels.points, extractor,
                                        config.augment, progress)
        descriptors = np.concatenate([descriptors, more_d])
        points = np.concatenate([points, more_p])
        timings["augment_s"] = time.perf_counter() - t0
    model = SceneCoordinateRegressor(RegressorConfig.preset(config.arch, extractor.dim))
    t0 = time.perf_counter()
    train_stats = train_regressor(model, descriptors, points, config.train, config.device,
                                  progress, checkpoint=ckpt, resume=resume, settings=settings)
    if config.augment.views:
        train_stats = {**train_stats, "augment": config.augment.to_dict(),
                       "n_augmented_rows": len(points) - len(db.points)}
    timings["train_s"] = time.perf_counter() - t0
    meta = MapMeta(
        features=FeatureMeta(config.features, extractor.config_dict()),
        regressor=RegressorMeta(config.arch, model.config.to_dict(), model.num_parameters()),
        train={**config.train.to_dict(), **train_stats},
        labels=labels.stats,
        camera=CameraMeta.from_camera(frames[0].camera),
        dataset=DatasetMeta(root=str(dataset.root.resolve()), kind=dataset.kind, split=split,
                            metric=dataset.metric, poses=dataset.poses_source),
        timings_s=timings,
        surface=None if surface is None else SurfaceMeta(n_points=len(surface.points),
                                                         voxel_m=config.surface.voxel_m))
    extra = {} if surface is None else {SURFACE: surface.to_arrays()}
    scene_map = SceneMap.load(save_map(out, meta, model, db, extra=extra))
    ckpt.unlink(missing_ok=True)  # the map now holds what the checkpoint was for
    return scene_map
