"""slamreloc_map.json, typed: `MapMeta` is the one schema of a map folder's metadata.

Every writer builds a MapMeta (`build_map`, the pseudo-label update, `migrate_map`) and
`save_map` writes `stamped(...).to_json()`; every reader gets one from `MapMeta.read`
(`SceneMap.info`). `from_json` parses and validates: a defect raises InputError, one line
naming the file and the problem.

    {"format": "slamreloc-map", "format_version": 2, "slamreloc_version": "...",
     "features": {"name": "sift", ...extractor options},                    FeatureMeta
     "regressor": {"arch": "wide", "config": {...}, "parameters": 2300000},   RegressorMeta
     "train": {...TrainConfig fields, ...training stats},                     stats
     "labels": {"n_labelled": 51234, ...label stats},                         stats
     "camera": {"width", "height", "fx", "fy", "cx", "cy"[, "model", "distortion"]},
                                                                              CameraMeta
     "dataset": {"root", "kind", "split", "metric", "poses"},                DatasetMeta
     "timings_s": {...},                                                      stats
     "pseudo_label": {...},  (a map update)                                   UpdateMeta
     "surface": {"n_points", "voxel_m"},                                      SurfaceMeta
     "files": {"regressor.npz": SHA-256 hex, ...}, "frame_names": [...]}

Nothing read is lost on a rewrite: a record's keys the schema does not type, and values of the
keys it reads leniently (everything but what `from_json` checks) that lack the field's type,
are kept verbatim in the record's `extra`, and `to_json` writes the keys in the order they were
read. `MapMeta.from_json(d, path).to_json() == d` for every metadata `from_json` accepts
(`format_version` is added where a format-1 map records only `version`).

A value kept verbatim is refused where it is used: `recorded_inputs` (which every command with
a map consults before it writes anything) refuses a `dataset.root` or `pseudo_label.dataset.root`
that is not a string (null: not recorded), naming the file and the field. `dataset_root`, a
view, reads such a root as none; `surface.voxel_m` is recorded, never read.
"""

from __future__ import annotations

import math
import re
from copy import deepcopy
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Callable

import torch

from slamreloc import __version__
from slamreloc.camera_models import distortion_problem
from slamreloc.errors import InputError
from slamreloc.io.fileio import read_bytes
from slamreloc.io.jsonio import parse_json
from slamreloc.io.values import check_values
from slamreloc.map.format import (DATABASE, FORMAT_VERSION, LEGACY_WEIGHTS, MAP_FILES, MAP_FORMAT,
                                  META, WEIGHTS)
from slamreloc.registry import DATASET_KINDS, FORMER_PRESETS, PRECISIONS, PRESETS
from slamreloc.regressor.model import RegressorConfig, SceneCoordinateRegressor
from slamreloc.regressor.train import TrainConfig
from slamreloc.types import Camera, camera_problem, frame_name_problem, lens_camera_problem

Json = Any  # a parsed JSON value: dict, list, str, int, float, bool or None
MAX_META_BYTES = 64 << 20
# a median label reprojection error beyond this many pixels describes no labels an image holds
MAX_LABEL_ERROR_PX = 1e4
_HEADER = ("format", "format_version", "slamreloc_version")
_TRAILER = ("files", "frame_names", "frame_pictures")
_STAMPED = (*_HEADER, "version", *_TRAILER)  # what `stamped` sets (`version`: format 1's key)
_NOT_JSON = ("extra", "order", "source")  # a record's fields that are no key of its JSON
_SHA256 = re.compile(r"[0-9a-f]{64}")  # a digest as the map writes it: lower-case hex


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _is_str(v) -> bool:
    return isinstance(v, str)


def _is_bool(v) -> bool:
    return isinstance(v, bool)


def _is_object(v) -> bool:
    return isinstance(v, dict)


def _is_strings(v) -> bool:
    return isinstance(v, list) and all(isinstance(s, str) for s in v)


def _short(v) -> str:
    text = repr(v)
    return text if len(text) <= 60 else text[:57] + "..."


def _key(check: Callable[[Json], bool], parse: Callable[[Json], Any] | None = None,
         default: Any = None):
    """A typed key of a record: read from JSON when `check` accepts its value (then converted
    by `parse`), else kept in `extra`; None (the default) when the key is absent."""
    return field(default=default, metadata={"check": check, "parse": parse})


def _to_json(v) -> Json:
    if isinstance(v, _Record):
        return v.to_json()
    if isinstance(v, tuple):
        return [_to_json(x) for x in v]
    return deepcopy(v)


@dataclass(frozen=True)
class _Record:
    """A JSON object of the metadata: typed fields (None: the key is absent), `extra` (the
    keys the schema does not type, verbatim) and `order` (the key order as read; keys it lacks
    follow, fields first in declaration order, then `extra`)."""

    extra: dict[str, Json] = field(default_factory=dict, kw_only=True)
    order: tuple[str, ...] = field(default=(), kw_only=True, compare=False, repr=False)

    def _typed(self) -> dict[str, Json]:
        """The typed fields' JSON values in declaration order, those not None."""
        return {f.name: _to_json(getattr(self, f.name)) for f in fields(self)
                if f.name not in _NOT_JSON and getattr(self, f.name) is not None}

    def get(self, key: str, default: Json = None) -> Json:
        """The value recorded under `key`, typed or not (`default` when absent), as dict.get."""
        typed = key not in _NOT_JSON and key in {f.name for f in fields(self)}
        value = getattr(self, key) if typed else None
        return self.extra.get(key, default) if value is None else value

    def to_json(self) -> dict[str, Json]:
        """The JSON object (fresh: changing it changes nothing here)."""
        typed = self._typed()
        doc = {**typed, **{k: deepcopy(v) for k, v in self.extra.items() if k not in typed}}
        first = [k for k in self.order if k in doc]
        seen = set(first)
        return {k: doc[k] for k in (*first, *(k for k in doc if k not in seen))}

    @classmethod
    def _parse(cls, obj: dict[str, Json], **typed):
        """From a JSON object: each typed key whose value passes its check (`typed` overrides,
        already checked), everything else into `extra`."""
        keys = {f.name: f.metadata for f in fields(cls) if "check" in f.metadata}
        extra = {}
        for k, v in obj.items():
            if k in typed:
                continue
            if k in keys and keys[k]["check"](v):
                parse = keys[k]["parse"]
                typed[k] = parse(v) if parse else v
            else:
                extra[k] = v
        return cls(**typed, extra=extra, order=tuple(obj))


@dataclass(frozen=True)
class FeatureMeta(_Record):
    """"features": the local features of the map's descriptors."""

    name: str  # sift | superpoint
    # the extractor's options as recorded (fields of SiftConfig / SuperPointConfig; options not
    # recorded take their defaults): make_extractor(name, **options)
    options: dict[str, Json] = field(default_factory=dict)

    def _typed(self) -> dict[str, Json]:
        return {"name": self.name, **deepcopy(self.options)}

    @classmethod
    def _from_json(cls, obj: dict) -> FeatureMeta:
        return cls(obj["name"], {k: v for k, v in obj.items() if k != "name"}, order=tuple(obj))


@dataclass(frozen=True)
class RegressorMeta(_Record):
    """"regressor": the scene-coordinate regressor whose weights regressor.npz holds."""

    arch: str  # the preset it was made from (RegressorConfig.preset): paper | tiny | wide ...
    config: dict[str, Json]  # RegressorConfig.to_dict() as recorded (`to_config`)
    parameters: int  # number of parameters

    @classmethod
    def _from_json(cls, obj: dict) -> RegressorMeta:
        rest = {k: v for k, v in obj.items() if k not in ("arch", "config", "parameters")}
        return cls(obj["arch"], obj["config"], obj["parameters"], extra=rest, order=tuple(obj))

    def to_config(self) -> RegressorConfig:
        """The config as a RegressorConfig (keys a map does not record take the defaults)."""
        return RegressorConfig.from_dict(self.config)


@dataclass(frozen=True)
class CameraMeta(_Record):
    """"camera": the training frames' camera as `Camera.to_dict()` writes it: image size and
    intrinsics in pixels (OpenCV convention: pixel centres at integer coordinates); `model` and
    `distortion` (a COLMAP lens model and its distortion parameters) only for a distorted lens.
    Values are kept as recorded (`to_camera` makes the Camera)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    model: str | None = None
    distortion: tuple[float, ...] | None = None

    @classmethod
    def from_camera(cls, camera: Camera) -> CameraMeta:
        d = camera.to_dict()
        return cls(**{**d, "distortion": tuple(d["distortion"]) if "distortion" in d else None})

    @classmethod
    def _from_json(cls, obj: dict) -> CameraMeta:
        dist = obj.get("distortion")
        return cls(**{**obj, "distortion": None if dist is None else tuple(dist)},
                   order=tuple(obj))

    def to_camera(self) -> Camera:
        return Camera.from_dict(self.to_json())


@dataclass(frozen=True)
class DatasetMeta(_Record):
    """"dataset": the dataset the map was built from."""

    root: str | None = _key(_is_str)  # its folder (or bag), an absolute path
    kind: str | None = _key(_is_str)  # its detected format: colmap | 7scenes | tum | synthetic...
    split: str | None = _key(_is_str)  # the split (or sequences) mapped
    metric: bool | None = _key(_is_bool)  # poses in metres (False: an SfM model without scale)
    poses: str | None = _key(_is_str)  # "dataset" (its own poses) or the --poses file used


@dataclass(frozen=True)
class UpdateMeta(_Record):
    """"pseudo_label": the last map update from an unlabelled sequence (pseudo-labelling)."""

    source_map: str | None = _key(_is_str)  # the map it updated (absolute path)
    dataset: dict[str, Json] | None = _key(_is_object)  # {"root": path, "split": name or null}
    n_frames: int | None = _key(_is_int)  # frames of the sequence
    # registered frames: their database rows are appended last, after the updated map's
    n_frames_registered: int | None = _key(_is_int)
    n_inherited_labels: int | None = _key(_is_int)  # map labels taken over by matches
    n_triangulated_labels: int | None = _key(_is_int)  # labels triangulated anew
    n_new_points: int | None = _key(_is_int)  # new 3D points among those
    update: str | None = _key(_is_str)  # finetune | retrain
    provenance: str | None = _key(_is_str)  # what provenance.npz holds (prose)
    history: tuple[str, ...] | None = _key(_is_strings, tuple)  # every map updated, oldest first
    # the datasets of the updates before this one (absolute paths, oldest first): an update of
    # an updated map still holds their frames
    earlier_dataset_roots: tuple[str, ...] | None = _key(_is_strings, tuple)


@dataclass(frozen=True)
class ExtensionMeta(_Record):
    """"extended": what a SLAM session that extended a map (`slam --map OLD --out NEW`) took
    over: NEW's first `n_prior_frames` frames are OLD's, whose images are in the datasets OLD
    records (`dataset_roots`, absolute paths, oldest first) and whose poses came from the pose
    files it records (`pose_files`); NEW's own `dataset` is the session's."""

    source_map: str | None = _key(_is_str)  # OLD (absolute path)
    dataset_roots: tuple[str, ...] | None = _key(_is_strings, tuple)
    n_prior_frames: int | None = _key(_is_int)
    # the pose files OLD's frames were posed from (`dataset.poses` of OLD and of the maps
    # before it; absolute paths, oldest first): inputs of every command on NEW too
    pose_files: tuple[str, ...] | None = _key(_is_strings, tuple)


@dataclass(frozen=True)
class SurfaceMeta(_Record):
    """"surface": the fused depth surface in surface.npz (map frame)."""

    n_points: int | None = _key(_is_int)
    voxel_m: float | None = _key(_is_number)  # fusion voxel size, metres


@dataclass(frozen=True, kw_only=True)
class MapMeta(_Record):
    """slamreloc_map.json. Poses and points of a map are in its map frame (the frame of the
    poses it was built from), in metres when `metric`; the database's training poses are
    camera-to-world (world_from_cam).

    Built in code, only the four checked sections are required; `save_map` stamps the
    format and slamreloc versions, the files' checksums and the frame names (`stamped`)."""

    format_version: int = _key(_is_int, default=FORMAT_VERSION)
    slamreloc_version: str | None = _key(_is_str)  # the version that wrote it
    features: FeatureMeta = field(metadata={"check": _is_object,
                                            "parse": FeatureMeta._from_json})
    regressor: RegressorMeta = field(metadata={"check": _is_object,
                                               "parse": RegressorMeta._from_json})
    # training settings (TrainConfig.to_dict(), `precision` the one it ran in) and stats
    # (train_regressor's: `final_loss_m`, metres...); a map update adds `update`
    train: dict[str, Json] | None = _key(_is_object)
    # label statistics (build_labels'): `n_labelled` database rows, `labelled_fraction`,
    # `median_reproj_error_px` (pixels, or null)...; a map update adds its label counts
    labels: dict[str, Json] = field(metadata={"check": _is_object, "parse": None})
    camera: CameraMeta = field(metadata={"check": _is_object, "parse": CameraMeta._from_json})
    dataset: DatasetMeta | None = _key(_is_object, DatasetMeta._parse)
    timings_s: dict[str, Json] | None = _key(_is_object)  # seconds per mapping stage
    pseudo_label: UpdateMeta | None = _key(_is_object, UpdateMeta._parse)
    extended: ExtensionMeta | None = _key(_is_object, ExtensionMeta._parse)
    surface: SurfaceMeta | None = _key(_is_object, SurfaceMeta._parse)
    files: dict[str, str] | None = _key(_is_object)  # file name -> SHA-256 hex (format >= 2)
    # the database's training frames, in the order of its poses (None: not recorded)
    frame_names: tuple[str, ...] | None = _key(_is_strings, tuple)
    # each frame's picture (`io.images.picture_digest` of its pixels, "" where not known), in
    # the order of `frame_names`: a frame is held by its picture too, whatever it is named and
    # wherever its dataset is now (`map.joining`); None: not recorded (maps of 0.1.0 and before)
    frame_pictures: tuple[str, ...] | None = _key(_is_strings, tuple)
    # the file it was read from (`from_json`'s path), for messages; None: built in code
    source: Path | None = field(default=None, compare=False, repr=False)

    def _typed(self) -> dict[str, Json]:
        return {"format": MAP_FORMAT, **super()._typed()}

    # -- reading ---------------------------------------------------------------------------

    @classmethod
    def read(cls, root: str | Path) -> MapMeta:
        """MAP/slamreloc_map.json, parsed and checked (`from_json`). A frame may be named more
        than once: a map updated with a sequence it already holds, or extended by a SLAM
        session over frames it was learned from, keeps each observation as a frame of its
        own."""
        path = Path(root) / META
        meta = cls.from_json(parse_json(read_bytes(path, "map metadata", MAX_META_BYTES), path),
                             path)
        return meta

    @classmethod
    def from_json(cls, doc: Json, path: str | Path) -> MapMeta:
        """The metadata of a parsed JSON document, checked: InputError naming `path` (the file
        it came from) and the problem unless it is a map's metadata this version reads."""
        if not isinstance(doc, dict):
            raise InputError(f"{path}: expected a JSON object, got {type(doc).__name__}")
        if doc.get("format") != MAP_FORMAT:
            raise InputError(f"{path}: not a slamreloc map (format={_short(doc.get('format'))})")
        version = doc.get("format_version", doc.get("version"))
        writer = doc.get("slamreloc_version")
        writer = writer if isinstance(writer, str) else "an unknown version"
        if not _is_int(version):
            raise InputError(f"{path}: format_version must be an integer, got {_short(version)}")
        if version > FORMAT_VERSION:
            raise InputError(f"{path}: map format version {version} (written by slamreloc "
                             f"{writer[:40]}) is newer than this slamreloc {__version__} reads "
                             f"(format versions 1 to {FORMAT_VERSION}); upgrade slamreloc")
        if version < 1:
            raise InputError(f"{path}: unknown map format version {version}")
        _check_schema(doc, version, path)
        meta = cls._parse({k: v for k, v in doc.items() if k != "format"},
                          format_version=version)
        return replace(meta, order=tuple(doc), source=Path(path))

    # -- writing ---------------------------------------------------------------------------

    def stamped(self, files: dict[str, str], frame_names, frame_pictures=None) -> MapMeta:
        """This metadata as `save_map` writes it: today's format version, this slamreloc's
        version, the map's `files` (name -> SHA-256), the database's `frame_names` and their
        `frame_pictures` (None: not known, not written); the format keys first, then the
        others in their order, `files`, `frame_names` and `frame_pictures` last. A format-1
        map's `version` is dropped."""
        body = [k for k in self.to_json() if k not in _STAMPED]
        pictures = None if frame_pictures is None else tuple(frame_pictures)
        return replace(self, format_version=FORMAT_VERSION, slamreloc_version=__version__,
                       files=dict(files), frame_names=tuple(frame_names),
                       frame_pictures=pictures,
                       extra={k: v for k, v in self.extra.items() if k not in _STAMPED},
                       order=(*_HEADER, *body, *_TRAILER))

    # -- typed views -----------------------------------------------------------------------

    @property
    def weights_file(self) -> str:
        """The regressor's file in a map of this format version."""
        return LEGACY_WEIGHTS if self.format_version == 1 else WEIGHTS

    @property
    def feature_name(self) -> str:
        return self.features.name

    @property
    def feature_options(self) -> dict[str, Json]:
        """make_extractor(feature_name, **feature_options) makes the map's extractor."""
        return dict(self.features.options)

    @property
    def regressor_arch(self) -> str:
        return self.regressor.arch

    @property
    def n_parameters(self) -> int:
        return self.regressor.parameters

    @property
    def n_labelled(self) -> int:
        """Database rows the regressor was trained on."""
        return self.labels["n_labelled"]

    def check_database_counts(self, n_rows: int, n_frames: int, path: Path) -> None:
        """InputError naming `path` (the database file) where the label counts disagree with
        the database read: `labels.n_labelled` is its rows; `labels.n_frames` (the frames a
        map was labelled from) and `labels.n_keyframes` (a session's keyframes) are at most
        its training frames, which an update or a later session adds to."""
        if self.n_labelled != n_rows:
            raise InputError(f"{path}: holds {n_rows} rows, but {META} says "
                             f"'labels.n_labelled' {self.n_labelled}")
        for key in ("n_frames", "n_keyframes"):
            n = self.labels.get(key)
            if _is_int(n) and n > n_frames:
                raise InputError(f"{path}: holds {n_frames} training frames, but {META} says "
                                 f"'labels.{key}' {n}")

    @property
    def label_reproj_error_px(self) -> float | None:
        """Median reprojection error (pixels) of the training tracks triangulated with the
        map's poses: how well labels and images agree (None: not recorded)."""
        error = self.labels.get("median_reproj_error_px")
        return float(error) if _is_number(error) and math.isfinite(error) else None

    @property
    def train_config(self) -> TrainConfig:
        """The recorded training settings; unrecorded or malformed ones take the defaults.
        `precision` is the one training ran in (fp32 | bf16), `auto` when not recorded."""
        train = self.train
        if train is None:
            return TrainConfig()
        kinds = {f.name: (int, float) if type(f.default) is float else type(f.default)
                 for f in fields(TrainConfig)}
        values = {k: v for k, v in train.items()
                  if k in kinds and k != "betas" and isinstance(v, kinds[k])}
        betas = train.get("betas")
        if isinstance(betas, list) and len(betas) == 2:
            values["betas"] = tuple(betas)
        return TrainConfig(**values)

    @property
    def dataset_root(self) -> Path | None:
        """The dataset the map was built from, when recorded (an absolute path; a recorded
        root of another type or a relative one reads as none here, and `recorded_inputs`, which
        every command that writes checks, refuses it)."""
        root = self.dataset.root if self.dataset else None
        return Path(root) if isinstance(root, str) and Path(root).is_absolute() else None

    @property
    def poses_source(self) -> str:
        """"dataset" (built from the dataset's own poses) or the --poses file it used."""
        return self.dataset.get("poses", "dataset") if self.dataset else "dataset"

    def recorded_inputs(self) -> dict[str, Path | None]:
        """The files the map records it was made from - its dataset, the pose file it used,
        the dataset of its last update: inputs (`check_outputs`) of every command that has the
        map, which never writes there. Only absolute paths count (the schema's). A recorded
        dataset that is not an object, or a root that is not a string (null: not recorded), is
        an InputError naming the file and the field: a check that silently passed over it
        would let a command write into that dataset."""
        def absolute(p) -> Path | None:
            return Path(p) if isinstance(p, str) and p and Path(p).is_absolute() else None

        update = self.pseudo_label.get("dataset") if self.pseudo_label else None
        earlier = self.earlier_dataset_roots
        poses = self.earlier_pose_files
        return {"the dataset the map records": absolute(self._recorded_root(
                    self.get("dataset"), "dataset")),
                "the pose file the map records": absolute(self.poses_source),
                "the dataset of the map's update": absolute(self._recorded_root(
                    update, "pseudo_label.dataset")),
                **{"a dataset of the map's earlier sessions"
                   + (f" ({i + 1} of {len(earlier)})" if len(earlier) > 1 else ""): Path(root)
                   for i, root in enumerate(earlier)},
                **{"a pose file of the map's earlier sessions"
                   + (f" ({i + 1} of {len(poses)})" if len(poses) > 1 else ""): Path(path)
                   for i, path in enumerate(poses)}}

    @property
    def earlier_dataset_roots(self) -> list[str]:
        """The datasets of frames this map holds besides its own dataset's and its last
        update's: those it took over from the map a SLAM session extended
        (`extended.dataset_roots`), then those of the updates before its last
        (`pseudo_label.earlier_dataset_roots`); absolute paths (the schema checks them),
        oldest first, each once."""
        roots: list[str] = []
        for record in (self.extended.dataset_roots if self.extended else None,
                       self.pseudo_label.earlier_dataset_roots if self.pseudo_label else None):
            roots += [r for r in record or () if r not in roots]
        return roots

    @property
    def earlier_pose_files(self) -> list[str]:
        """The pose files the frames this map took over from the map a SLAM session extended
        were posed from (`extended.pose_files`, checked absolute by the schema), oldest
        first."""
        return list(self.extended.pose_files or ()) if self.extended else []

    def pose_files(self) -> list[str]:
        """Every pose file this map's frames were posed from, oldest first (each once)."""
        own = self.recorded_inputs()["the pose file the map records"]
        files = self.earlier_pose_files
        return files + [str(own)] if own is not None and str(own) not in files else files

    def dataset_roots(self) -> list[str]:
        """Every dataset whose frames this map holds, oldest first: its earlier sessions',
        its own, its update's (each once)."""
        roots = self.earlier_dataset_roots
        for key, path in self.recorded_inputs().items():
            if path is not None and "pose file" not in key and str(path) not in roots:
                roots.append(str(path))
        return roots

    def _recorded_root(self, dataset: Json, where: str) -> str | None:
        """`recorded_root` of this metadata's file."""
        if isinstance(dataset, _Record):
            dataset = dataset.to_json()
        return recorded_root(dataset, where, self.source or META)

    @property
    def metric(self) -> bool:
        """Whether the map is in metres (False: an SfM model's units; recorded or true).
        `dataset.metric` is true or false (null: false, as maps read it before the schema);
        any other value, kept verbatim, is an InputError naming the file and the field here,
        where it is read as a bool ("false" would be true)."""
        if not self.dataset:
            return True
        metric = self.dataset.get("metric", True)
        if metric is None or isinstance(metric, bool):
            return bool(metric)
        raise InputError(f"{self.source or META}: 'dataset.metric' must be true or false, got "
                         f"{_short(metric)}")

    @property
    def n_frames_updated(self) -> int:
        """Frames the map's last update registered, appended last to the database (0: none)."""
        n = self.pseudo_label.get("n_frames_registered", 0) if self.pseudo_label else 0
        return n if isinstance(n, int) else 0


def recorded_root(dataset: Json, where: str, path) -> str | None:
    """The `root` of a recorded dataset record (`where`: its key path in the metadata file
    `path`), None where none is recorded; InputError naming the file and the field for a
    record that is not an object, or a root that is not an absolute path this system holds."""
    if dataset is None:
        return None
    if not isinstance(dataset, dict):
        raise InputError(f"{path}: '{where}' must be an object, got {_short(dataset)}")
    root = dataset.get("root")
    if root is not None:
        check_recorded_path(root, f"{where}.root", path)
    return root


def check_recorded_path(root: Json, key: str, path) -> None:
    """InputError naming the metadata file `path` and its `key` unless `root`, a dataset's
    recorded path, is a string this system can hold (no NUL byte, at most 4096 bytes) and
    absolute."""
    if not isinstance(root, str):
        raise InputError(f"{path}: '{key}' must be a string (the dataset's path), got "
                         f"{_short(root)}")
    if "\0" in root or len(root.encode("utf-8", "replace")) > 4096:
        raise InputError(f"{path}: '{key}' is not a path this system can hold (a NUL byte, or "
                         f"over 4096 bytes), got {_short(root)}")
    if not Path(root).is_absolute():  # "" too: no path at all
        raise InputError(f"{path}: '{key}' must be an absolute path (maps record one; a "
                         "relative one would name another dataset from each folder a command "
                         f"runs in), got {_short(root)}")


def _digest_problem(digest: Json) -> str | None:
    """Why `digest` is not a SHA-256 as a map records one (`files`, `frame_pictures`): 64
    lower-case hex digits; None when it is."""
    if isinstance(digest, str) and _SHA256.fullmatch(digest):
        return None
    if isinstance(digest, str) and _SHA256.fullmatch(digest.lower()):
        return "is a SHA-256 in upper-case hex digits; a map records lower-case ones"
    return "is not a SHA-256 digest (64 lower-case hex digits)"


def _check_schema(meta: dict, version: int, path) -> None:
    def need(obj: dict, key: str, kind, where: str):
        if key not in obj:
            raise InputError(f"{path}: missing key '{where}{key}'")
        val = obj[key]
        ok = _is_int(val) if kind is int else (
            _is_number(val) if kind is float else isinstance(val, kind))
        if not ok:
            name = {int: "an integer", float: "a number", dict: "an object", str: "a string",
                    list: "a list", bool: "true or false"}[kind]
            raise InputError(f"{path}: '{where}{key}' must be {name}, got {_short(val)}")
        return val

    feats = need(meta, "features", dict, "")
    _check_feature_options(feats, path)
    reg = need(meta, "regressor", dict, "")
    if need(reg, "arch", str, "regressor.") not in PRESETS:
        raise InputError(f"{path}: 'regressor.arch' must be one of {', '.join(PRESETS)}, got "
                         f"{_short(reg['arch'])}")
    need(reg, "parameters", int, "regressor.")
    cfg = need(reg, "config", dict, "regressor.")
    _check_regressor_config(cfg, path)
    _check_regressor_record(reg, path)
    labels = need(meta, "labels", dict, "")
    need(labels, "n_labelled", int, "labels.")
    # the training frames' names, one per database pose: every writer (format 1's too) lists
    # them, and export, pseudo-label and slam --map look frames up by them
    need(meta, "frame_names", list, "")
    for section in ("labels", "surface", "pseudo_label"):
        _check_counts(meta.get(section), section, path)
    _check_optional(labels, "labelled_fraction", "labels.", path, "a fraction in [0, 1]",
                    lambda v: _is_number(v) and 0 <= v <= 1)
    surface = meta.get("surface")
    if isinstance(surface, dict):
        _check_optional(surface, "voxel_m", "surface.", path, "a voxel size in (0, 10] metres",
                        lambda v: _is_number(v) and 0 < v <= 10)
    dataset = meta.get("dataset")
    _check_optional(meta, "pseudo_label", "", path, "an object (the update's record)",
                    _is_object)
    recorded_root(dataset, "dataset", path)  # every command's rule, not only a dataset's user
    if isinstance(meta.get("pseudo_label"), dict):
        recorded_root(meta["pseudo_label"].get("dataset"), "pseudo_label.dataset", path)
        _check_optional(meta["pseudo_label"], "earlier_dataset_roots", "pseudo_label.", path,
                        "a list of the datasets' absolute paths", _is_strings)
        for i, root in enumerate(meta["pseudo_label"].get("earlier_dataset_roots") or []):
            check_recorded_path(root, f"pseudo_label.earlier_dataset_roots[{i}]", path)
    _check_optional(meta, "extended", "", path, "an object (what a SLAM session took over)",
                    _is_object)
    if isinstance(meta.get("extended"), dict):
        for key in ("dataset_roots", "pose_files"):
            _check_optional(meta["extended"], key, "extended.", path,
                            "a list of absolute paths", _is_strings)
            for i, root in enumerate(meta["extended"].get(key) or []):
                check_recorded_path(root, f"extended.{key}[{i}]", path)
        _check_optional(meta["extended"], "source_map", "extended.", path,
                        "a string (the extended map's path)", lambda v: isinstance(v, str))
        n_frames = len(meta["frame_names"])
        _check_optional(meta["extended"], "n_prior_frames", "extended.", path,
                        f"a count of at most the map's frames ({n_frames})",
                        _in(0, n_frames, whole=True))
    if isinstance(dataset, dict):
        _check_optional(dataset, "split", "dataset.", path, "a string (the split's sequences)",
                        lambda v: isinstance(v, str))
        _check_optional(dataset, "kind", "dataset.", path,
                        f"one of {', '.join(DATASET_KINDS)}", lambda v: v in DATASET_KINDS)
        _check_optional(dataset, "poses", "dataset.", path, '"dataset", "slam" or the '
                        "absolute path of the pose file the map was made from",
                        lambda v: isinstance(v, str) and (v in ("dataset", "slam")
                                                          or Path(v).is_absolute()))
    _check_optional(labels, "median_reproj_error_px", "labels.", path,
                    f"a number of pixels in [0, {MAX_LABEL_ERROR_PX:g}] or null",
                    lambda v: _is_number(v) and 0 <= v <= MAX_LABEL_ERROR_PX)
    train = meta.get("train")
    if isinstance(train, dict):
        _check_optional(train, "precision", "train.", path,
                        f"one of {', '.join(PRECISIONS)}", lambda v: v in PRECISIONS)
        for key, (want, ok) in TRAIN_RULES.items():  # what a retraining would use
            _check_optional(train, key, "train.", path, want, ok)
        _check_optional(train, "device", "train.", path, "a torch device type (one of "
                        f"{', '.join(DEVICE_TYPES)}) or null", lambda v: v in DEVICE_TYPES)
    # the labelling's counts agree (an update's pseudo-labels come from other frames: past
    # one, only depth labels are still counts of the labelled frames' keypoints)
    updated = bool(meta.get("pseudo_label"))  # an object (checked above), not empty
    keypoints, labelled = labels.get("n_keypoints"), labels.get("n_labelled")
    if _is_int(keypoints):
        for key in ("n_depth_labels",) if updated else ("n_labelled", "n_depth_labels"):
            _check_optional(labels, key, "labels.", path, f"a count of at most 'labels."
                            f"n_keypoints' ({keypoints})", _in(0, keypoints, whole=True))
        if not updated and _is_int(labelled) and keypoints:
            share = labelled / keypoints  # as labelling records it
            _check_optional(labels, "labelled_fraction", "labels.", path,
                            f"'labels.n_labelled' / 'labels.n_keypoints' ({share:.6g})",
                            lambda v: _is_number(v) and abs(v - share) <= 1e-6)
    if not updated and _is_int(labelled):
        # a track is labelled rows of one world point: never more tracks than labelled rows
        _check_optional(labels, "n_tracks", "labels.", path, "a count of at most "
                        f"'labels.n_labelled' ({labelled})", _in(0, labelled, whole=True))
    depth_labels, tracks = labels.get("n_depth_labels"), labels.get("n_tracks")
    if _is_int(depth_labels) or tracks == 0:  # a depth label its track contradicts
        most, of = (0, "'labels.n_tracks'") if tracks == 0 else (depth_labels,
                                                                "'labels.n_depth_labels'")
        _check_optional(labels, "n_track_depth_disagreements", "labels.", path,
                        f"a count of at most {of} ({most})", _in(0, most, whole=True))
    frames = labels.get("n_frames")
    if _is_int(frames):  # a pair is two of the labelled frames
        most = frames * (frames - 1) // 2
        _check_optional(labels, "n_pairs", "labels.", path, f"a count of at most {most} "
                        f"(pairs of 'labels.n_frames' {frames})", _in(0, most, whole=True))
    if _is_int(tracks):  # observations per track: none without tracks, at most all keypoints
        most = keypoints / max(tracks, 1) if _is_int(keypoints) else None
        _check_optional(labels, "mean_track_length", "labels.", path,
                        "0 ('labels.n_tracks' is 0)" if tracks == 0 else
                        "a number of observations, 1 or more" if most is None else
                        f"a number of observations in 1..{most:.6g} ('labels.n_keypoints' / "
                        "'labels.n_tracks')",
                        _in(0, 0) if tracks == 0 else _in(1, math.inf if most is None else most))
    if isinstance(train, dict) and _is_int(train.get("epochs")):
        for key in ("resumed_at_epoch", "averaged_epochs"):
            _check_optional(train, key, "train.", path,
                            f"a whole number of epochs in 0..{train['epochs']} ('train.epochs')",
                            _in(0, train["epochs"], whole=True))
    if isinstance(dataset, dict):
        _check_optional(dataset, "metric", "dataset.", path, "true or false", _is_bool)
    _check_optional(meta, "timings_s", "", path, "an object of seconds", _is_object)
    # every field by its name's kind, as in reports: counts, seconds, metres, shares
    check_values(meta, path, names=())
    cam = need(meta, "camera", dict, "")
    for key in ("width", "height"):
        if not 0 < need(cam, key, int, "camera.") <= 1 << 16:
            raise InputError(f"{path}: 'camera.{key}' must be in 1..65536, got {cam[key]}")
    for key in ("fx", "fy", "cx", "cy"):
        need(cam, key, float, "camera.")
    problem = camera_problem(*(cam[k] for k in ("width", "height", "fx", "fy", "cx", "cy")))
    if problem:
        raise InputError(f"{path}: 'camera': {problem}")
    extra = set(cam) - {"width", "height", "fx", "fy", "cx", "cy", "model", "distortion"}
    if extra:
        raise InputError(f"{path}: unknown camera key '{sorted(extra)[0]}'")
    model, dist = "PINHOLE", []
    if "model" in cam or "distortion" in cam:
        model = need(cam, "model", str, "camera.")
        dist = need(cam, "distortion", list, "camera.")
        problem = distortion_problem(model, dist)
        if problem:
            raise InputError(f"{path}: 'camera': {problem}")
    problem = lens_camera_problem(model, *(cam[k] for k in ("width", "height", "fx", "fy",
                                                              "cx", "cy")), tuple(dist))
    if problem:  # every rule of a camera (`Camera`), named by the file here
        raise InputError(f"{path}: 'camera': {problem}")
    names = meta.get("frame_names", [])
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise InputError(f"{path}: 'frame_names' must be a list of strings")
    for i, name in enumerate(names):  # a name twice is one frame observed twice (`read`)
        problem = frame_name_problem(name)
        if problem:
            raise InputError(f"{path}: 'frame_names'[{i}] {_short(name)} {problem}")
    pictures = meta.get("frame_pictures")
    if pictures is not None:
        if not isinstance(pictures, list) or len(pictures) != len(names):
            raise InputError(f"{path}: 'frame_pictures' must be a list of one picture digest "
                             f"per frame of 'frame_names' ({len(names)})")
        for i, digest in enumerate(pictures):
            problem = digest != "" and _digest_problem(digest)  # "": not known
            if problem:
                raise InputError(f"{path}: 'frame_pictures'[{i}] {_short(digest)} {problem} "
                                 "(or \"\", not known)")
    if version >= 2:
        files = need(meta, "files", dict, "")
        for name in (WEIGHTS, DATABASE):
            need(files, name, str, "files.")
        for name, digest in files.items():  # what the folder's reader checks, and only that
            if name not in MAP_FILES or name in (META, LEGACY_WEIGHTS):
                raise InputError(f"{path}: 'files' lists {_short(name)}, which is not a file "
                                 f"a map of format {version} holds")
            problem = _digest_problem(digest)
            if problem:
                raise InputError(f"{path}: 'files.{name}' {_short(digest)} {problem}")


def _in(low: float, high: float, whole: bool = False) -> Callable[[Any], bool]:
    """A check: a number (a whole one where `whole`) within [low, high]."""
    return lambda v: (_is_int(v) if whole else _is_number(v)) and low <= v <= high


DEVICE_TYPES = ("cpu", "cuda", "mps", "xpu")  # `train.device`: where the map was trained

# the recorded training settings a retraining (`pseudo-label --update retrain`) reuses: present
# and not null, each must be a value training can run with (`train_config`'s fields)
TRAIN_RULES: dict[str, tuple[str, Callable[[Any], bool]]] = {
    "epochs": ("a whole number of epochs, 0 or more", _in(0, 10 ** 9, whole=True)),
    "batch_size": ("a whole number of rows in 1..1048576", _in(1, 1 << 20, whole=True)),
    "lr": ("a learning rate in (0, 10]", lambda v: _is_number(v) and 0 < v <= 10),
    "weight_decay": ("a number in [0, 10]", _in(0, 10)),
    "betas": ("two numbers in [0, 1)", lambda v: isinstance(v, list) and len(v) == 2
              and all(_is_number(b) and 0 <= b < 1 for b in v)),
    "lr_halvings": ("a whole number in 0..64", _in(0, 64, whole=True)),
    "noise": ("a number in [0, 10]", _in(0, 10)),
    "input_dropout": ("a fraction in [0, 1)", lambda v: _is_number(v) and 0 <= v < 1),
    "average_tail": ("a fraction in [0, 1]", _in(0, 1)),
    "seed": ("a whole number", _in(-(2 ** 63), 2 ** 63 - 1, whole=True)),
    "checkpoint_every_s": ("seconds, 0 or more", _in(0, 1e9)),
}


def _check_counts(section, where: str, path) -> None:
    """InputError for a count of the record (a key `n_*`) that is not a whole number >= 0
    (null: not counted)."""
    if not isinstance(section, dict):
        return
    for key, val in section.items():
        if key.startswith("n_") and val is not None and not (_is_int(val) and val >= 0):
            raise InputError(f"{path}: '{where}.{key}' is a count, a whole number >= 0; got "
                             f"{_short(val)}")


def _check_regressor_record(reg: dict, path) -> None:
    """A config (already checked) that is a preset's (today's, or one a name made in an earlier
    version: FORMER_PRESETS) is recorded under that preset's name in `arch` (a config made in
    code, no preset's, may carry any preset name); `parameters` is the config's size."""
    cfg, arch = reg["config"], reg["arch"]
    made_by = [name for name, preset in _preset_configs() if preset == _arch_of(cfg)]
    if made_by and arch not in made_by:
        raise InputError(f"{path}: 'regressor.arch' is {_short(arch)}, but 'regressor.config' "
                         f"is the '{made_by[0]}' architecture")
    with torch.device("meta"):  # the size alone: no memory for the weights
        size = SceneCoordinateRegressor(RegressorConfig.from_dict(cfg)).num_parameters()
    if reg["parameters"] != size:
        raise InputError(f"{path}: 'regressor.parameters' is {reg['parameters']}, but the "
                         f"recorded config has {size} parameters")


def _arch_of(cfg: dict) -> tuple:
    """What a preset fixes of a config: its layer widths, head and (a clusters head's) count."""
    head = cfg.get("head", "regression")
    return tuple(cfg["hidden"]), head, cfg.get("n_clusters", 1) if head == "clusters" else 1


def _preset_configs() -> list[tuple[str, tuple]]:
    """(name, `_arch_of` its config) for every preset, today's and former ones."""
    return [(name, _arch_of(preset)) for name in PRESETS
            for preset in (PRESETS[name], *FORMER_PRESETS.get(name, ()))]


def _check_optional(obj: dict, key: str, where: str, path, want: str,
                    ok: Callable[[Any], bool]) -> None:
    """InputError `'WHERE.KEY' must be WANT, got V` for a key that is present, not null and
    not `ok`."""
    val = obj.get(key)
    if val is not None and not ok(val):
        raise InputError(f"{path}: '{where}{key}' must be {want}, got {_short(val)}")


def _check_feature_options(feats: dict, path) -> None:
    from slamreloc.features.sift import SiftConfig

    name = feats.get("name")
    if name == "sift":
        config_cls = SiftConfig
    elif name == "superpoint":
        from slamreloc.features.superpoint import SuperPointConfig as config_cls
    else:
        raise InputError(f"{path}: 'features.name' must be sift or superpoint, got {_short(name)}")
    defaults = config_cls()
    for key, val in feats.items():
        if key == "name":
            continue
        known = {f.name for f in fields(config_cls)}
        if key not in known:
            raise InputError(f"{path}: unknown feature option 'features.{key}'")
        default = getattr(defaults, key)
        ok = (isinstance(val, bool) if isinstance(default, bool) else
              _is_int(val) if isinstance(default, int) else
              _is_number(val) and math.isfinite(val) if isinstance(default, float) else
              isinstance(val, type(default)))
        if not ok:
            raise InputError(f"{path}: 'features.{key}' has the wrong type ({_short(val)})")
    if _is_int(feats.get("max_keypoints")) and not 0 < feats["max_keypoints"] <= 1 << 20:
        raise InputError(f"{path}: 'features.max_keypoints' out of range")
    try:
        config_cls(**{k: v for k, v in feats.items() if k != "name"})  # the options' ranges
    except InputError as err:
        raise InputError(f"{path}: 'features': {err}") from None


def _check_regressor_config(cfg: dict, path) -> None:
    where = "regressor.config."
    known = {f.name for f in fields(RegressorConfig)}
    extra = set(cfg) - known
    if extra:
        raise InputError(f"{path}: unknown key '{where}{sorted(extra)[0]}'")
    for key in ("in_dim", "hidden"):
        if key not in cfg:
            raise InputError(f"{path}: missing key '{where}{key}'")
    if not _is_int(cfg["in_dim"]) or not 0 < cfg["in_dim"] <= 4096:
        raise InputError(f"{path}: '{where}in_dim' must be an integer in 1..4096")
    hidden = cfg["hidden"]
    if (not isinstance(hidden, list) or not 0 < len(hidden) <= 32
            or not all(_is_int(h) and 0 < h <= 1 << 16 for h in hidden)):
        raise InputError(f"{path}: '{where}hidden' must be a list of 1..32 layer widths "
                         "in 1..65536")
    if cfg.get("head", "regression") not in ("regression", "clusters"):
        raise InputError(f"{path}: '{where}head' must be regression or clusters")
    n = cfg.get("n_clusters", 1)
    if not _is_int(n) or not 0 < n <= 1 << 16:
        raise InputError(f"{path}: '{where}n_clusters' must be an integer in 1..65536")
    if not isinstance(cfg.get("prototype_init", True), bool):
        raise InputError(f"{path}: '{where}prototype_init' must be true or false")
    thr = cfg.get("prototype_threshold", 0.0)
    if not _is_number(thr) or not -1 <= thr <= 1:
        raise InputError(f"{path}: '{where}prototype_threshold' must be a cosine in [-1, 1], "
                         f"got {_short(thr)}")
