"""COLMAP projects made from another dataset's frames (pycolmap writes the model), for tests."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from slamreloc.types import Frame


def write_colmap_project(frames: list[Frame], root: Path, ext: str = "bin",
                         legacy: bool = False, model_dir: str = "sparse/0",
                         model: str = "PINHOLE", distortion: tuple[float, ...] = ()) -> Path:
    """ROOT/images/<sequence>/<file> and a sparse model of `frames` (posed, one camera per
    distinct `frame.camera`, numbered from 1 in order of appearance: COLMAP's principal point
    is ours + 0.5; `model` PINHOLE, or OPENCV etc. with `distortion` after fx, fy, cx, cy).
    `legacy`: without rigs and frames files, as COLMAP before 3.12 writes one."""
    import pycolmap

    rec = pycolmap.Reconstruction()
    camera_ids: dict = {}
    for cam in (f.camera for f in frames):
        if cam not in camera_ids:
            camera_ids[cam] = len(camera_ids) + 1
            rec.add_camera_with_trivial_rig(pycolmap.Camera(
                model=model, width=cam.width, height=cam.height, camera_id=camera_ids[cam],
                params=[cam.fx, cam.fy, cam.cx + 0.5, cam.cy + 0.5, *distortion]))
    (root / "images").mkdir(parents=True)
    for i, f in enumerate(frames):
        name = f"{f.sequence}/{f.image_path.name}"
        (root / "images" / f.sequence).mkdir(exist_ok=True)
        shutil.copy(f.image_path, root / "images" / name)
        cam_from_world = f.world_from_cam.inverse()
        rec.add_image_with_trivial_frame(
            pycolmap.Image(name=name, camera_id=camera_ids[f.camera], image_id=i + 1),
            pycolmap.Rigid3d(pycolmap.Rotation3d(cam_from_world.rotation),
                             np.asarray(cam_from_world.translation, np.float64)))
    model = root / model_dir
    model.mkdir(parents=True)
    rec.write_binary(str(model)) if ext == "bin" else rec.write_text(str(model))
    if legacy:
        for name in ("rigs", "frames"):
            (model / f"{name}.{ext}").unlink()
    return root
