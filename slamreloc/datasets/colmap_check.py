"""Structural checks of a COLMAP sparse model, before pycolmap reads anything.

pycolmap's binary reader does not notice a truncated file (it reads on past the end) and
trusts every count it reads, so a damaged `.bin` would load garbage, allocate without bound or
never return: each file is walked here record by record (bounds-checked little-endian reads),
and a text file line by line, so that any defect is an InputError naming the file (and the
line). The walk also checks what the adapter relies on: known camera models with finite
parameters and sane image sizes, unique image ids and names, images whose camera exists, and
in a COLMAP >= 3.12 model the rigs and frames that pose the images (every sensor, image and
rig they name exists, each image in one frame, unit quaternions).

A text model file is bounded by `max_text_bytes` (`slamreloc.io.limits`) and held in memory
once, as bytes: a line is never split into a list of all its words (a POINTS2D line of 150 MB
would be 17 million str objects, ~28 times the file), but matched by a compiled pattern or
read a word at a time.
"""

from __future__ import annotations

import math
import mmap
import re
import struct
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import cache
from pathlib import Path

from slamreloc.errors import InputError
from slamreloc.geometry import MAX_COORDINATE, unit_quaternion
from slamreloc.io.fileio import open_regular, optional_file, read_text_bytes
from slamreloc.io.numbers import parse_number, parse_whole

MAX_NAME_BYTES = 4096  # an image name, in .bin and .txt models alike
TEXT_LIMIT = "max_text_bytes"  # the bound on a text model file (`slamreloc.io.limits`)
RIG_FILES = ("rigs", "frames")  # COLMAP >= 3.12: both, or neither


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


@cache
def sensor_types() -> dict[int, str]:
    """COLMAP sensor type id -> name (CAMERA, IMU), as this pycolmap knows them: the types
    a rig's sensor or a frame's data may have (rigs.bin writes the id, rigs.txt the name)."""
    import pycolmap

    return {int(t): t.name for t in pycolmap.SensorType.__members__.values()
            if t.name != "INVALID"}


CAMERA_SENSOR = "CAMERA"  # the sensor type whose data are images (of the camera of its id)


def _camera_sensor_type() -> int:
    """The type id of CAMERA_SENSOR."""
    return next(i for i, name in sensor_types().items() if name == CAMERA_SENSOR)


class _Binary:
    """Bounds-checked little-endian reads of a whole file. As a record reader (`records`):
    `where` names the file, `record` the record being read (for "truncated" messages)."""

    def __init__(self, path: Path, data: bytes | mmap.mmap) -> None:
        self.path, self.data, self.pos = path, data, 0
        self.where, self.record = str(path), "the file"

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
            raise _name_too_long(self.path, what)
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

    def records(self, min_record_bytes: int, noun: str) -> Iterator[_Binary]:
        """This reader once per record of the file (its count first: `count`), `record`
        naming each ("frame 2 of 6"); the file must end with the last."""
        n = self.count(min_record_bytes, f"{noun}s")
        for i in range(n):
            self.record = f"{noun} {i + 1} of {n}"
            yield self
        self.end()

    def whole(self, what: str, bits: int = 32) -> int:
        """An unsigned id or count of `bits` (32 or 64) bits."""
        return self.take("<Q" if bits == 64 else "<I", self.record)[0]

    def flag(self, what: str) -> bool:
        """A byte that is 0 or 1 (COLMAP writes nothing else there)."""
        (value,) = self.take("<B", self.record)
        if value > 1:
            raise InputError(f"{self.path}: {self.record}: {what} is {value}, not 0 or 1")
        return bool(value)

    def pose(self, what: str) -> tuple[float, ...]:
        """QW QX QY QZ TX TY TZ."""
        return self.take("<7d", self.record)

    def sensor(self, what: str) -> tuple[int, int]:
        """(sensor type id, sensor id); InputError for a type `sensor_types` does not know."""
        kind, sensor_id = self.take("<iI", self.record)
        if kind not in sensor_types():
            raise _unknown_sensor(self.where, what, kind)
        return kind, sensor_id

    def done(self) -> None:
        """The end of a record (a binary record's size is its fields')."""


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
    """What the structural check learnt: camera models and the images' camera ids; for a
    text model, also images.txt as the check read it with its POINTS2D lines emptied (what
    pycolmap is given to read: slamreloc uses no 2D point)."""

    camera_models: dict[int, int]  # camera id -> model id
    image_cameras: dict[str, int]  # image name -> camera id
    images_text: bytes | None = None  # images.txt, image lines only (None: a .bin model)


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


def _name_too_long(where, what: str) -> InputError:
    """The one bound on an image name (MAX_NAME_BYTES, UTF-8 bytes), .bin and .txt alike."""
    return InputError(f"{where}: {what} is longer than {MAX_NAME_BYTES} bytes")


def _check_pose(where, what: str, pose) -> None:
    """QW QX QY QZ TX TY TZ of `what` (an image, a frame, a rig's sensor): finite, the
    translation within MAX_COORDINATE (the model's units), the quaternion a unit one by
    `unit_quaternion` (the rule of every pose read; COLMAP writes them normalised: a zero or
    far-from-unit one is damage, which normalising would turn into a made-up pose)."""
    if not all(math.isfinite(v) for v in pose) or max(abs(v) for v in pose[4:]) > MAX_COORDINATE:
        raise InputError(f"{where}: {what} has a non-finite pose or a translation beyond "
                         f"{MAX_COORDINATE:g}")
    unit_quaternion(pose[:4], f"{where}: {what} (QW QX QY QZ)")


def _check_image_pose(where, image_id: int, pose) -> None:
    """`_check_pose` of the pose an image line or record holds."""
    _check_pose(where, f"image {image_id}", pose)


def _add_image(out: dict, path, image_id: int, name: str, cam_id: int) -> None:
    if image_id in out:
        raise InputError(f"{path}: image id {image_id} appears twice")
    out[image_id] = (name, cam_id)


def _unknown_sensor(where: str, what: str, kind) -> InputError:
    known = ", ".join(f"{name} ({i})" for i, name in sensor_types().items())
    return InputError(f"{where}: {what} has unknown sensor type {str(kind)[:40]!r} (known: "
                      f"{known})")


def _sensor_text(sensor: tuple[int, int]) -> str:
    """A sensor in words: `CAMERA 1`."""
    return f"{sensor_types()[sensor[0]]} {sensor[1]}"


def _walk_rigs(records: Iterator, cams: dict[int, int],
               cameras_file: str) -> dict[int, set[tuple[int, int]]]:
    """Each rig's sensors ((type, id): `sensor`) by rig id, from the records of rigs.bin or
    rigs.txt (RIG_ID NUM_SENSORS, the reference sensor's TYPE ID, then each other sensor's
    TYPE ID HAS_POSE [QW QX QY QZ TX TY TZ]): unique rig ids, no sensor twice in a rig, every
    camera sensor a camera of `cams`, every sensor pose by `_check_pose`."""
    camera, rigs = _camera_sensor_type(), {}
    for r in records:
        rig_id = r.whole("RIG_ID")
        sensors: set[tuple[int, int]] = set()
        for k in range(r.whole("NUM_SENSORS")):
            sensor = r.sensor(f"sensor {k + 1} of rig {rig_id}")
            if sensor in sensors:
                raise InputError(f"{r.where}: rig {rig_id} holds {_sensor_text(sensor)} twice")
            if sensor[0] == camera and sensor[1] not in cams:
                raise InputError(f"{r.where}: rig {rig_id} names camera {sensor[1]}, which "
                                 f"{cameras_file} does not have")
            if k and r.flag(f"HAS_POSE of sensor {k + 1} of rig {rig_id}"):
                _check_pose(r.where, f"rig {rig_id}'s sensor {_sensor_text(sensor)}",
                            r.pose("SENSOR_FROM_RIG"))
            sensors.add(sensor)
        r.done()
        if rig_id in rigs:
            raise InputError(f"{r.where}: rig id {rig_id} appears twice")
        rigs[rig_id] = sensors
    return rigs


def _walk_frames(records: Iterator, rigs: dict[int, set[tuple[int, int]]],
                 images: dict[int, tuple[str, int]], files: tuple[str, str]) -> dict[int, int]:
    """Frame id by image id of every image a frame holds, from the records of frames.bin or
    frames.txt (FRAME_ID RIG_ID QW QX QY QZ TX TY TZ NUM_DATA_IDS, then each datum's
    SENSOR_TYPE SENSOR_ID DATA_ID): unique frame ids, rigs of `rigs`, poses by `_check_pose`,
    each datum's sensor one of its rig's, each image (a CAMERA datum) one of `images`, of
    that camera, in one frame only. `files`: the rigs and images files' names."""
    camera, frames, framed = _camera_sensor_type(), set(), {}
    for r in records:
        frame_id, rig_id = r.whole("FRAME_ID"), r.whole("RIG_ID")
        if frame_id in frames:
            raise InputError(f"{r.where}: frame id {frame_id} appears twice")
        if rig_id not in rigs:
            raise InputError(f"{r.where}: frame {frame_id} names rig {rig_id}, which "
                             f"{files[0]} does not have")
        _check_pose(r.where, f"frame {frame_id}", r.pose("RIG_FROM_WORLD"))
        for k in range(r.whole("NUM_DATA_IDS")):
            sensor = r.sensor(f"datum {k + 1} of frame {frame_id}")
            data_id = r.whole("DATA_ID", bits=64)
            if sensor not in rigs[rig_id]:
                raise InputError(f"{r.where}: frame {frame_id} names {_sensor_text(sensor)}, "
                                 f"which its rig {rig_id} does not have")
            if sensor[0] == camera:
                _frame_image(r.where, frame_id, sensor[1], data_id, images, framed, files[1])
        r.done()
        frames.add(frame_id)
    return framed


def _frame_image(where: str, frame_id: int, cam_id: int, image_id: int,
                 images: dict[int, tuple[str, int]], framed: dict[int, int],
                 images_file: str) -> None:
    """Record that frame `frame_id` holds image `image_id` of camera `cam_id`; InputError
    unless the image exists, is of that camera and is in no other frame."""
    if image_id not in images:
        raise InputError(f"{where}: frame {frame_id} names image {image_id}, which "
                         f"{images_file} does not have")
    if images[image_id][1] != cam_id:
        raise InputError(f"{where}: frame {frame_id} names image {image_id} as one of camera "
                         f"{cam_id}, but {images_file} gives it camera {images[image_id][1]}")
    if image_id in framed:
        raise InputError(f"{where}: image {image_id} is in frames {framed[image_id]} and "
                         f"{frame_id}")
    framed[image_id] = frame_id


def _check_rigs_and_frames(folder: Path, ext: str, cams: dict[int, int],
                           images: dict[int, tuple[str, int]]) -> None:
    """COLMAP >= 3.12's rigs and frames files, where the model has them: both or neither
    (COLMAP writes both: one alone is a model cut short), each walked (`_walk_rigs`,
    `_walk_frames`); once they hold a rig, pycolmap takes every image's pose from its frame,
    so every image must be in one."""
    files = [folder / f"{name}.{ext}" for name in RIG_FILES]
    present = [optional_file(path, "COLMAP model") for path in files]  # a pipe there: said so
    if not any(present):
        return
    if not all(present):
        have, missing = files if present[0] else files[::-1]
        raise InputError(f"{folder}: incomplete COLMAP model: {have.name} without "
                         f"{missing.name} (a COLMAP >= 3.12 model has both, or neither)")
    rigs = _records(files[0], 8, lambda r: _walk_rigs(r, cams, f"cameras.{ext}"))
    framed = _records(files[1], 68, lambda r: _walk_frames(r, rigs, images,
                                                          (files[0].name, f"images.{ext}")))
    if rigs:
        for image_id, (name, _) in images.items():
            if image_id not in framed:
                raise InputError(f"{files[1]}: image {image_id} ({name[:80]!r}) is in no "
                                 "frame (with rigs, COLMAP takes every image's pose from its "
                                 "frame)")


def _records(path: Path, min_record_bytes: int, walk: Callable[[Iterator], object]) -> object:
    """`walk` over the record readers of a rigs or frames file: `_Binary` (.bin: a count,
    then records of at least `min_record_bytes`) or `_Words` (.txt: one data line each)."""
    noun = path.stem[:-1]  # "rigs" -> "rig"
    if path.suffix == ".bin":
        return _walk_binary(path, lambda r: walk(r.records(min_record_bytes, noun)))
    data = _model_bytes(path)
    return walk(_Words(path, line, data, start, end) for line, start, end in _data_lines(data))


# --- text models ---------------------------------------------------------------------------

_WORD = re.compile(rb"\S+")
# A POINTS2D line: X Y POINT3D_ID triples. Triples whose numbers pass `slamreloc.io.numbers`'s
# rule at a glance (at most 100 integer digits, 200 fraction digits and a positive exponent
# below 200: finite and under its 400 characters; an id of at most 9 digits, or -1: in range)
# are matched by one compiled pattern (possessive: no backtracking state kept per triple), so
# a line of any length is never split into words; any other line is read a word at a time.
_COORD = (rb"[+-]?(?:[0-9]{1,100}(?:\.[0-9]{0,200})?|\.[0-9]{1,200})"
          rb"(?:[eE](?:[+-]?1?[0-9]{1,2}|-[0-9]{1,80}))?")
_POINT3D_ID = rb"(?:-0{0,50}1|-0{1,50}|\+?0{0,50}[0-9]{1,9})"
_PLAIN_POINTS = re.compile(rb"(?:\s*%s\s+%s\s+%s(?!\S))*+\s*" % (_COORD, _COORD, _POINT3D_ID))


def _model_bytes(path: Path) -> bytes:
    """A text model file's bytes, by `read_text`'s rule and the `max_text_bytes` bound;
    InputError for one that starts with a byte-order mark, which slamreloc's other text
    readers drop but COLMAP's own reader (that reads the model after this check) takes for
    part of the first line."""
    data = read_text_bytes(path, "COLMAP model", TEXT_LIMIT)
    if data.startswith(b"\xef\xbb\xbf"):
        raise InputError(f"{path}: starts with a UTF-8 byte-order mark, which COLMAP's "
                         "reader does not skip (save the file without it)")
    return data


def _lines(data: bytes) -> Iterator[tuple[int, int, int]]:
    """(line number from 1, start, end) of each line of `data`, its end of line left out:
    lines end at LF only, as COLMAP's reader's do (a CR before it is a blank)."""
    start, line = 0, 1
    while start < len(data):
        end = data.find(b"\n", start)
        end = len(data) if end < 0 else end
        yield line, start, end
        start, line = end + 1, line + 1


def _is_data(data: bytes, start: int, end: int) -> bool:
    """Whether a line holds data: not blank, not a comment (`#` first, after blanks)."""
    first = _WORD.search(data, start, end)
    return first is not None and data[first.start()] != ord("#")


def _data_lines(data: bytes) -> Iterator[tuple[int, int, int]]:
    """`_lines` that hold data (`_is_data`)."""
    return ((i, a, b) for i, a, b in _lines(data) if _is_data(data, a, b))


def _first_words(raw: bytes, most: int) -> list[str]:
    """The first `most` words of a line and, where it holds more, the rest of it as one more
    item (so a line of any length is never split into a list of all its words)."""
    return [w.decode("utf-8") for w in raw.split(None, most)]


def _word_count(data: bytes, start: int = 0, end: int | None = None) -> int:
    """How many words `data[start:end]` holds, counted one at a time (for a message: no list
    of them is made)."""
    return sum(1 for _ in _WORD.finditer(data, start, len(data) if end is None else end))


class _Words:
    """The words of one data line of a text model read in order, one at a time (a record of
    rigs.txt or frames.txt: the same reads as `_Binary`'s, from text)."""

    def __init__(self, path: Path, line: int, data: bytes, start: int, end: int) -> None:
        self.path, self.line, self.where = path, line, f"{path}:{line}"
        self._words = _WORD.finditer(data, start, end)

    def word(self, what: str) -> str:
        found = next(self._words, None)
        if found is None:
            raise InputError(f"{self.where}: the line ends before {what}")
        return found.group().decode("utf-8")

    def whole(self, what: str, bits: int = 32) -> int:
        return int(_number(self.path, self.line, self.word(what), what, integer=True,
                           bits=bits))

    def flag(self, what: str) -> bool:
        word = self.word(what)
        if word not in ("0", "1"):
            raise InputError(f"{self.where}: {what} is {word[:40]!r}, not 0 or 1")
        return word == "1"

    def pose(self, what: str) -> tuple[float, ...]:
        return tuple(_number(self.path, self.line, self.word(what), f"a value of {what}")
                     for _ in range(7))

    def sensor(self, what: str) -> tuple[int, int]:
        name = self.word(f"the type of {what}")
        kind = next((i for i, known in sensor_types().items() if known == name), None)
        if kind is None:
            raise _unknown_sensor(self.where, what, name)
        return kind, self.whole(f"the id of {what}")

    def done(self) -> None:
        if next(self._words, None) is not None:
            raise InputError(f"{self.where}: more values than the line's counts call for")


def _number(path: Path, line: int, word: str, what: str, integer: bool = False,
            low: int = 0, bits: int = 32) -> float:
    """A field of a COLMAP text model (`slamreloc.io.numbers`: plain ASCII decimal, finite);
    `integer`: a whole number in low..2^bits-1 (an id; POINT3D_ID -1 is "none")."""
    if not integer:
        return parse_number(word, f"{path}:{line}", what)
    value = parse_whole(word, f"{path}:{line}", what)
    if not low <= value < 1 << bits:
        raise InputError(f"{path}:{line}: {what} out of range ({word[:40]})")
    return value


def _read_cameras_text(path: Path) -> dict[int, int]:
    by_name = {name: (model_id, n) for model_id, (name, n) in camera_models().items()}
    most = 4 + max(n for _, n in by_name.values())  # fields of the longest camera line
    data, out = _model_bytes(path), {}
    for line, start, end in _data_lines(data):
        words = _first_words(raw := data[start:end], most)
        if len(words) < 4:
            raise InputError(f"{path}:{line}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS...")
        cam_id = int(_number(path, line, words[0], "CAMERA_ID", integer=True))
        if words[1] not in by_name:
            raise InputError(f"{path}:{line}: unknown camera model {words[1][:40]!r}")
        model_id, n_params = by_name[words[1]]
        if len(words) != 4 + n_params:
            got = (len(words) if len(words) <= most else _word_count(raw)) - 4
            raise InputError(f"{path}:{line}: the {words[1]} model has {n_params} parameters, "
                             f"got {got}")
        width, height = (int(_number(path, line, w, k, integer=True))
                         for w, k in zip(words[2:4], ("WIDTH", "HEIGHT")))
        params = [_number(path, line, w, "a parameter") for w in words[4:]]
        _check_camera(f"{path}:{line}", cam_id, width, height, params)
        if cam_id in out:
            raise InputError(f"{path}:{line}: camera id {cam_id} appears twice")
        out[cam_id] = model_id
    return out


def _read_images_text(path: Path) -> tuple[dict[int, tuple[str, int]], bytes]:
    """(image id -> (name, camera id), the image lines each followed by an empty POINTS2D
    line: what pycolmap is given). Mirrors COLMAP's reader: an image line (data), then the
    next line, whatever it holds, is its points (`_check_points`)."""
    data = _model_bytes(path)
    lines = _lines(data)
    out, kept = {}, bytearray()
    for line, start, end in lines:
        if not _is_data(data, start, end):
            continue
        image_id, name, cam_id = _image_line(path, line, data[start:end])
        points = next(lines, None)
        if points is not None:
            _check_points(path, points[0], data, points[1], points[2])
        _add_image(out, f"{path}:{line}", image_id, name, cam_id)
        kept += data[start:end] + b"\n\n"
    return out, bytes(kept)


def _image_line(path: Path, line: int, raw: bytes) -> tuple[int, str, int]:
    """(IMAGE_ID, NAME, CAMERA_ID) of an image line, its pose checked (`_check_image_pose`)
    and its name bounded (MAX_NAME_BYTES, as in images.bin)."""
    words = _first_words(raw, 10)
    if len(words) != 10:
        got = len(words) if len(words) <= 10 else _word_count(raw)
        raise InputError(f"{path}:{line}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID "
                         f"NAME (10 fields), got {got}")
    image_id = int(_number(path, line, words[0], "IMAGE_ID", integer=True))
    if len(words[9].encode("utf-8")) > MAX_NAME_BYTES:
        raise _name_too_long(f"{path}:{line}", f"the name of image {image_id}")
    pose = [_number(path, line, w, "a pose value") for w in words[1:8]]
    _check_image_pose(f"{path}:{line}", image_id, pose)
    cam_id = int(_number(path, line, words[8], "CAMERA_ID", integer=True))
    return image_id, words[9], cam_id


def _check_points(path: Path, line: int, data: bytes, start: int, end: int) -> None:
    """A POINTS2D line (`data[start:end]`): X Y POINT3D_ID triples, each number by
    `_number`'s rule. Matched whole by `_PLAIN_POINTS` where it can be; otherwise read a word
    at a time (lazily: never a list of its words), which names the first bad one."""
    if _PLAIN_POINTS.fullmatch(data, start, end):
        return
    n = _word_count(data, start, end)
    if n % 3:
        raise InputError(f"{path}:{line}: expected X Y POINT3D_ID triples, got {n} values")
    for k, found in enumerate(_WORD.finditer(data, start, end)):  # X Y POINT3D_ID (-1: none)
        word = found.group().decode("utf-8")
        if k % 3 == 2:
            _number(path, line, word, "a POINT3D_ID", integer=True, low=-1)
        else:
            _number(path, line, word, "a 2D point coordinate")


def check_model(folder: Path, ext: str) -> ModelIndex:
    """Walk every model file slamreloc uses; InputError naming the file on any defect."""
    images_text = None
    if ext == "bin":
        cams = _walk_binary(folder / "cameras.bin", _walk_cameras)
        images = _walk_binary(folder / "images.bin", _walk_images)
    else:
        cams = _read_cameras_text(folder / "cameras.txt")
        images, images_text = _read_images_text(folder / "images.txt")
    images_file = folder / f"images.{ext}"
    by_name = {}
    for name, cam_id in images.values():
        if cam_id not in cams:
            raise InputError(f"{images_file}: image {name!r} has camera {cam_id}, which "
                             f"cameras.{ext} does not have")
        if name in by_name:
            raise InputError(f"{images_file}: image name {name!r} appears twice")
        by_name[name] = cam_id
    _check_rigs_and_frames(folder, ext, cams, images)
    return ModelIndex(cams, by_name, images_text)
