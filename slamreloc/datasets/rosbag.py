"""ROS 1 and ROS 2 bags as datasets, read with `rosbags` (no ROS installation needed).

A bag is a ROS 1 `.bag` file, a ROS 2 bag folder (with `metadata.yaml`) or a ROS 2 `.db3` /
`.mcap` file. One bag is one sequence (named after the bag's stem), in both splits.

- Images: `sensor_msgs/Image` (rgb8, bgr8, rgba8, bgra8, mono8) or `sensor_msgs/CompressedImage`
  (JPEG or PNG, kept byte for byte). Timestamps are the header stamps in seconds (the bag's
  receive time where a header stamp is zero).
- Depth: `sensor_msgs/Image`, 16UC1 in millimetres or 32FC1 in metres, taken as registered to
  the colour image (same pixels, same size); each image takes the depth map nearest in time
  within 20 ms.
- Camera: `sensor_msgs/CameraInfo` (K in pixels, OpenCV convention as `Camera`'s; D mapped to
  the `slamreloc.camera_models` model of the same formulas).
- Poses (optional): `nav_msgs/Odometry`, `geometry_msgs/PoseStamped` or
  `geometry_msgs/TransformStamped` messages, or the `/tf` transforms of one parent:child frame
  pair; each image's world_from_cam (metres) is interpolated at its stamp between the pose
  messages around it, within 0.1 s on both sides. A pose whose child frame is not the image's
  frame is composed with the `/tf_static` chain from that frame to the image's when there is
  one. A pose topic's messages all name one world frame (header.frame_id) and one child
  frame, and `/tf_static` is a tree (each frame one parent, no loop); else the bag is refused.
- Repeated stamps: two messages of one image, depth or pose topic at one instant (stamps
  within a microsecond: `geometry.Instants`, every stamped reader's rule) are one
  message twice when they hold the same image bytes or the same pose (`geometry.same_pose`:
  within float noise), and are read once; otherwise the bag is refused, naming the topic and
  the stamp (which of the two is the camera's is not for slamreloc to guess).

Images and depth maps are extracted into a private temporary folder (removed when the
interpreter exits), so that frames point at ordinary files: compressed images as received,
raw images as PNG, depth as 16-bit PNG in millimetres.
"""

from __future__ import annotations

import atexit
import hashlib
import os
import shutil
import tempfile
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from slamreloc.datasets.base import Dataset
from slamreloc.errors import InputError
from slamreloc.geometry import (
    MAX_COORDINATE,
    Instants,
    Rigid3,
    matrix_to_quat,
    nearest_stamps,
    pose_gap,
    same_pose,
    unit_quaternion,
)
from slamreloc.io.fileio import open_regular
from slamreloc.io.images import (
    check_encoded_image,
    check_image_size,
    clean_depth_m,
    encode_image,
)
from slamreloc.runtime.progress import console
from slamreloc.types import Camera, Frame, k_matrix_problem

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
ODOMETRY = "nav_msgs/msg/Odometry"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
TRANSFORM_STAMPED = "geometry_msgs/msg/TransformStamped"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
POSE_TYPES = (ODOMETRY, POSE_STAMPED, TRANSFORM_STAMPED)
TF_TOPIC, TF_STATIC_TOPIC = "/tf", "/tf_static"
# raw colour encodings: channels, and the conversion to BGR for cv2.imwrite (None: as is)
COLOUR_ENCODINGS: dict[str, tuple[int, int | None]] = {
    "rgb8": (3, cv2.COLOR_RGB2BGR), "bgr8": (3, None), "rgba8": (4, cv2.COLOR_RGBA2BGR),
    "bgra8": (4, cv2.COLOR_BGRA2BGR), "mono8": (1, None)}
DEPTH_ENCODINGS: dict[str, type] = {"16UC1": np.uint16, "32FC1": np.float32}
COMPRESSED_SUFFIXES = {"PNG": ".png", "JPEG": ".jpg"}
# CameraInfo distortion_model -> number of coefficients in D
ROS_DISTORTION = {"plumb_bob": 5, "rational_polynomial": 8, "equidistant": 4}
TRANSPORTS = ("compressed", "compressedDepth", "theora", "zstd")  # image_transport suffixes
DEPTH_UNITS_PER_METRE = 1000.0  # the extracted depth PNGs: millimetres
MAX_DEPTH_MM = 65534  # 65535 means "no measurement"
MAX_DEPTH_DT = 0.02  # seconds between an image and its depth map
MAX_POSE_GAP = 0.1  # seconds from an image to the pose messages on either side of it
TOPIC_KINDS = ("image", "depth", "camera_info", "pose")


@dataclass(frozen=True)
class BagTopics:
    """The topics a bag is read from; None: found automatically. `pose` is a pose topic or
    `tf:PARENT:CHILD` (the /tf transforms from frame PARENT to frame CHILD)."""

    image: str | None = None
    depth: str | None = None
    camera_info: str | None = None
    pose: str | None = None


_default_topics = BagTopics()
_default_topics_read = False  # whether a bag was loaded with them since `set_topics`


def set_topics(topics: BagTopics) -> None:
    """The topics `load_rosbag` reads when it is given none (the CLI's `--topic`)."""
    global _default_topics, _default_topics_read
    _default_topics, _default_topics_read = topics, False


def default_topics() -> BagTopics:
    return _default_topics


def default_topics_unread() -> bool:
    """Whether topics were set (`set_topics`) and no bag has been loaded with them since: a
    command that read no bag took the CLI's `--topic` for nothing."""
    return _default_topics != BagTopics() and not _default_topics_read


def parse_topics(items: list[str]) -> BagTopics:
    """`["image=/cam/image_raw", "pose=tf:map:camera", ...]` (the CLI's `--topic KIND=NAME`)
    -> BagTopics; a name without a leading '/' gets one."""
    chosen: dict[str, str] = {}
    for item in items:
        kind, sep, name = (s.strip() for s in item.partition("="))
        kind = kind.replace("-", "_")
        if not sep or kind not in TOPIC_KINDS or not name:
            raise InputError(f"`topic` {item!r}: expected KIND=NAME with KIND one of "
                             f"{', '.join(TOPIC_KINDS)}")
        if kind == "pose" and name.startswith("tf:"):
            tf_frames(name, f"`topic` {item!r}")
        elif not name.startswith("/"):
            name = "/" + name
        if kind in chosen:  # which one was meant? (the rule of `--limit` given twice)
            raise InputError(f"`topic` {kind} is given twice ({chosen[kind]!r} and {name!r}): "
                             "give each kind once")
        chosen[kind] = name
    return BagTopics(**chosen)


def tf_frames(spec: str, source: str) -> tuple[str, str]:
    """`tf:PARENT:CHILD` -> (PARENT, CHILD), leading slashes dropped."""
    parts = spec.split(":")
    if len(parts) != 3 or parts[0] != "tf" or not all(p.strip("/ ") for p in parts[1:]):
        raise InputError(f"{source}: expected tf:PARENT:CHILD (two frame names), got {spec!r}")
    return _frame_id(parts[1]), _frame_id(parts[2])


def is_rosbag(path: Path) -> bool:
    """A ROS 1 `.bag` file, a ROS 2 bag folder (with metadata.yaml) or a `.db3`/`.mcap` file."""
    path = Path(path)
    if path.is_dir():  # whatever metadata.yaml is: a pipe or a folder there is named so
        return os.path.lexists(path / "metadata.yaml")
    return path.is_file() and path.suffix in (".bag", ".db3", ".mcap")


# --- reading -----------------------------------------------------------------------------------

class _Bag:
    """An open bag: its topics (name -> (message type, count)) and its messages by topic."""

    def __init__(self, path: Path, reader: Any):
        self.path = path
        self.reader = reader
        self.topics = {name: (info.msgtype or "(mixed types)", info.msgcount)
                       for name, info in reader.topics.items()}
        self._first: dict[str, Any] = {}
        # (parent, child) of every /tf transform, once a pass has read the whole topic
        self.tf_pairs: set[tuple[str, str]] | None = None

    def messages(self, topic: str) -> Iterator[tuple[float, Any]]:
        """(receive time in seconds, message) of each message on `topic`, in bag order."""
        connections = [c for c in self.reader.connections if c.topic == topic]
        if not connections:  # (rosbags reads every topic when given no connection)
            return
        items = self.reader.messages(connections=connections)
        while True:
            try:
                item = next(items, None)
                if item is None:
                    return
                connection, time_ns, raw = item
                msg = self.reader.deserialize(raw, connection.msgtype)
            except Exception as err:  # noqa: BLE001 - damaged bytes fail in many ways
                raise InputError(f"{self.path}: topic {topic}: unreadable message "
                                 f"({type(err).__name__}: {_one_line(err)})") from None
            yield time_ns * 1e-9, msg

    def first(self, topic: str) -> Any | None:
        """The first message on `topic` (None if it has none), read once."""
        if topic not in self._first:
            self._first[topic] = next((m for _, m in self.messages(topic)), None)
        return self._first[topic]

    def listing(self) -> str:
        return ", ".join(f"{t} ({ty}, {n})" for t, (ty, n) in sorted(self.topics.items())) \
            or "none"


@contextmanager
def _open_bag(path: Path) -> Iterator[_Bag]:
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise InputError(f"{path}: reading ROS bags needs the rosbags package (pip install "
                         "rosbags)") from None
    if not is_rosbag(path):
        raise InputError(f"{path}: not a ROS bag (a .bag file, a ROS 2 bag folder with "
                         "metadata.yaml, or a .db3/.mcap file)")
    # every file of the bag is a regular file: a named pipe or a device would block the reader
    if path.is_dir():
        open_regular(path / "metadata.yaml", "ROS bag metadata").close()
    for part in [path] if not path.is_dir() else sorted(path.iterdir()):
        if not part.is_dir():
            open_regular(part, "ROS bag file").close()
    try:
        reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except Exception as err:  # noqa: BLE001 - rosbags' parsers raise many kinds on bad bytes
        raise InputError(f"{path}: not a readable ROS bag ({_one_line(err)})") from None
    try:
        yield _Bag(path, reader)
    finally:
        reader.close()


def _one_line(err: BaseException) -> str:
    return " ".join(str(err).split())[:200] or type(err).__name__


def _frame_id(name: str) -> str:
    return name.strip().lstrip("/")


def _stamp(header: Any, receive_time: float) -> float:
    """Seconds of a header's stamp; the receive time where the stamp is zero."""
    stamp = header.stamp.sec + header.stamp.nanosec * 1e-9
    return float(stamp) if stamp else receive_time


def _field(msg: Any, name: str) -> Any:
    """A CameraInfo array field: ROS 2 spells it lower case (k), ROS 1 upper case (K)."""
    return getattr(msg, name) if hasattr(msg, name) else getattr(msg, name.upper())


# --- topics ------------------------------------------------------------------------------------

def _check_named(bag: _Bag, kind: str, name: str, allowed: tuple[str, ...]) -> str:
    """A topic given by name: present, and of one of the allowed types."""
    if name not in bag.topics:
        raise InputError(f"{bag.path}: {kind} topic {name} is not in the bag (topics: "
                         f"{bag.listing()})")
    if bag.topics[name][0] not in allowed:
        raise InputError(f"{bag.path}: {kind} topic {name} is {bag.topics[name][0]}, not "
                         f"{' or '.join(allowed)}")
    return name


def _check_pose(bag: _Bag, spec: str) -> str:
    if spec.startswith("tf:"):
        tf_frames(spec, str(bag.path))
        _check_named(bag, "pose", TF_TOPIC, (TF_MESSAGE,))
        return spec
    return _check_named(bag, "pose", spec, POSE_TYPES)


def _of_type(bag: _Bag, *types: str) -> list[str]:
    return sorted(t for t, (ty, _) in bag.topics.items() if ty in types)


def _image_kind(bag: _Bag, topic: str) -> str:
    """"colour", "depth" or "other" (an encoding not read), from the topic's first message."""
    msg = bag.first(topic)
    if msg is None:
        return "other"
    if bag.topics[topic][0] == COMPRESSED:
        return "other" if "compresseddepth" in msg.format.lower() else "colour"
    return ("colour" if msg.encoding in COLOUR_ENCODINGS else
            "depth" if msg.encoding in DEPTH_ENCODINGS else "other")


def _only_best(bag: _Bag, kind: str, candidates: list[str], rank: Callable[[str], tuple]
               ) -> str | None:
    """The candidate topic that ranks above every other (None for none); an InputError
    listing them where two rank first alike: the choice would be a guess (two cameras of one
    rig), so the user names one."""
    if not candidates:
        return None
    ranked = sorted(candidates, key=rank, reverse=True)
    if len(ranked) > 1 and rank(ranked[0]) == rank(ranked[1]):
        tied = [t for t in ranked if rank(t) == rank(ranked[0])]
        raise InputError(f"{bag.path}: {len(tied)} {kind} topics could be the one to read "
                         f"({', '.join(tied)}): name one with `topic` {kind}=NAME")
    return ranked[0]


def _auto_image(bag: _Bag) -> str:
    """The colour image topic: 3- or 4-channel (or compressed) before grey, then the most
    messages; else any non-depth image topic, whose encoding is then refused by name. Two
    topics alike on both counts are refused (`_only_best`)."""
    kinds = {t: _image_kind(bag, t) for t in _of_type(bag, IMAGE, COMPRESSED)}
    candidates = [t for t, k in kinds.items() if k != "depth" and bag.topics[t][1]]
    if not candidates:
        raise InputError(f"{bag.path}: no image topic (sensor_msgs/Image or CompressedImage "
                         f"with colour images; topics: {bag.listing()})")
    return _only_best(bag, "image", candidates, lambda t: (
        kinds[t] == "colour", kinds[t] == "colour" and not _is_grey(bag, t), bag.topics[t][1]))


def _is_grey(bag: _Bag, topic: str) -> bool:
    msg = bag.first(topic)
    return bag.topics[topic][0] == IMAGE and msg is not None and msg.encoding == "mono8"


def _auto_depth(bag: _Bag) -> str | None:
    """A 16UC1/32FC1 image topic with messages: an aligned/registered one first, then the
    most messages; two alike on both counts are refused (`_only_best`)."""
    depth = [t for t in _of_type(bag, IMAGE)
             if _image_kind(bag, t) == "depth" and bag.topics[t][1]]
    return _only_best(bag, "depth", depth, lambda t: (
        "aligned" in t or "registered" in t, bag.topics[t][1]))


def _namespace(topic: str) -> str:
    parts = topic.strip("/").split("/")
    if parts[-1] in TRANSPORTS:
        parts = parts[:-1]
    return "/".join(parts[:-1])


def _auto_camera_info(bag: _Bag, image: str) -> str | None:
    """The CameraInfo topic of the image's namespace (`/ns/image_raw` -> `/ns/camera_info`),
    where there is one: a CameraInfo of another namespace describes another camera until the
    user names it."""
    same = [t for t in _of_type(bag, CAMERA_INFO) if _namespace(t) == _namespace(image)]
    return same[0] if len(same) == 1 else None


def _auto_pose(bag: _Bag) -> str | None:
    poses = _of_type(bag, ODOMETRY, POSE_STAMPED)
    return poses[0] if len(poses) == 1 else None


def _choose_image(bag: _Bag, wanted: BagTopics) -> str:
    return (_check_named(bag, "image", wanted.image, (IMAGE, COMPRESSED)) if wanted.image
            else _auto_image(bag))


def _choose_topics(bag: _Bag, wanted: BagTopics) -> BagTopics:
    """The topics to read: those named in `wanted` (checked), the others found automatically
    (None where there is none)."""
    image = _choose_image(bag, wanted)
    return BagTopics(
        image=image,
        depth=_check_named(bag, "depth", wanted.depth, (IMAGE,)) if wanted.depth
        else _auto_depth(bag),
        camera_info=_check_named(bag, "camera_info", wanted.camera_info, (CAMERA_INFO,))
        if wanted.camera_info else _auto_camera_info(bag, image),
        pose=_check_pose(bag, wanted.pose) if wanted.pose else _auto_pose(bag))


def _print_choice(bag: _Bag, chosen: BagTopics) -> None:
    for kind in TOPIC_KINDS:
        name = getattr(chosen, kind)
        topic = TF_TOPIC if name and name.startswith("tf:") else name
        if topic is None:
            _say(f"bag: no {kind} topic found")
            hint = _unchosen(bag, kind)
            if hint:
                warnings.warn(f"{bag.path}: {hint}", stacklevel=2)
        else:
            msgtype, count = bag.topics[topic]
            via = f"{topic}, " if topic != name else ""
            _say(f"bag: {kind} {name} ({via}{msgtype}, {count} messages)")


def _unchosen(bag: _Bag, kind: str) -> str:
    """Where no pose topic was chosen, a warning's text naming the bag's pose topics (several,
    or TransformStamped / tf ones, which are never picked automatically); "" where it has
    none."""
    names = _of_type(bag, *POSE_TYPES, TF_MESSAGE) if kind == "pose" else []
    names = [n for n in names if n != TF_STATIC_TOPIC]
    return (f"no pose topic chosen from the candidates {', '.join(names)}: the frames have no "
            "poses unless one is named with `topic` pose=NAME or pose=tf:PARENT:CHILD"
            ) if names else ""


def _say(line: str) -> None:
    console.print(line, markup=False, highlight=False, soft_wrap=True)


# --- images and depth --------------------------------------------------------------------------

@dataclass(frozen=True)
class _Still:
    """One extracted image or depth map: header stamp (seconds) and file."""

    stamp: float
    path: Path


def _raw_pixels(msg: Any, channels: int, dtype: type, source: str, what: str) -> np.ndarray:
    """A raw `sensor_msgs/Image` as an (H, W[, C]) array of `dtype`, its size checked against
    the bounds before anything is allocated for it."""
    width, height, step = int(msg.width), int(msg.height), int(msg.step)
    check_image_size(width, height, source, what)
    row = width * channels * np.dtype(dtype).itemsize
    if step < row or len(msg.data) < step * height:
        raise InputError(f"{source}: {len(msg.data)} bytes with step {step} do not hold a "
                         f"{width}x{height} {msg.encoding} {what}")
    rows = np.frombuffer(msg.data, np.uint8, count=step * height).reshape(height, step)
    order = ">" if msg.is_bigendian else "<"
    pixels = np.ascontiguousarray(rows[:, :row]).view(np.dtype(dtype).newbyteorder(order))
    shape = (height, width) if channels == 1 else (height, width, channels)
    return pixels.reshape(shape).astype(dtype)


def colour_file(msg: Any, source: str) -> tuple[bytes, str, tuple[int, int]]:
    """(file bytes, suffix, (width, height)) of a colour Image or CompressedImage message (a
    bag's, or a live ROS node's: messages are read by their fields)."""
    if getattr(msg, "__msgtype__", None) == COMPRESSED or not hasattr(msg, "encoding"):
        data = bytes(msg.data)
        header = check_encoded_image(data, source, "image")
        if header.format not in COMPRESSED_SUFFIXES:
            raise InputError(f"{source}: compressed image in {header.format} (format "
                             f"{msg.format!r}); JPEG and PNG are read")
        return data, COMPRESSED_SUFFIXES[header.format], (header.width, header.height)
    if msg.encoding not in COLOUR_ENCODINGS:
        raise InputError(f"{source}: image encoding {msg.encoding!r} is not read (known: "
                         f"{', '.join(COLOUR_ENCODINGS)})")
    channels, to_bgr = COLOUR_ENCODINGS[msg.encoding]
    pixels = _raw_pixels(msg, channels, np.uint8, source, "image")
    bgr = pixels if to_bgr is None else cv2.cvtColor(pixels, to_bgr)
    return encode_image(bgr, ".png", source), ".png", (int(msg.width), int(msg.height))


def depth_millimetres(depth: np.ndarray) -> np.ndarray:
    """float depth in metres -> uint16 millimetres; what is no measurement by the rule of
    float depth (`clean_depth_m`: non-finite, non-positive, over 65.534 m) becomes 0."""
    mm = np.round(clean_depth_m(depth.astype(np.float64)) * 1000.0)
    return np.where(mm <= MAX_DEPTH_MM, mm, 0).astype(np.uint16)


def _depth_file(msg: Any, source: str) -> tuple[bytes, str, tuple[int, int]]:
    """(16-bit PNG in millimetres, suffix, (width, height)) of a depth Image message."""
    if msg.encoding not in DEPTH_ENCODINGS:
        raise InputError(f"{source}: depth encoding {msg.encoding!r} is not read (known: "
                         f"{', '.join(DEPTH_ENCODINGS)})")
    dtype = DEPTH_ENCODINGS[msg.encoding]
    depth = _raw_pixels(msg, 1, dtype, source, "depth")
    mm = depth if dtype is np.uint16 else depth_millimetres(depth)
    return encode_image(mm, ".png", source), ".png", (int(msg.width), int(msg.height))


FileMaker = Callable[[Any, str], tuple[bytes, str, tuple[int, int]]]


def _extract(bag: _Bag, topic: str, folder: Path, make_file: FileMaker,
             size: tuple[int, int], what: str) -> list[_Still]:
    """Write each message of `topic` to `folder` as a file; all must be `size` pixels."""
    folder.mkdir()
    stills: list[_Still] = []
    seen = Instants()  # each instant's first (message, its file's digest)
    for i, (receive_time, msg) in enumerate(bag.messages(topic)):
        source = f"{bag.path}: {what} topic {topic}, message {i}"
        data, suffix, got = make_file(msg, source)
        if got != size:
            raise InputError(f"{source}: {what} is {got[0]}x{got[1]} pixels, the images are "
                             f"{size[0]}x{size[1]}" + (" (depth must be registered to the "
                                                       "images)" if what == "depth" else ""))
        stamp = _stamp(msg.header, receive_time)
        digest = hashlib.sha256(data).digest()
        first_stamp, (first, first_digest) = seen.setdefault(stamp, (i, digest))
        if first != i:  # one instant again: the same message again is read once
            if first_digest != digest:
                raise InputError(f"{bag.path}: {what} topic {topic}: messages {first} and {i} "
                                 f"are {_stamped_words(first_stamp, stamp)} but hold different "
                                 f"{'depth maps' if what == 'depth' else 'images'}")
            continue
        path = folder / f"{len(stills):06d}{suffix}"
        path.write_bytes(data)
        stills.append(_Still(stamp, path))
    return stills


def _stamped_words(first: float, again: float) -> str:
    """How two messages of one instant (`geometry.Instants`) are stamped, for a refusal."""
    if first == again:
        return f"both stamped {first:.6f} s"
    return f"stamped {first:.9f} and {again:.9f} s, one instant (within 1 microsecond)"


@contextmanager
def _extraction_folder() -> Iterator[Path]:
    """A private temporary folder, removed at interpreter exit (at once on failure)."""
    folder = Path(tempfile.mkdtemp(prefix="slamreloc-bag-"))
    atexit.register(shutil.rmtree, folder, True)
    try:
        yield folder
    except BaseException:
        shutil.rmtree(folder, ignore_errors=True)
        raise


# --- camera ------------------------------------------------------------------------------------

def ros_lens(distortion_model: str, d: list[float], source: str) -> tuple[str, tuple]:
    """CameraInfo's distortion_model and D -> (slamreloc camera model, its parameters).
    plumb_bob (k1 k2 p1 p2 k3): OPENCV when k3 is 0, else FULL_OPENCV; rational_polynomial
    (k1 k2 p1 p2 k3 k4 k5 k6): FULL_OPENCV; equidistant (k1 k2 k3 k4): OPENCV_FISHEYE; an
    all-zero (or empty) D: PINHOLE, whatever the model's name."""
    if not any(d):
        return "PINHOLE", ()
    n = ROS_DISTORTION.get(distortion_model)
    if n is None:
        raise InputError(f"{source}: distortion model {distortion_model[:40]!r} is not read "
                         f"(known: {', '.join(ROS_DISTORTION)})")
    if len(d) != n:
        raise InputError(f"{source}: distortion model {distortion_model} has {n} "
                         f"coefficients, D has {len(d)}")
    if distortion_model == "equidistant":
        return "OPENCV_FISHEYE", tuple(d)
    if distortion_model == "plumb_bob" and d[4] == 0:
        return "OPENCV", tuple(d[:4])
    return "FULL_OPENCV", tuple(d) + (0.0,) * (8 - n)


def _binning(msg: Any) -> tuple[int, int]:
    """CameraInfo's (binning_x, binning_y); 0 (or a message without them) is 1, no binning."""
    return (int(getattr(msg, "binning_x", 0) or 1), int(getattr(msg, "binning_y", 0) or 1))


def _roi(msg: Any, source: str) -> tuple[int, int, int, int]:
    """CameraInfo's roi (x_offset, y_offset, width, height), in full-resolution pixels; all
    zero (or a message without one) is the full image."""
    roi = getattr(msg, "roi", None)
    if roi is None:
        return 0, 0, 0, 0
    x, y, w, h = (int(roi.x_offset), int(roi.y_offset), int(roi.width), int(roi.height))
    if (w == 0) != (h == 0):
        raise InputError(f"{source}: CameraInfo's roi is {w}x{h}: a window has a width and a "
                         "height, or neither (0x0 at (0, 0): the full image)")
    if w == 0 and (x, y) != (0, 0):
        raise InputError(f"{source}: CameraInfo's roi at ({x}, {y}) has no size (0x0 is the "
                         "full image, at (0, 0))")
    return x, y, w, h


def _delivered_size(msg: Any, size: tuple[int, int], binning: tuple[int, int],
                    roi: tuple[int, int, int, int], source: str) -> None:
    """Refuse a CameraInfo whose roi does not fit its width x height, whose window (the roi,
    else width x height) is not a whole number of binned pixels, or whose delivered image
    (the window / binning) is not of the images' `size`. Width and height 0 (size not given)
    check the roi's window alone, if there is one."""
    full = (int(msg.width), int(msg.height))
    x, y, w, h = roi
    bx, by = binning
    plain = binning == (1, 1) and roi == (0, 0, 0, 0)
    if plain:  # a CameraInfo of the images themselves
        if full not in ((0, 0), size):
            raise InputError(f"{source}: CameraInfo is for {full[0]}x{full[1]} images, the "
                             f"images are {size[0]}x{size[1]}")
        return
    if w and full != (0, 0) and (x + w > full[0] or y + h > full[1]):
        raise InputError(f"{source}: CameraInfo's roi ({w}x{h} at ({x}, {y})) does not fit "
                         f"its {full[0]}x{full[1]} image")
    window = (w, h) if w else full
    if window == (0, 0):  # no size given: the images' size is not checked
        return
    said = (f"the {w}x{h} roi at ({x}, {y})" if w else f"its full {full[0]}x{full[1]} image") \
        + (f" with binning_x {bx}, binning_y {by}" if (bx, by) != (1, 1) else "")
    if window[0] % bx or window[1] % by:
        raise InputError(f"{source}: CameraInfo's window ({said}) is not a whole number of "
                         f"binned pixels: {window[0]}x{window[1]} does not divide by "
                         f"{bx}x{by}")
    expected = (window[0] // bx, window[1] // by)
    if expected != size:
        raise InputError(f"{source}: CameraInfo gives {expected[0]}x{expected[1]} images "
                         f"({said}), the images are {size[0]}x{size[1]}")


def camera_from_info(msg: Any, size: tuple[int, int], source: str) -> Camera:
    """A `Camera` of the images' size (width, height) from a CameraInfo message.

    ROS (REP 104): width, height, K and D are those of the full-resolution calibration; `roi`
    (x_offset, y_offset, width, height in full-resolution pixels; all zero: the full image)
    is the window captured, and binning_x / binning_y (0 or 1: none) divide it, so the image
    delivered is (roi.width or width) / binning_x by (roi.height or height) / binning_y. The
    camera returned is that image's: fx / binning_x, fy / binning_y, and the principal point
    by exact pixel-centre geometry in slamreloc's (OpenCV's) convention, pixel centres at
    integer coordinates: the delivered pixel u_b covers full-resolution pixels x_offset +
    binning_x * u_b ... + binning_x - 1, centred at u_f = x_offset + binning_x * u_b +
    (binning_x - 1) / 2, so cx_b = (cx_f - x_offset - (binning_x - 1) / 2) / binning_x (cy
    likewise). ROS's image_geometry uses (cx - x_offset) / binning_x, which puts the centre
    of a binned pixel at its first full-resolution pixel: a quarter pixel off at binning 2
    (3/8 at 4); this uses the exact form so that a point projects onto the binned pixel that
    holds it. D is in normalized coordinates and stays. A CameraInfo whose window does not fit
    its width x height, is not a whole number of binned pixels, or gives images of another
    size than the bag's is refused; width and height 0 (size not given) take the images'."""
    k = [float(v) for v in _field(msg, "k")]
    d = [float(v) for v in _field(msg, "d")]
    problem = k_matrix_problem(k)
    if problem:
        calibrate = f": calibrate it ({STAND_IN_HELP})" if not any(k) else ""
        raise InputError(f"{source}: {problem}{calibrate}")
    binning, roi = _binning(msg), _roi(msg, source)
    _delivered_size(msg, size, binning, roi, source)
    (bx, by), (x0, y0) = binning, roi[:2]
    fx, fy = k[0] / bx, k[4] / by
    cx, cy = (k[2] - x0 - (bx - 1) / 2) / bx, (k[5] - y0 - (by - 1) / 2) / by
    model, distortion = ros_lens(msg.distortion_model, d, source)
    try:
        return Camera(size[0], size[1], fx, fy, cx, cy, model, distortion)
    except InputError as err:
        raise InputError(f"{source}: {err}") from None


GUESS = "guess"  # `camera_in_place_of_info`: a pinhole guess of the images' size
STAND_IN_HELP = "`sfm` and `localize` take `--camera` in its place"
_stand_in: Camera | str | None = None


@contextmanager
def camera_in_place_of_info(camera: Camera | str | None) -> Iterator[None]:
    """While inside, a bag whose image topic has no CameraInfo, or an uncalibrated one (K all
    zero), is read with `camera` (the user's `--camera`, fitted to the images' size by
    `Camera.for_image`; GUESS: a pinhole of focal 1.2 x the longer side, centred, COLMAP's
    own first guess, for SfM to refine) instead of being refused. None: refused."""
    global _stand_in
    before, _stand_in = _stand_in, camera
    try:
        yield
    finally:
        _stand_in = before


def _stand_in_camera(size: tuple[int, int], source: str) -> Camera:
    if _stand_in == GUESS:
        f = 1.2 * max(size)
        return Camera(size[0], size[1], f, f, size[0] / 2, size[1] / 2)
    return _stand_in.for_image(*size, f"`--camera` for {source}")


def _camera(bag: _Bag, topic: str | None, image: str, size: tuple[int, int]) -> Camera:
    if topic is None:
        if _stand_in is not None:
            return _stand_in_camera(size, f"{bag.path}: image topic {image}")
        expected = "/".join(("", _namespace(image), "camera_info")).replace("//", "/")
        others = _of_type(bag, CAMERA_INFO)
        there = (f" (the bag's CameraInfo topics, {', '.join(others)}, are of other cameras "
                 "or several)" if others else "")
        raise InputError(f"{bag.path}: no sensor_msgs/CameraInfo for image topic {image}"
                         f"{there}: add {expected} to the bag, or name one with `topic` "
                         f"camera_info=NAME ({STAND_IN_HELP})")
    source = f"{bag.path}: camera_info topic {topic}"
    camera, first_uncalibrated = None, None
    for i, (_, msg) in enumerate(bag.messages(topic)):  # one camera for the whole bag
        # ROS's uncalibrated camera (K all zero) in every message, or in none: a bag that
        # changes from one to the other describes two cameras, whatever `--camera` says
        uncalibrated = not np.any(np.asarray(_field(msg, "k"), np.float64))
        if first_uncalibrated is None:
            first_uncalibrated = uncalibrated
        elif uncalibrated != first_uncalibrated:
            said = ("uncalibrated (K all zero), message 0 calibrated" if uncalibrated else
                    "calibrated, message 0 uncalibrated (K all zero)")
            raise InputError(f"{source}: message {i} is {said}: one camera per bag (split the "
                             "bag where it changes)")
        if uncalibrated:
            continue  # refused below unless the user gave the camera
        this = camera_from_info(msg, size, f"{source}, message {i}" if i else source)
        if camera is None:
            camera = this
        elif not this.same_as(camera):
            raise InputError(f"{source}: message {i} describes another camera than message 0 "
                             f"({this.describe()} against {camera.describe()}): one camera "
                             "per bag (split the bag where it changes)")
    if first_uncalibrated is None:
        raise InputError(f"{source} has no messages")
    if first_uncalibrated:
        if _stand_in is not None:
            return _stand_in_camera(size, source)
        camera_from_info(bag.first(topic), size, source)  # refused: "calibrate it"
    return camera


# --- poses -------------------------------------------------------------------------------------

@dataclass
class PoseTrack:
    """Pose messages sorted by stamp: parent_from_child (metres) at `stamps` (seconds);
    `child` is None where the messages do not say (PoseStamped)."""

    stamps: np.ndarray
    poses: list[Rigid3]
    child: str | None


def _rigid(translation: Any, rotation: Any, source: str) -> Rigid3:
    """A Rigid3 from ROS Point/Vector3 and Quaternion (x y z w: a unit quaternion,
    `unit_quaternion`'s rule, as every pose file's)."""
    t = np.array([translation.x, translation.y, translation.z], np.float64)
    q = np.array([rotation.x, rotation.y, rotation.z, rotation.w], np.float64)
    if not np.all(np.isfinite(t)) or np.abs(t).max() > MAX_COORDINATE:
        raise InputError(f"{source}: invalid pose (translation {t.tolist()}, quaternion "
                         f"{q.tolist()})")
    return Rigid3.from_qt(unit_quaternion(q, source), t)


def _pose_fields(msg: Any) -> tuple[Any, str | None, Any, Any]:
    """(header, child frame or None, translation, rotation) of a pose message."""
    if msg.__msgtype__ == ODOMETRY:
        pose = msg.pose.pose
        return msg.header, msg.child_frame_id, pose.position, pose.orientation
    if msg.__msgtype__ == POSE_STAMPED:
        return msg.header, None, msg.pose.position, msg.pose.orientation
    return msg.header, msg.child_frame_id, msg.transform.translation, msg.transform.rotation


def _pose_messages(bag: _Bag, spec: str) -> Iterator[tuple[float, Any]]:
    """(receive time, pose message) of a pose topic, or of the /tf transforms of a
    `tf:PARENT:CHILD` pair."""
    if not spec.startswith("tf:"):
        yield from bag.messages(spec)
        return
    pair = tf_frames(spec, str(bag.path))
    seen: set[tuple[str, str]] = set()  # every pair, for the tree check (`_tf_pairs`)
    for receive_time, msg in bag.messages(TF_TOPIC):
        for transform in msg.transforms:
            names = (_frame_id(transform.header.frame_id), _frame_id(transform.child_frame_id))
            seen.add(names)
            if names == pair:
                yield receive_time, transform
    bag.tf_pairs = seen


def _one_frame(bag: _Bag, spec: str, field: str, frames: list[str | None]) -> str | None:
    """The frame id that every message of pose `spec` names in `field` (`header.frame_id`:
    the world frame, `child_frame_id`: the frame posed; None: PoseStamped names none). Two
    frame ids on one topic are an InputError naming the bag, the topic and both: its poses
    would be of two frames, or in two worlds, taken as one trajectory. An empty id on every
    message is one frame id like any other."""
    other = next((i for i, frame in enumerate(frames) if frame != frames[0]), None)
    if other is not None:
        raise InputError(f"{bag.path}: pose {spec}: messages 0 and {other} have different "
                         f"{field} ({frames[0]!r} and {frames[other]!r}): the poses of one "
                         "topic must be of one frame in one world frame")
    return frames[0]


def _read_pose_track(bag: _Bag, spec: str) -> PoseTrack:
    """The pose messages of `spec` (a pose topic or tf:PARENT:CHILD), sorted by stamp, each
    stamp once: all must name one world and one child frame (`_one_frame`), and messages of
    one stamp must carry the same pose (`same_pose`), else InputError naming the bag, the
    topic and the frames or the stamp."""
    stamps, poses = [], []
    parents: list[str | None] = []  # header.frame_id of each message
    children: list[str | None] = []  # child_frame_id of each message (None: PoseStamped)
    for i, (receive_time, msg) in enumerate(_pose_messages(bag, spec)):
        header, child_frame, translation, rotation = _pose_fields(msg)
        stamps.append(_stamp(header, receive_time))
        poses.append(_rigid(translation, rotation, f"{bag.path}: pose {spec}, message {i}"))
        parents.append(_frame_id(header.frame_id))
        children.append(_frame_id(child_frame) if child_frame is not None else None)
    if not poses:
        raise InputError(f"{bag.path}: pose {spec} has no messages")
    _one_frame(bag, spec, "header.frame_id", parents)
    child = _one_frame(bag, spec, "child_frame_id", children)
    kept: list[int] = []  # message indices, by stamp, the first of each instant
    instants = Instants()
    for i in np.argsort(stamps, kind="stable").tolist():
        first = instants.setdefault(stamps[i], i)[1]
        if first == i:
            kept.append(i)
        elif not same_pose(poses[first], poses[i]):
            raise InputError(f"{bag.path}: pose {spec}: messages {first} and {i} are "
                             f"{_stamped_words(stamps[first], stamps[i])} but carry different "
                             f"poses ({pose_gap(poses[first], poses[i])})")
    return PoseTrack(np.asarray(stamps)[kept], [poses[i] for i in kept], child)


def _static_transforms(bag: _Bag) -> dict[tuple[str, str], Rigid3]:
    """(parent, child) -> parent_from_child of every /tf_static transform. A pair published
    again with the same transform (latched topics repeat) is read once; with another one it
    is an InputError naming the pair (`same_pose`): which one holds is not for us to guess.
    The transforms must form a tf tree (`_check_tree`): one chain between two frames."""
    if bag.topics.get(TF_STATIC_TOPIC, ("",))[0] != TF_MESSAGE:
        return {}
    edges: dict[tuple[str, str], Rigid3] = {}
    for _, msg in bag.messages(TF_STATIC_TOPIC):
        for t in msg.transforms:
            pair = (_frame_id(t.header.frame_id), _frame_id(t.child_frame_id))
            edge = _rigid(t.transform.translation, t.transform.rotation,
                          f"{bag.path}: /tf_static")
            if pair in edges and not same_pose(edges[pair], edge):
                raise InputError(f"{bag.path}: /tf_static gives {pair[0]} -> {pair[1]} twice "
                                 f"with different transforms ({pose_gap(edges[pair], edge)})")
            edges.setdefault(pair, edge)
    _check_tree(bag, [(pair, TF_STATIC_TOPIC) for pair in edges] + _tf_pairs(bag))
    return edges


def _tf_pairs(bag: _Bag) -> list[tuple[tuple[str, str], str]]:
    """((parent, child), "/tf") of every pair the bag's /tf transforms name (none without
    /tf): /tf and /tf_static make one tf tree. /tf is read here unless a pose's pass over it
    (`_pose_messages`) has already gathered them."""
    if bag.topics.get(TF_TOPIC, ("",))[0] != TF_MESSAGE:
        return []
    if bag.tf_pairs is None:
        bag.tf_pairs = {(_frame_id(t.header.frame_id), _frame_id(t.child_frame_id))
                        for _, msg in bag.messages(TF_TOPIC) for t in msg.transforms}
    return [(pair, TF_TOPIC) for pair in sorted(bag.tf_pairs)]


def _check_tree(bag: _Bag, pairs: list[tuple[tuple[str, str], str]]) -> None:
    """An InputError naming the bag where the (parent, child) pairs of /tf_static and /tf
    (each with the topic that gives it) are no tree: a frame given two parents (the frame,
    both parents and their topics) or a loop (its frames): either gives two chains between
    some frames, which may disagree, and which one holds is not for us to guess."""
    parents: dict[str, tuple[str, str]] = {}  # child -> (parent, the topic giving it)
    for (parent, child), topic in pairs:
        first, where = parents.setdefault(child, (parent, topic))
        if first != parent:
            said = f"{where} gives" if where == topic else f"{where} and {topic} give"
            raise InputError(f"{bag.path}: {said} frame {child} two parents ({first} and "
                             f"{parent}): a tf tree gives each frame one parent")
    loop = _loop({child: parent for child, (parent, _) in parents.items()})
    if loop:
        topics = sorted({parents[child][1] for child in loop[1:]})  # those of its transforms
        said = f"{topics[0]} has" if len(topics) == 1 else " and ".join(topics) + " hold"
        raise InputError(f"{bag.path}: {said} a loop ({' -> '.join(loop)}): a tf tree has "
                         "none")


def _loop(parents: dict[str, str]) -> list[str] | None:
    """The frames of a loop in a child -> parent map, parent first and back to it (["a", "b",
    "a"]: a -> b -> a), None where every frame's ancestors end at a root."""
    rooted: set[str] = set()  # frames whose ancestors end at a root
    for start in parents:
        path = {start: 0}  # start, its parent, its grandparent, ... -> place in the walk
        frame = start
        while frame in parents and frame not in rooted:
            frame = parents[frame]
            if frame in path:
                up = list(path)[path[frame]:]  # the loop, child first
                return up[::-1] + [up[-1]]
            path[frame] = len(path)
        rooted.update(path)
    return None


def static_chain(edges: dict[tuple[str, str], Rigid3], start: str, goal: str) -> Rigid3 | None:
    """start_from_goal through the static transforms (either direction), None without a
    chain. Breadth first: the chain of fewest transforms (in a tree, `_check_tree`, the only
    one)."""
    reached = {start: Rigid3.identity()}
    frontier = [start]
    while frontier and goal not in reached:
        nxt = []
        for frame in frontier:
            for (parent, child), parent_from_child in edges.items():
                step = (child, parent_from_child) if parent == frame else \
                    (parent, parent_from_child.inverse()) if child == frame else None
                if step and step[0] not in reached:
                    reached[step[0]] = reached[frame] @ step[1]
                    nxt.append(step[0])
        frontier = nxt
    return reached.get(goal)


def _child_from_cam(bag: _Bag, track: PoseTrack, image_frame: str) -> tuple[Rigid3, str]:
    """(the pose's child frame from the camera, a note for the listing, "" when direct)."""
    child = track.child
    if child is None or not image_frame or child == image_frame:
        return Rigid3.identity(), ""
    chain = static_chain(_static_transforms(bag), child, image_frame)
    if chain is None:
        return Rigid3.identity(), (f"bag: no /tf_static chain from the pose's frame {child!r} "
                                   f"to the image frame {image_frame!r}: the poses are taken "
                                   "as the camera's")
    return chain, f"bag: pose frame {child!r} composed with /tf_static to {image_frame!r}"


def _slerp(q0: np.ndarray, q1: np.ndarray, w: float) -> np.ndarray:
    """Spherical interpolation of unit quaternions (x y z w), shortest arc."""
    dot = float(q0 @ q1)
    if dot < 0:
        q1, dot = -q1, -dot
    if dot > 0.9995:  # nearly equal: linear, normalised
        q = q0 + w * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = np.arccos(dot)
    return (np.sin((1 - w) * theta) * q0 + np.sin(w * theta) * q1) / np.sin(theta)


def interpolate_pose(stamps: np.ndarray, poses: list[Rigid3], t: float,
                     max_gap: float = MAX_POSE_GAP) -> Rigid3 | None:
    """The pose at time `t` (seconds) between the poses stamped around it (sorted `stamps`):
    linear in translation, slerp in rotation; None unless a pose lies within `max_gap`
    seconds on both sides (a pose stamped exactly `t` is returned as it is)."""
    after = int(np.searchsorted(stamps, t, side="left"))  # first stamp >= t
    if after < len(stamps) and stamps[after] == t:
        return poses[after]
    before = after - 1
    if before < 0 or after >= len(stamps) or t - stamps[before] > max_gap \
            or stamps[after] - t > max_gap:
        return None
    w = (t - stamps[before]) / (stamps[after] - stamps[before])
    p0, p1 = poses[before], poses[after]
    q = _slerp(matrix_to_quat(p0.rotation), matrix_to_quat(p1.rotation), w)
    return Rigid3.from_qt(q, (1 - w) * p0.translation + w * p1.translation)


def _camera_poses(bag: _Bag, spec: str, image_frame: str) -> tuple[PoseTrack, str]:
    """The pose track of `spec` as world_from_cam (composed with the static chain to the
    image frame where there is one), and the listing's note."""
    track = _read_pose_track(bag, spec)
    child_from_cam, note = _child_from_cam(bag, track, image_frame)
    return PoseTrack(track.stamps, [p @ child_from_cam for p in track.poses], image_frame), note


# --- datasets ----------------------------------------------------------------------------------

def load_rosbag(path: str | Path, topics: BagTopics | None = None) -> Dataset:
    """A bag as a one-sequence Dataset (frames `"{stem}/{index:06d}"` in bag order, in both
    splits); `topics` default to `set_topics`' (the CLI's `--topic`), else are found
    automatically. One summary line per topic is printed."""
    global _default_topics_read
    path = Path(path)
    sequence = path.stem
    if topics is None:
        topics, _default_topics_read = default_topics(), True
    with _open_bag(path) as bag:
        chosen = _choose_topics(bag, topics)
        _print_choice(bag, chosen)
        image = chosen.image
        first = bag.first(image)
        if first is None:
            raise InputError(f"{bag.path}: image topic {image} has no messages")
        size = colour_file(first, f"{bag.path}: image topic {image}, message 0")[2]
        camera = _camera(bag, chosen.camera_info, image, size)
        track = None
        if chosen.pose:
            track, note = _camera_poses(bag, chosen.pose, _frame_id(first.header.frame_id))
            if note:
                _say(note)
        with _extraction_folder() as folder:
            stills = _extract(bag, image, folder / "image", colour_file, size, "image")
            depth = (_extract(bag, chosen.depth, folder / "depth", _depth_file, size, "depth")
                     if chosen.depth else [])
    stamps = np.array([s.stamp for s in stills])
    nearest = nearest_stamps([d.stamp for d in depth], stamps, MAX_DEPTH_DT)
    frames = [Frame(name=f"{sequence}/{i:06d}", image_path=still.path, camera=camera,
                    depth_path=depth[j].path if j >= 0 else None,
                    world_from_cam=interpolate_pose(track.stamps, track.poses, still.stamp)
                    if track else None,
                    sequence=sequence, timestamp=still.stamp)
              for i, (still, j) in enumerate(zip(stills, nearest))]
    return Dataset(path, "rosbag", {sequence: frames}, {"train": [sequence], "test": [sequence]},
                   depth_registered=True, depth_units_per_metre=DEPTH_UNITS_PER_METRE)


def bag_trajectory(path: str | Path, topic: str) -> tuple[np.ndarray, list[Rigid3]]:
    """(stamps in seconds, world_from_cam poses) of a bag's pose topic (or tf:PARENT:CHILD),
    composed with the /tf_static chain to the image frame where there is one (the image topic
    as `load_rosbag` chooses it)."""
    path = Path(path)
    with _open_bag(path) as bag:
        spec = _check_pose(bag, topic if topic.startswith(("/", "tf:")) else "/" + topic)
        first = bag.first(_choose_image(bag, default_topics()))
        frame = _frame_id(first.header.frame_id) if first is not None else ""
        track, _ = _camera_poses(bag, spec, frame)
    return track.stamps, track.poses

