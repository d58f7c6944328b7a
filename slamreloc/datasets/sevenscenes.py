"""7-Scenes layout (also written by the synthetic generator, which adds scene.json).

    ROOT/seq-XX/frame-XXXXXX.{color.png|color.jpg, depth.png, pose.txt}
    ROOT/TrainSplit.txt, ROOT/TestSplit.txt   lines "sequence1", ...   (optional)
    ROOT/intrinsics.txt                       3x3 K (optional; default fx=fy=525, cx=320, cy=240)
    ROOT/camera.txt                           a COLMAP camera string, any lens model (optional;
                                              read instead of intrinsics.txt)
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from slamreloc.datasets.base import Dataset
from slamreloc.datasets.io import (
    check_frame_files,
    image_size,
    read_intrinsics,
    read_pose,
    read_text,
)
from slamreloc.errors import InputError
from slamreloc.geometry import Rigid3
from slamreloc.io.fileio import file_kind, optional_file, read_bytes
from slamreloc.io.jsonio import parse_json
from slamreloc.types import Camera, Frame

DEFAULT_K = (525.0, 525.0, 320.0, 240.0)
# 7-Scenes' depth is not registered to the RGB images: it comes from the Kinect v1's depth
# camera, fx = fy = 585 px, principal point (320, 240), in the 640x480 depth maps
SEVENSCENES_DEPTH_CAMERA = Camera(640, 480, 585.0, 585.0, 320.0, 240.0)
# Kinect v1 rig: depth camera -> RGB camera (0.6 deg, 2.6 cm along x), the calibration the
# 7-Scenes "calibrated depth" of DSAC* and ACE is made with (LIRIS activities dataset)
SEVENSCENES_RGB_FROM_DEPTH = (
    (0.99996518012567637, 0.0026765126468950343, -0.0079041012313000904, -0.025558943178152542),
    (-0.0027409311281316700, 0.99996302803027592, -0.0081504520778013286, 0.00010109636268061706),
    (0.0078819942130445332, 0.0081718328771890631, 0.99993554558014031, 0.0020318321729487039),
    (0.0, 0.0, 0.0, 1.0))
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
_SEQ = re.compile(r"^seq-?(\d+)$")


def is_sevenscenes(root: Path) -> bool:
    return any(_SEQ.match(p.name) and p.is_dir() for p in root.iterdir())


def load_sevenscenes(root: Path) -> Dataset:
    root = Path(root)
    scene = _read_scene_json(root)
    registered = bool(scene.get("depth_registered", False))
    camera = _camera(root)
    sequences = {}
    for seq_dir in sorted(p for p in root.iterdir() if p.is_dir() and _SEQ.match(p.name)):
        frames = _sequence(seq_dir, camera, registered)
        if frames:
            sequences[seq_dir.name] = frames
    if not sequences:
        raise InputError(f"{root}: 7-Scenes layout but no frame-XXXXXX.color.* files found")
    splits, split_files = {}, {}
    for split, fname in (("train", "TrainSplit.txt"), ("test", "TestSplit.txt")):
        if optional_file(root / fname, "split file"):
            splits[split] = _read_split(root / fname)
            split_files[split] = root / fname
    return Dataset(root, "synthetic" if scene else "7scenes", sequences, splits,
                   depth_registered=registered, roles=scene.get("sequences", {}),
                   split_files=split_files)


def _read_scene_json(root: Path) -> dict:
    path = root / "scene.json"
    if not optional_file(path, "scene description"):  # a folder or pipe there: refused
        return {}
    scene = parse_json(read_bytes(path, "scene description", 1 << 24), path)
    if not isinstance(scene, dict):
        raise InputError(f"{path}: expected a JSON object, got {type(scene).__name__}")
    if not isinstance(scene.get("depth_registered", False), bool):
        raise InputError(f"{path}: 'depth_registered' must be true or false")
    roles = scene.get("sequences", {})
    if not isinstance(roles, dict) or not all(isinstance(k, str) and isinstance(v, str)
                                              for k, v in roles.items()):
        raise InputError(f"{path}: 'sequences' must map sequence names to role names")
    return scene


def _camera(root: Path) -> Camera:
    first = next(iter(sorted(p for p in root.glob("seq*/frame-*.color.*") if _is_image(p))),
                 None)
    if first is None:
        raise InputError(f"{root}: no seq-XX/frame-XXXXXX.color.* images found")
    width, height = image_size(first)
    if optional_file(root / "camera.txt", "camera"):  # a COLMAP camera string: any lens model
        path = root / "camera.txt"
        camera = Camera.parse(read_text(path, "camera", 1 << 12), str(path))
        if (camera.width, camera.height) != (width, height):
            raise InputError(f"{path}: camera is {camera.width}x{camera.height} but {first} is "
                             f"{width}x{height}")
        if optional_file(root / "intrinsics.txt", "intrinsics"):  # both: they must agree
            k = read_intrinsics(root / "intrinsics.txt")
            given = np.array([k[0, 0], k[1, 1], k[0, 2], k[1, 2]], np.float64)
            own = camera.pinhole.params()
            if not np.allclose(own, given, rtol=1e-6, atol=1e-6):
                raise InputError(f"{path}: camera (fx fy cx cy "
                                 f"{' '.join(f'{v:g}' for v in own)}) and "
                                 f"{root / 'intrinsics.txt'} ({' '.join(f'{v:g}' for v in given)})"
                                 " disagree; keep one")
        return camera
    if optional_file(root / "intrinsics.txt", "intrinsics"):
        k = read_intrinsics(root / "intrinsics.txt")
        try:
            return Camera(width, height, k[0, 0], k[1, 1], k[0, 2], k[1, 2])
        except InputError as err:  # the camera rule with the images' size: name the file
            raise InputError(f"{root / 'intrinsics.txt'}: {err} (the images are "
                             f"{width}x{height})") from None
    fx, fy, cx, cy = DEFAULT_K  # 7-Scenes' camera: never stretched onto another aspect ratio
    return Camera(640, 480, fx, fy, cx, cy).for_image(
        width, height, f"{first}: the default 7-Scenes camera (give the dataset an "
        "intrinsics.txt or a camera.txt)")


def _is_image(path: Path) -> bool:
    """A frame's colour image by its name; InputError where that name is not a file (a
    folder, a link to nothing): the frame would otherwise vanish from the dataset unsaid."""
    if path.suffix.lower() not in IMAGE_SUFFIXES:
        return False
    if not path.is_file():
        try:
            kind = file_kind(os.stat(path).st_mode)
        except OSError:
            kind = "a broken link" if os.path.islink(path) else "not readable"
        raise InputError(f"{path}: named as a colour image but not a regular file ({kind})")
    return True


def _sequence(seq_dir: Path, camera: Camera, registered: bool) -> list[Frame]:
    """The sequence's frames; depth not `registered` is the Kinect's depth camera's."""
    frames = []
    rgb_from_depth = None if registered else sevenscenes_rgb_from_depth()
    first: dict[str, Path] = {}  # frame stem -> its colour image
    for color in sorted((p for p in seq_dir.glob("frame-*.color.*") if _is_image(p)),
                        key=_frame_order):
        stem = color.name.split(".")[0]
        if stem in first:  # frame-000000.color.png and .color.jpg: which is the frame?
            raise InputError(f"{color}: frame {seq_dir.name}/{stem} has two colour images "
                             f"({first[stem].name} and {color.name}); keep one")
        first[stem] = color
        depth = seq_dir / f"{stem}.depth.png"
        pose_path = seq_dir / f"{stem}.pose.txt"
        has_depth = os.path.lexists(depth)
        if has_depth and not depth.is_file():  # a folder, a device, a broken link: not "none"
            raise InputError(f"{depth}: the frame's depth image is not a regular file")
        check_frame_files(color, (camera.width, camera.height),
                          depth if has_depth else None, check_depth=registered)
        unregistered = has_depth and not registered
        frames.append(Frame(
            name=f"{seq_dir.name}/{stem}", image_path=color, camera=camera,
            depth_path=depth if has_depth else None,
            world_from_cam=(read_pose(pose_path) if optional_file(pose_path, "pose")
                            else None),
            sequence=seq_dir.name, timestamp=float(len(frames)) / 30.0,
            depth_camera=SEVENSCENES_DEPTH_CAMERA if unregistered else None,
            rgb_from_depth=rgb_from_depth if unregistered else None))
    # a frame whose pose or depth is there without its image would vanish from the dataset
    for other in sorted([*seq_dir.glob("frame-*.pose.txt"), *seq_dir.glob("frame-*.depth.png")]):
        stem = other.name.split(".")[0]
        if stem not in first:
            raise InputError(f"{other}: frame {seq_dir.name}/{stem} has no colour image "
                             f"({stem}.color.png or .jpg); restore it, or remove its files")
    return frames


def sevenscenes_rgb_from_depth() -> Rigid3:
    """The Kinect v1 rig's depth camera in its RGB camera's frame (metres)."""
    return Rigid3.from_matrix(np.array(SEVENSCENES_RGB_FROM_DEPTH), source="7-Scenes rig")


def _frame_order(color: Path) -> tuple:
    """Frames in the order of their numbers (frame-2 before frame-10 where they are written
    without zeros in front), then by name."""
    number = re.fullmatch(r"frame-([0-9]+)", color.name.split(".")[0])
    return (0, int(number.group(1)), color.name) if number else (1, 0, color.name)


def _read_split(path: Path) -> list[str]:
    """Sequence names of a split file; whether they exist is checked when the split is used."""
    names = []
    for word in read_text(path, "split", "max_text_bytes").split():
        m = re.fullmatch(r"sequence([0-9]{1,6})", word)  # ASCII digits, as every number
        if not m:
            raise InputError(f"{path}: expected lines like 'sequence1', got {word[:40]!r}")
        name = f"seq-{int(m.group(1)):02d}"
        if name in names:  # as `--split seq-01,seq-01`: its frames would be used twice
            raise InputError(f"{path}: names {name} twice ({word[:40]!r}): its frames would be "
                             "used twice")
        names.append(name)
    return names
