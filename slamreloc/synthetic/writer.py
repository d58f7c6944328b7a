"""Render the synthetic scene to disk in the 7-Scenes layout, plus scene.json.

    out_dir/seq-XX/frame-NNNNNN.color.png   RGB image (PNG)
    out_dir/seq-XX/frame-NNNNNN.depth.png   uint16 z-depth in millimetres, 0 = invalid
    out_dir/seq-XX/frame-NNNNNN.pose.txt    4x4 world_from_cam, metres
    out_dir/intrinsics.txt, TrainSplit.txt, TestSplit.txt, scene.json
    out_dir/camera.txt                      the COLMAP camera string of a distorted lens
"""

from __future__ import annotations

import json
import os
import re
import shutil
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from slamreloc.errors import InputError
from slamreloc.io.fileio import read_bytes
from slamreloc.io.folder_lock import Debris, folder_write_lock, holds_only, leftovers
from slamreloc.io.images import write_image
from slamreloc.io.outputs import make_temp_dir, temp_dir_path
from slamreloc.synthetic.render import RenderScene, render_frame
from slamreloc.synthetic.room import build_room
from slamreloc.synthetic.trajectories import SEQUENCES, make_trajectories
from slamreloc.types import Camera

GENERATOR, VERSION = "slamreloc-synthetic", 2
MIN_CLEARANCE_M = 0.4


@dataclass(frozen=True)
class SceneConfig:
    """Seed, image size, intrinsics (pixels) and lens model (`slamreloc.camera_models`: PINHOLE,
    or OPENCV, OPENCV_FISHEYE, ... with its distortion parameters), and frames per
    sequence."""

    seed: int = 0
    width: int = 640
    height: int = 480
    fx: float = 525.0
    fy: float = 525.0
    cx: float = 319.5
    cy: float = 239.5
    n_map: int = 150
    n_query: int = 60
    n_kidnap: int = 120
    n_unlabelled: int = 80
    model: str = "PINHOLE"
    distortion: tuple[float, ...] = ()

    def camera(self) -> Camera:
        return Camera(self.width, self.height, self.fx, self.fy, self.cx, self.cy, self.model,
                      self.distortion)

    def counts(self) -> dict[str, int]:
        return dict(zip(SEQUENCES, (self.n_map, self.n_query, self.n_kidnap, self.n_unlabelled)))


def scene_json(config: SceneConfig) -> dict:
    fields = asdict(config)
    if config.model == "PINHOLE":  # as before lens models existed: old scenes stay valid
        del fields["model"], fields["distortion"]
    return {"generator": GENERATOR, "version": VERSION, "seed": config.seed,
            "width": config.width, "height": config.height, "depth_registered": True,
            "sequences": dict(SEQUENCES), "config": fields}


def _existing(out_dir: Path, config: SceneConfig) -> bool:
    """True if out_dir already holds this scene; InputError if it holds anything else."""
    if not out_dir.exists() or (out_dir.is_dir() and not any(out_dir.iterdir())):
        return False  # missing or empty: render into it
    try:
        meta = json.loads(read_bytes(out_dir / "scene.json", "scene", 16 << 20))
    except (OSError, ValueError, InputError):
        raise InputError(f"{out_dir}: exists and is not a synthetic scene "
                         "(no valid scene.json)") from None
    if meta != json.loads(json.dumps(scene_json(config))):
        raise InputError(f"{out_dir}: holds a synthetic scene with a different config; "
                         "remove it or choose another folder")
    return True


Progress = Callable[[int, int], None]


def _write_frames(tmp: Path, config: SceneConfig, progress: Progress | None) -> None:
    scene = RenderScene(build_room(config.seed))
    camera = config.camera()
    trajectories = make_trajectories(config.seed, config.counts())
    centres = np.array([p.translation for poses in trajectories.values() for p in poses])
    if len(centres) and scene.distance(centres).min() < MIN_CLEARANCE_M - 0.05:
        raise RuntimeError("synthetic trajectories come too close to the scene geometry")
    total, done = sum(len(p) for p in trajectories.values()), 0
    for seq_index, (seq, poses) in enumerate(trajectories.items()):
        (tmp / seq).mkdir()
        for i, world_from_cam in enumerate(poses):
            rgb, depth = render_frame(scene, camera, world_from_cam,
                                      noise_seed=(config.seed, seq_index, i))
            stem = tmp / seq / f"frame-{i:06d}"
            depth_mm = np.where(np.isfinite(depth) & (depth < 65.5), depth * 1000.0 + 0.5, 0)
            write_image(f"{stem}.color.png", rgb[:, :, ::-1])
            write_image(f"{stem}.depth.png", depth_mm.astype(np.uint16))
            np.savetxt(f"{stem}.pose.txt", world_from_cam.matrix())
            done += 1
            if progress is not None:
                progress(done, total)
    np.savetxt(tmp / "intrinsics.txt", camera.K)
    if camera.distorted:
        (tmp / "camera.txt").write_text(camera.colmap_string() + "\n")
    (tmp / "TrainSplit.txt").write_text("sequence1\n")
    (tmp / "TestSplit.txt").write_text("sequence2\n")
    (tmp / "scene.json").write_text(json.dumps(scene_json(config), indent=2) + "\n")


_SCENE_FILES = {"intrinsics.txt", "camera.txt", "TrainSplit.txt", "TestSplit.txt",
                "scene.json"}
_SEQUENCE = re.compile(r"seq-[0-9]{2}")
_FRAME_FILE = re.compile(r"frame-[0-9]{6}\.(?:color\.png|depth\.png|pose\.txt)")


def _only_scene_files(folder: Path) -> bool:
    """Whether `folder` holds nothing but what `render_scene` writes: its top-level files
    and `seq-XX` folders of frame files, all regular files (a killed render's temporary)."""
    def regular(entry: os.DirEntry) -> bool:
        return entry.is_file(follow_symlinks=False)

    def frame(entry: os.DirEntry) -> bool:
        return regular(entry) and _FRAME_FILE.fullmatch(entry.name) is not None

    def scene_entry(entry: os.DirEntry) -> bool:
        if entry.is_dir(follow_symlinks=False) and _SEQUENCE.fullmatch(entry.name):
            return holds_only(entry.path, frame)
        return regular(entry) and entry.name in _SCENE_FILES

    return holds_only(folder, scene_entry)


# a render cut short (a scene is written in one rename: never moved aside)
SCENE_DEBRIS = Debris(new=_only_scene_files, old=None, put_back=None)


def render_scene(out_dir: Path, config: SceneConfig = SceneConfig(),
                 progress: Progress | None = None) -> Path:
    """Render all sequences into out_dir (atomically, via a temporary sibling folder, under
    the folder's write lock: a killed render's temporary is removed by the next render of
    it). A scene already there with this config is taken as it is; another process writing
    the folder is refused at once, as every folder writer does; a symbolic
    link at out_dir is refused before any work, never rendered through."""
    out_dir = Path(out_dir)
    if os.path.islink(out_dir):
        raise InputError(f"{out_dir}: is a symbolic link (to {os.readlink(out_dir)[:200]}); a "
                         "scene is rendered into a folder, never through a link: give a plain "
                         "path")
    if _existing(out_dir, config) and not leftovers(out_dir, SCENE_DEBRIS):
        return out_dir
    with folder_write_lock(out_dir, "this scene", SCENE_DEBRIS):
        if not _existing(out_dir, config):
            _render_into(out_dir, config, progress)
    return out_dir


def _render_into(out_dir: Path, config: SceneConfig, progress: Progress | None) -> None:
    tmp = make_temp_dir(temp_dir_path(out_dir), str(out_dir))
    try:
        _write_frames(tmp, config, progress)
        os.replace(tmp, out_dir)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
