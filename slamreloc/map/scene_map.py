"""The map: its regressor (what localization needs), the labelled training database, and what
else its folder holds (fused surface, provenance of an updated map's labels), each read on
first use, checked against the metadata and its checksum. The folder's format is
map_format.py's; writing it is map_write.py's.

    scene_map = SceneMap.load(MAP)                    # checks the metadata, builds the regressor
    scene_map = SceneMap.load(MAP, regressor=False)   # the same checks, no model (the viewer)
    scene_map.info                                    # the metadata, typed (MapMeta)
    scene_map.database, scene_map.surface, scene_map.provenance
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from functools import cached_property
from pathlib import Path

import numpy as np

from slamreloc.errors import InputError
from slamreloc.map.format import (
    DATABASE,
    DB_KEYS,
    META,
    PROVENANCE,
    SURFACE,
    WEIGHTS,
    check_database,
    check_digest,
    check_provenance,
    is_map,
    read_meta,
    read_npz,
    weights_name,
)
from slamreloc.map.lock import clean_leftovers
from slamreloc.map.weights import read_regressor
from slamreloc.regressor.model import RegressorConfig, SceneCoordinateRegressor
from slamreloc.regressor.train import TrainConfig
from slamreloc.map.surface import Surface
from slamreloc.types import Camera


def rows_by_frame(frame_index: np.ndarray, n_frames: int) -> list[np.ndarray]:
    """For each frame 0..n_frames-1, the indices of the rows whose `frame_index` is that
    frame, in row order."""
    order = np.argsort(frame_index, kind="stable")
    bounds = np.searchsorted(frame_index[order], np.arange(n_frames + 1))
    return [order[bounds[i]:bounds[i + 1]] for i in range(n_frames)]


@dataclass
class MapDatabase:
    descriptors: np.ndarray  # (M, D) float16, labelled training descriptors
    points: np.ndarray  # (M, 3) float32 world points, metres
    keypoints: np.ndarray  # (M, 2) float32 pixels
    frame_index: np.ndarray  # (M,) int32 into frame_names
    frame_names: list[str] = field(default_factory=list)
    world_from_cam: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))


@dataclass(frozen=True)
class MapProvenance:
    """Where each database row of an updated map came from (provenance.npz)."""

    source: np.ndarray  # (M,) int8: map_format.LABELLED, PSEUDO or NEW
    quality: np.ndarray  # (M,) float32 training weight in 0..1 (1 for labelled rows)


@dataclass(frozen=True)
class MapMeta:
    """The typed view of slamreloc_map.json, built once when the map is opened (after the
    schema check); `SceneMap.meta` keeps the JSON as written."""

    format_version: int
    slamreloc_version: str | None  # the version that wrote the map (None: not recorded)
    camera: Camera  # the training frames' intrinsics
    feature_name: str  # sift | superpoint
    feature_options: dict  # the extractor's options: make_extractor(feature_name, **options)
    regressor_arch: str  # preset name
    regressor: RegressorConfig
    n_parameters: int
    n_labelled: int  # database rows the regressor was trained on
    train: TrainConfig  # recorded training settings (defaults for what a map does not record);
    # `precision` is the one training ran in (fp32 | bf16), `auto` when not recorded
    frame_names: tuple[str, ...]  # database frames (empty for maps that did not record them)
    dataset_root: Path | None  # the dataset the map was built from, when recorded
    n_frames_updated: int  # frames the map's last update registered, appended last (0: none)
    # median reprojection error (pixels) of the training tracks triangulated with the map's
    # poses: how well labels and images agree (None: not recorded)
    label_reproj_error_px: float | None = None

    @staticmethod
    def from_json(meta: dict) -> MapMeta:
        """From metadata that passed `read_meta`'s schema check."""
        feats = dict(meta["features"])
        dataset = meta.get("dataset")
        root = dataset.get("root") if isinstance(dataset, dict) else None
        update = meta.get("pseudo_label")
        n_updated = update.get("n_frames_registered", 0) if isinstance(update, dict) else 0
        error = meta["labels"].get("median_reproj_error_px")
        finite = isinstance(error, (int, float)) and not isinstance(error, bool) \
            and math.isfinite(error)
        return MapMeta(
            meta["format_version"], meta.get("slamreloc_version"),
            Camera.from_dict(meta["camera"]),
            feats.pop("name"), feats, meta["regressor"]["arch"],
            RegressorConfig.from_dict(meta["regressor"]["config"]),
            meta["regressor"]["parameters"], meta["labels"]["n_labelled"],
            _train_config(meta.get("train")), tuple(meta.get("frame_names", [])),
            Path(root) if isinstance(root, str) else None,
            n_updated if isinstance(n_updated, int) else 0,
            float(error) if finite else None)


def _train_config(train) -> TrainConfig:
    """The recorded training settings; unrecorded or malformed ones take the defaults."""
    if not isinstance(train, dict):
        return TrainConfig()
    kinds = {f.name: (int, float) if type(f.default) is float else type(f.default)
             for f in fields(TrainConfig)}
    values = {k: v for k, v in train.items()
              if k in kinds and k != "betas" and isinstance(v, kinds[k])}
    betas = train.get("betas")
    if isinstance(betas, list) and len(betas) == 2:
        values["betas"] = tuple(betas)
    return TrainConfig(**values)


@dataclass
class SceneMap:
    root: Path
    meta: dict  # slamreloc_map.json as written (schema-checked); `info` is its typed view
    info: MapMeta
    regressor: SceneCoordinateRegressor | None  # None: loaded with regressor=False

    @staticmethod
    def is_map(path: Path) -> bool:
        return is_map(path)

    @staticmethod
    def load(path: str | Path, regressor: bool = True) -> SceneMap:
        """Read and check a map folder; any defect raises InputError naming the file.
        `regressor=False` checks the weights' checksum but builds no model (for readers of the
        database only)."""
        root = Path(path)
        clean_leftovers(root)
        if not root.is_dir():
            raise InputError(f"{root}: map folder not found")
        if not is_map(root):
            raise InputError(f"{root}: not a slamreloc map (no {META})")
        meta = read_meta(root)
        info = MapMeta.from_json(meta)
        if regressor:
            return SceneMap(root, meta, info, read_regressor(root, meta))
        if meta["format_version"] >= 2:
            check_digest(root, WEIGHTS, meta)
        return SceneMap(root, meta, info, None)

    @property
    def camera(self) -> Camera:
        return self.info.camera

    @property
    def format_version(self) -> int:
        return self.info.format_version

    @cached_property
    def database(self) -> MapDatabase:
        path = self.root / DATABASE
        if not path.is_file():
            raise InputError(f"{path}: map has no training database")
        if self.format_version >= 2:
            check_digest(self.root, DATABASE, self.meta)
        arrays = read_npz(path, "training database")
        names = list(self.info.frame_names)
        check_database(arrays, path, self.info.regressor.in_dim, names)
        return MapDatabase(*(arrays[k] for k in DB_KEYS[:4]), names, arrays["world_from_cam"])

    @cached_property
    def surface(self) -> Surface | None:
        """The fused depth surface, or None for a map built without depth."""
        if SURFACE not in self.meta.get("files", {}):
            return None
        path = self.root / SURFACE
        if not path.is_file():
            raise InputError(f"{path}: the map lists a surface but the file is missing")
        check_digest(self.root, SURFACE, self.meta)
        return Surface.from_arrays(read_npz(path, "surface"), str(path))

    @cached_property
    def provenance(self) -> MapProvenance | None:
        """Per database row: where the label came from and its training weight; None for a
        map that was never updated. Maps updated before provenance.npz was checksummed are
        read without the checksum."""
        path = self.root / PROVENANCE
        listed = PROVENANCE in self.meta.get("files", {})
        if not listed and not path.is_file():
            return None
        if not path.is_file():
            raise InputError(f"{path}: the map lists provenance but the file is missing")
        if listed:
            check_digest(self.root, PROVENANCE, self.meta)
        arrays = read_npz(path, "provenance")
        check_provenance(arrays, path, len(self.database.points))
        return MapProvenance(arrays["source"].astype(np.int8),
                             arrays["quality"].astype(np.float32))

    def size_bytes(self) -> int:
        """The network: weights + metadata (with the guided refinement, localization also
        reads the database, `database_bytes`)."""
        return ((self.root / weights_name(self.meta)).stat().st_size
                + (self.root / META).stat().st_size)

    def database_bytes(self) -> int:
        return (self.root / DATABASE).stat().st_size

    @property
    def has_database(self) -> bool:
        """Whether the folder holds its training database (a map can be shipped without it:
        the regressor then localizes without the guided refinement)."""
        return (self.root / DATABASE).is_file()
