"""Structural checks of a COLMAP sparse model, before pycolmap reads anything.

pycolmap's binary reader does not notice a truncated file (it reads on past the end) and
trusts every count it reads, so a damaged `.bin` would load garbage, allocate without bound or
never return: each file is walked here record by record (bounds-checked little-endian reads),
and a text file line by line, so that any defect is an InputError naming the file (and the
line). The walk also checks what the adapter relies on: known camera models with finite
parameters and sane image sizes, unique image ids and names, images whose camera exists.
"""

from __future__ import annotations

import math
import mmap
import struct
from dataclasses import dataclass
from functools import cache
from pathlib import Path

from slamreloc.datasets.io import read_text
from slamreloc.errors import InputError
from slamreloc.geometry import MAX_COORDINATE, unit_quaternion
from slamreloc.io.fileio import open_regular
from slamreloc.io.numbers import parse_number, parse_whole

MAX_NAME_BYTES = 4096
MAX_TEXT_BYTES = 1 << 31


@cache
def camera_models() -> dict[int, tuple[str, int]]:
    """COLMAP camera model id -> (name, number of parameters), as this pycolmap knows them."""
    import pycolmap

    models = {}
    for model in pycolmap.CameraModelId.__members__.values():
        if model.name != "INVALID":
            cam = pycolmap.Camera.create_from_model_id(1, model, 1.0, 1, 1)
            models[int(model)] = (model.name, len(cam.params))
    return models


class _Binary:
    """Bounds-checked little-endian reads of a whole file."""

    def __init__(self, path: Path, data: bytes | mmap.mmap) -> None:
        self.path, self.data, self.pos = path, data, 0

    def take(self, fmt: str, what: str) -> tuple:
        size = struct.calcsize(fmt)
        if self.pos + size > len(self.data):
            raise InputError(f"{self.path}: truncated (ends inside {what})")
        values = struct.unpack_from(fmt, self.data, self.pos)
        self.pos += size
        return values

    def skip(self, n_bytes: int, what: str) -> None:
        if self.pos + n_bytes > len(self.data):
            raise InputError(f"{self.path}: truncated (ends inside {what})")
        self.pos += n_bytes

    def count(self, min_record_bytes: int, what: str) -> int:
        (n,) = self.take("<Q", f"the number of {what}")
        left = len(self.data) - self.pos
        if n * min_record_bytes > left:
            raise InputError(f"{self.path}: damaged or truncated (claims {n} {what} in "
                             f"{left} bytes)")
        return n

    def name(self, what: str) -> str:
        end = self.data.find(b"\0", self.pos, self.pos + MAX_NAME_BYTES + 1)
        if end < 0:
            if len(self.data) - self.pos <= MAX_NAME_BYTES:
                raise InputError(f"{self.path}: truncated (ends inside {what})")
            raise InputError(f"{self.path}: {what} is longer than {MAX_NAME_BYTES} bytes")
        raw = bytes(self.data[self.pos:end])
        self.pos = end + 1
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError:
            raise InputError(f"{self.path}: {what} is not UTF-8 text") from None

    def end(self) -> None:
        if self.pos != len(self.data):
            raise InputError(f"{self.path}: {len(self.data) - self.pos} bytes after the last "
                             "record (damaged file)")


def _walk_binary(path: Path, walk) -> object:
    try:
        with open_regular(path, "COLMAP model") as f:  # never a pipe or a device
            size = f.seek(0, 2)
            if size == 0:
                raise InputError(f"{path}: empty file")
            with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as data:
                return walk(_Binary(path, data))
    except OSError as err:
        raise InputError(f"{path}: cannot read ({err.strerror or err})") from None


@dataclass(frozen=True)
class ModelIndex:
    """What the structural check learnt: camera models and the images' camera ids."""

    camera_models: dict[int, int]  # camera id -> model id
    image_cameras: dict[str, int]  # image name -> camera id


def _walk_cameras(r: _Binary) -> dict[int, int]:
    models, out = camera_models(), {}
    n = r.count(24, "cameras")
    for i in range(n):
        what = f"camera {i + 1} of {n}"
        cam_id, model = r.take("<Ii", what)
        if model not in models:
            raise InputError(f"{r.path}: camera {cam_id} has unknown camera model id {model}")
        width, height = r.take("<QQ", what)
        params = r.take(f"<{models[model][1]}d", what)
        _check_camera(r.path, cam_id, width, height, params)
        out[cam_id] = model
    r.end()
    return out


def _check_camera(path, cam_id: int, width: int, height: int, params) -> None:
    if not (0 < width <= 1 << 16 and 0 < height <= 1 << 16):
        raise InputError(f"{path}: camera {cam_id} has image size {width}x{height}")
    if not all(math.isfinite(p) for p in params):
        raise InputError(f"{path}: camera {cam_id} has non-finite parameters")


def _walk_images(r: _Binary) -> dict[int, tuple[str, int]]:
    out = {}
    n = r.count(73, "images")
    for i in range(n):
        what = f"image {i + 1} of {n}"
        image_id, *pose, cam_id = r.take("<I7dI", what)
        _check_image_pose(r.path, image_id, pose)
        name = r.name(f"the name of {what}")
        (n_points,) = r.take("<Q", what)
        r.skip(24 * n_points, f"the points of {what}")
        _add_image(out, r.path, image_id, name, cam_id)
    r.end()
    return out


def _check_image_pose(where, image_id: int, pose) -> None:
    """QW QX QY QZ TX TY TZ: finite, and a unit quaternion (COLMAP writes them normalised; a
    zero or far-from-unit one is damage, which normalising would turn into a made-up pose)."""
    if not all(math.isfinite(v) for v in pose) or max(abs(v) for v in pose[4:]) > MAX_COORDINATE:
        raise InputError(f"{where}: image {image_id} has a non-finite pose or a translation "
                         f"beyond {MAX_COORDINATE:g}")
    unit_quaternion(pose[:4], f"{where}: image {image_id} (QW QX QY QZ)")


def _add_image(out: dict, path, image_id: int, name: str, cam_id: int) -> None:
    if image_id in out:
        raise InputError(f"{path}: image id {image_id} appears twice")
    out[image_id] = (name, cam_id)


def _walk_rigs(r: _Binary) -> None:
    n = r.count(8, "rigs")
    for i in range(n):
        what = f"rig {i + 1} of {n}"
        _, n_sensors = r.take("<II", what)
        if n_sensors and 8 + 9 * (n_sensors - 1) > len(r.data) - r.pos:
            raise InputError(f"{r.path}: damaged or truncated ({what} claims {n_sensors} "
                             "sensors)")
        if n_sensors:
            r.skip(8, what)
        for _ in range(max(n_sensors - 1, 0)):
            _, _, has_pose = r.take("<iIB", what)
            if has_pose:
                r.skip(56, what)
    r.end()


def _walk_frames(r: _Binary) -> None:
    n = r.count(68, "frames")
    for i in range(n):
        what = f"frame {i + 1} of {n}"
        r.skip(64, what)
        (n_data,) = r.take("<I", what)
        r.skip(16 * n_data, what)
    r.end()


def _model_text(path: Path) -> str:
    """A text model file as text; InputError for one that starts with a byte-order mark,
    which slamreloc's other text readers drop but COLMAP's own reader (that reads the model
    after this check) takes for part of the first line."""
    text = read_text(path, "COLMAP model", MAX_TEXT_BYTES)
    with open(path, "rb") as f:
        if f.read(3) == b"\xef\xbb\xbf":
            raise InputError(f"{path}: starts with a UTF-8 byte-order mark, which COLMAP's "
                             "reader does not skip (save the file without it)")
    return text


def _text_rows(path: Path) -> list[tuple[int, list[str]]]:
    """(line number, words) of the data lines (not blank, not comments)."""
    text = _model_text(path)
    return [(i, line.split()) for i, line in enumerate(text.splitlines(), 1)
            if line.strip() and not line.lstrip().startswith("#")]


def _number(path: Path, line: int, word: str, what: str, integer: bool = False,
            low: int = 0) -> float:
    """A field of a COLMAP text model (`slamreloc.io.numbers`: plain ASCII decimal, finite);
    `integer`: a whole number in low..2^32-1 (an id; POINT3D_ID -1 is "none")."""
    if not integer:
        return parse_number(word, f"{path}:{line}", what)
    value = parse_whole(word, f"{path}:{line}", what)
    if not low <= value < 1 << 32:
        raise InputError(f"{path}:{line}: {what} out of range ({word[:40]})")
    return value


def _read_cameras_text(path: Path) -> dict[int, int]:
    by_name = {name: (model_id, n) for model_id, (name, n) in camera_models().items()}
    out = {}
    for line, words in _text_rows(path):
        if len(words) < 4:
            raise InputError(f"{path}:{line}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS...")
        cam_id = int(_number(path, line, words[0], "CAMERA_ID", integer=True))
        if words[1] not in by_name:
            raise InputError(f"{path}:{line}: unknown camera model {words[1][:40]!r}")
        model_id, n_params = by_name[words[1]]
        if len(words) != 4 + n_params:
            raise InputError(f"{path}:{line}: the {words[1]} model has {n_params} parameters, "
                             f"got {len(words) - 4}")
        width, height = (int(_number(path, line, w, k, integer=True))
                         for w, k in zip(words[2:4], ("WIDTH", "HEIGHT")))
        params = [_number(path, line, w, "a parameter") for w in words[4:]]
        _check_camera(f"{path}:{line}", cam_id, width, height, params)
        if cam_id in out:
            raise InputError(f"{path}:{line}: camera id {cam_id} appears twice")
        out[cam_id] = model_id
    return out


def _read_images_text(path: Path) -> dict[int, tuple[str, int]]:
    """Mirrors COLMAP's reader: an image line (data), then the next line holds its points."""
    text = _model_text(path)
    lines = text.splitlines()
    out, i = {}, 0
    while i < len(lines):
        words = lines[i].split()
        i += 1
        if not words or words[0].startswith("#"):
            continue
        line = i
        if len(words) != 10:
            raise InputError(f"{path}:{line}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID "
                             f"NAME (10 fields), got {len(words)}")
        image_id = int(_number(path, line, words[0], "IMAGE_ID", integer=True))
        pose = [_number(path, line, w, "a pose value") for w in words[1:8]]
        _check_image_pose(f"{path}:{line}", image_id, pose)
        cam_id = int(_number(path, line, words[8], "CAMERA_ID", integer=True))
        points = lines[i].split() if i < len(lines) else []
        i += 1
        if len(points) % 3:
            raise InputError(f"{path}:{line + 1}: expected X Y POINT3D_ID triples, got "
                             f"{len(points)} values")
        for k, w in enumerate(points):  # X Y POINT3D_ID (-1: no point)
            if k % 3 == 2:
                _number(path, line + 1, w, "a POINT3D_ID", integer=True, low=-1)
            else:
                _number(path, line + 1, w, "a 2D point coordinate")
        if image_id in out:
            raise InputError(f"{path}:{line}: image id {image_id} appears twice")
        out[image_id] = (words[9], cam_id)
    return out


def check_model(folder: Path, ext: str) -> ModelIndex:
    """Walk every model file slamreloc uses; InputError naming the file on any defect."""
    if ext == "bin":
        cams = _walk_binary(folder / "cameras.bin", _walk_cameras)
        images = _walk_binary(folder / "images.bin", _walk_images)
        for name, walk in (("rigs", _walk_rigs), ("frames", _walk_frames)):
            if (folder / f"{name}.bin").is_file():
                _walk_binary(folder / f"{name}.bin", walk)
    else:
        cams = _read_cameras_text(folder / "cameras.txt")
        images = _read_images_text(folder / "images.txt")
        for name in ("rigs", "frames"):
            if (folder / f"{name}.txt").is_file():
                _model_text(folder / f"{name}.txt")
    images_file = folder / f"images.{ext}"
    by_name = {}
    for name, cam_id in images.values():
        if cam_id not in cams:
            raise InputError(f"{images_file}: image {name!r} has camera {cam_id}, which "
                             f"cameras.{ext} does not have")
        if name in by_name:
            raise InputError(f"{images_file}: image name {name!r} appears twice")
        by_name[name] = cam_id
    return ModelIndex(cams, by_name)
