"""The map folder: the regressor (what localization needs) plus the labelled training database.

    MAP/slamreloc_map.json   metadata: feature and regressor configs, label/train stats, camera
    MAP/regressor.pt         regressor weights (float16) and output normalisation
    MAP/database.npz         labelled training descriptors (float16), their world points (m),
                             keypoints, frame index, training poses (world_from_cam 4x4) —
                             used by the matching baseline, pseudo-labelling and the viewer
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np
import torch

from slamreloc.errors import InputError
from slamreloc.regressor.model import RegressorConfig, SceneCoordinateRegressor
from slamreloc.types import Camera

MAP_FORMAT = "slamreloc-map"
META, WEIGHTS, DATABASE = "slamreloc_map.json", "regressor.pt", "database.npz"


@dataclass
class MapDatabase:
    descriptors: np.ndarray  # (M, D) float16, labelled training descriptors
    points: np.ndarray  # (M, 3) float32 world points, metres
    keypoints: np.ndarray  # (M, 2) float32 pixels
    frame_index: np.ndarray  # (M,) int32 into frame_names
    frame_names: list[str] = field(default_factory=list)
    world_from_cam: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))


@dataclass
class SceneMap:
    root: Path
    meta: dict
    regressor: SceneCoordinateRegressor

    @staticmethod
    def is_map(path: Path) -> bool:
        return (Path(path) / META).is_file()

    @staticmethod
    def load(path: str | Path) -> SceneMap:
        root = Path(path)
        if not root.is_dir():
            raise InputError(f"{root}: map folder not found")
        if not SceneMap.is_map(root):
            raise InputError(f"{root}: not a slamreloc map (no {META})")
        try:
            meta = json.loads((root / META).read_text())
        except json.JSONDecodeError as err:
            raise InputError(f"{root / META}: not valid JSON ({err})") from None
        if meta.get("format") != MAP_FORMAT:
            raise InputError(f"{root / META}: not a slamreloc map (format={meta.get('format')!r})")
        try:
            state = torch.load(root / WEIGHTS, map_location="cpu", weights_only=True)
            cfg = meta["regressor"]["config"]
            model = SceneCoordinateRegressor(RegressorConfig.from_dict(cfg))
            model.load_state_dict({k: v.float() for k, v in state.items()})
        except (OSError, RuntimeError, KeyError, EOFError) as err:
            raise InputError(f"{root / WEIGHTS}: cannot load regressor ({err})") from None
        return SceneMap(root, meta, model.eval())

    @property
    def camera(self) -> Camera:
        return Camera(**self.meta["camera"])

    @cached_property
    def database(self) -> MapDatabase:
        path = self.root / DATABASE
        if not path.is_file():
            raise InputError(f"{path}: map has no training database")
        with np.load(path) as z:
            return MapDatabase(z["descriptors"], z["points"], z["keypoints"], z["frame_index"],
                               list(self.meta.get("frame_names", [])), z["world_from_cam"])

    def size_bytes(self) -> int:
        """What localization with the regressor needs: weights + metadata."""
        return (self.root / WEIGHTS).stat().st_size + (self.root / META).stat().st_size

    def database_bytes(self) -> int:
        return (self.root / DATABASE).stat().st_size


def check_map_target(out: Path) -> None:
    """Raise unless `out` is absent, an empty folder, or a slamreloc map (to be replaced)."""
    out = Path(out)
    if out.exists() and (not out.is_dir() or (any(out.iterdir()) and not SceneMap.is_map(out))):
        raise InputError(f"{out}: exists and is not a slamreloc map; refusing to overwrite it")


def save_map(out: str | Path, meta: dict, model: SceneCoordinateRegressor, db: MapDatabase) -> Path:
    """Write a map atomically: into a temporary sibling folder, then rename over `out`.

    Refuses to replace an existing non-empty folder that is not a slamreloc map."""
    out = Path(out)
    check_map_target(out)
    tmp = out.parent / f".{out.name}.tmp-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    try:
        state = {k: (v.half() if v.is_floating_point() and v.dim() > 0 and k.startswith("mlp")
                     else v) for k, v in model.state_dict().items()}
        torch.save(state, tmp / WEIGHTS)
        np.savez(tmp / DATABASE, descriptors=db.descriptors.astype(np.float16),
                 points=db.points.astype(np.float32), keypoints=db.keypoints.astype(np.float32),
                 frame_index=db.frame_index.astype(np.int32), world_from_cam=db.world_from_cam)
        meta = {"format": MAP_FORMAT, "version": 1, **meta, "frame_names": db.frame_names}
        (tmp / META).write_text(json.dumps(meta, indent=1))
        if out.exists():
            old = out.parent / f".{out.name}.old-{os.getpid()}"
            os.replace(out, old)
            os.replace(tmp, out)
            shutil.rmtree(old)
        else:
            os.replace(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out
