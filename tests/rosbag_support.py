"""Writing ROS 1 and ROS 2 bags with rosbags, from a slamreloc dataset's frames (for
tests/test_rosbag.py): images (PNG CompressedImage or raw rgb8), 16UC1 or 32FC1 depth,
CameraInfo, and poses as PoseStamped, Odometry or /tf with the static rig on /tf_static."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from slamreloc.datasets import load_dataset
from slamreloc.datasets.base import Dataset
from slamreloc.datasets.rosbag import BagTopics, set_topics
from slamreloc.geometry import Rigid3, axis_angle_to_matrix
from slamreloc.io.images import read_image
from slamreloc.types import Camera, Frame

T0 = 1_700_000_000  # seconds: a frame's stamp is T0 + its timestamp in the dataset
CAM = "cam"  # the images' frame_id
IMAGE_TOPIC = "/cam/color/image_raw"
DEPTH_TOPIC = "/cam/aligned_depth_to_color/image_raw"
INFO_TOPIC = "/cam/color/camera_info"
# the rig: the odometry's "body" seen from the camera, and the tf chain base -> mount -> cam
CAM_FROM_BODY = Rigid3(axis_angle_to_matrix([0.1, -0.2, 0.3]), np.array([0.05, -0.02, 0.1]))
BASE_FROM_MOUNT = Rigid3(axis_angle_to_matrix([0.0, 0.0, 0.5]), np.array([0.2, 0.0, 0.4]))
MOUNT_FROM_CAM = Rigid3(axis_angle_to_matrix([-1.2, 0.0, -1.5]), np.array([0.0, 0.03, 0.0]))
# Camera model -> CameraInfo distortion model and the padding of D to its length
ROS_MODELS = {"PINHOLE": ("plumb_bob", 5), "OPENCV": ("plumb_bob", 5),
              "FULL_OPENCV": ("rational_polynomial", 8), "OPENCV_FISHEYE": ("equidistant", 4)}


def full_resolution(camera: Camera, binning: tuple[int, int] = (1, 1),
                    roi_offset: tuple[int, int] = (0, 0),
                    size: tuple[int, int] | None = None) -> Camera:
    """The full-resolution calibration (of `size`, default the window's) of which `camera` is
    the image delivered with `binning` (binning_x, binning_y; 0 is 1) and a window at
    `roi_offset`: f_full = b f, c_full = b c + offset + (b - 1) / 2 (a binned pixel's centre
    is the centre of the b full-resolution pixels it sums)."""
    bx, by = (b or 1 for b in binning)
    x, y = roi_offset
    width, height = size or (camera.width * bx + x, camera.height * by + y)
    return Camera(width, height, camera.fx * bx, camera.fy * by,
                  camera.cx * bx + x + (bx - 1) / 2, camera.cy * by + y + (by - 1) / 2,
                  camera.model, camera.distortion)


def stamp_ns(seconds: float) -> int:
    return int(round(seconds * 1e9))


class Messages:
    """Message builders for a bag of one ROS version (ROS 2 Humble's types, or ROS 1 Noetic's
    plus tf2_msgs/TFMessage, which rosbags' Noetic store lacks)."""

    def __init__(self, version: int):
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        self.version = version
        self.store = get_typestore(Stores.ROS2_HUMBLE if version == 2 else Stores.ROS1_NOETIC)
        if "tf2_msgs/msg/TFMessage" not in self.store.types:
            self.store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms",
                                                   "tf2_msgs/msg/TFMessage"))

    def make(self, msgtype: str, **values: Any) -> Any:
        """A message; field names in ROS 2 spelling (ROS 1 CameraInfo's are upper case)."""
        cls = self.store.types[msgtype]
        names = cls.__dataclass_fields__
        return cls(**{k if k in names else k.upper(): v for k, v in values.items()})

    def header(self, stamp: float, frame: str = CAM) -> Any:
        ns = stamp_ns(stamp)
        time = self.make("builtin_interfaces/msg/Time", sec=ns // 10**9, nanosec=ns % 10**9)
        seq = {"seq": 0} if self.version == 1 else {}
        return self.make("std_msgs/msg/Header", stamp=time, frame_id=frame, **seq)

    def compressed(self, stamp: float, data: bytes, fmt: str) -> Any:
        return self.make("sensor_msgs/msg/CompressedImage", header=self.header(stamp),
                         format=fmt, data=np.frombuffer(data, np.uint8).copy())

    def raw(self, stamp: float, pixels: np.ndarray, encoding: str,
            size: tuple[int, int] | None = None) -> Any:
        """A raw Image of `pixels` ((H, W[, C]) uint8/uint16/float32, little-endian);
        `size` (width, height): the size the message claims instead of the pixels'."""
        h, w = pixels.shape[:2]
        width, height = size or (w, h)
        data = np.ascontiguousarray(pixels).view(np.uint8).reshape(-1)
        return self.make("sensor_msgs/msg/Image", header=self.header(stamp), height=height,
                         width=width, encoding=encoding, is_bigendian=0,
                         step=len(data) // h, data=data.copy())

    def camera_info(self, stamp: float, camera: Camera, model: str | None = None,
                    d: list[float] | None = None, binning: tuple[int, int] = (0, 0),
                    roi: tuple[int, int, int, int] = (0, 0, 0, 0),
                    size: tuple[int, int] | None = None) -> Any:
        """A CameraInfo of `camera`, or of its K with the given distortion model and D;
        `binning` (binning_x, binning_y), `roi` (x_offset, y_offset, width, height) and `size`
        (the width, height it claims instead of the camera's; (0, 0): not given) as given
        (`camera` is then the full-resolution calibration: see `full_resolution`)."""
        name, n = ROS_MODELS[camera.model]
        d = d if d is not None else (list(camera.distortion) + [0.0] * n)[:n]
        k = [camera.fx, 0, camera.cx, 0, camera.fy, camera.cy, 0, 0, 1]
        p = [camera.fx, 0, camera.cx, 0, 0, camera.fy, camera.cy, 0, 0, 0, 1, 0]
        x, y, w, h = roi
        window = self.make("sensor_msgs/msg/RegionOfInterest", x_offset=x, y_offset=y,
                           height=h, width=w, do_rectify=False)
        width, height = size or (camera.width, camera.height)
        return self.make("sensor_msgs/msg/CameraInfo", header=self.header(stamp),
                         height=height, width=width,
                         distortion_model=model or name, d=np.array(d, np.float64),
                         k=np.array(k, np.float64), r=np.eye(3).reshape(-1),
                         p=np.array(p, np.float64), binning_x=binning[0],
                         binning_y=binning[1], roi=window)

    def _xyz(self, msgtype: str, v) -> Any:
        return self.make(msgtype, x=float(v[0]), y=float(v[1]), z=float(v[2]))

    def _quaternion(self, pose: Rigid3) -> Any:
        x, y, z, w = pose.quat_xyzw()
        return self.make("geometry_msgs/msg/Quaternion", x=x, y=y, z=z, w=w)

    def _pose(self, pose: Rigid3) -> Any:
        return self.make("geometry_msgs/msg/Pose",
                         position=self._xyz("geometry_msgs/msg/Point", pose.translation),
                         orientation=self._quaternion(pose))

    def transform(self, stamp: float, parent: str, child: str, pose: Rigid3) -> Any:
        """A TransformStamped: parent_from_child = `pose`."""
        transform = self.make("geometry_msgs/msg/Transform",
                              translation=self._xyz("geometry_msgs/msg/Vector3",
                                                    pose.translation),
                              rotation=self._quaternion(pose))
        return self.make("geometry_msgs/msg/TransformStamped",
                         header=self.header(stamp, parent), child_frame_id=child,
                         transform=transform)

    def pose_stamped(self, stamp: float, parent: str, pose: Rigid3) -> Any:
        return self.make("geometry_msgs/msg/PoseStamped", header=self.header(stamp, parent),
                         pose=self._pose(pose))

    def odometry(self, stamp: float, parent: str, child: str, pose: Rigid3) -> Any:
        zero = self._xyz("geometry_msgs/msg/Vector3", (0, 0, 0))
        twist = self.make("geometry_msgs/msg/Twist", linear=zero, angular=zero)
        return self.make(
            "nav_msgs/msg/Odometry", header=self.header(stamp, parent), child_frame_id=child,
            pose=self.make("geometry_msgs/msg/PoseWithCovariance", pose=self._pose(pose),
                           covariance=np.zeros(36)),
            twist=self.make("geometry_msgs/msg/TwistWithCovariance", twist=twist,
                            covariance=np.zeros(36)))

    def tf(self, transforms: list[Any]) -> Any:
        return self.make("tf2_msgs/msg/TFMessage", transforms=transforms)


def write_messages(path: Path, msgs: Messages, topics: dict[str, list[Any]],
                   mcap: bool = False) -> Path:
    """A bag at `path` (ROS 2: a folder, SQLite or MCAP storage; ROS 1: a .bag file) with the
    messages of each topic, each received at its header stamp (TFMessage: its first
    transform's)."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2

    if msgs.version == 2:
        storage = StoragePlugin.MCAP if mcap else StoragePlugin.SQLITE3
        writer, serialize = Writer2(path, version=9, storage_plugin=storage), \
            msgs.store.serialize_cdr
    else:
        writer, serialize = Writer1(path), msgs.store.serialize_ros1
    with writer:
        for topic, messages in topics.items():
            if not messages:
                continue
            connection = writer.add_connection(topic, messages[0].__msgtype__,
                                               typestore=msgs.store)
            for msg in messages:
                header = msg.transforms[0].header if hasattr(msg, "transforms") else msg.header
                stamp = header.stamp.sec * 10**9 + header.stamp.nanosec
                writer.write(connection, stamp, serialize(msg, msg.__msgtype__))
    return path


def frame_stamp(frame: Frame) -> float:
    return T0 + frame.timestamp


def _image(msgs: Messages, frame: Frame, compressed: bool) -> Any:
    if compressed:
        fmt = "png" if frame.image_path.suffix == ".png" else "jpeg"
        return msgs.compressed(frame_stamp(frame), frame.image_path.read_bytes(), fmt)
    return msgs.raw(frame_stamp(frame), read_image(frame.image_path), "rgb8")


def _depth(msgs: Messages, frame: Frame, encoding: str, units_per_metre: float) -> Any:
    mm = cv2.imread(str(frame.depth_path), cv2.IMREAD_ANYDEPTH)
    if encoding == "32FC1":
        valid = (mm > 0) & (mm < 65535)
        return msgs.raw(frame_stamp(frame),
                        np.where(valid, mm / units_per_metre, np.nan).astype(np.float32),
                        encoding)
    return msgs.raw(frame_stamp(frame), mm, encoding)


def _poses(msgs: Messages, frames: list[Frame], kind: str) -> dict[str, list[Any]]:
    """The pose topics of `kind`: world_from_cam of each frame, at its stamp, as a PoseStamped
    (/pose), as the Odometry of the rig's body (/odom), or as /tf of the rig's base (map ->
    base, with base -> mount -> cam on /tf_static)."""
    stamps = [frame_stamp(f) for f in frames]
    if kind == "pose":
        return {"/pose": [msgs.pose_stamped(t, "map", f.world_from_cam)
                          for t, f in zip(stamps, frames)]}
    if kind == "odometry":
        return {"/odom": [msgs.odometry(t, "map", "body", f.world_from_cam @ CAM_FROM_BODY)
                          for t, f in zip(stamps, frames)]}
    cam_from_base = (BASE_FROM_MOUNT @ MOUNT_FROM_CAM).inverse()
    return {"/tf": [msgs.tf([msgs.transform(t, "map", "base", f.world_from_cam @ cam_from_base)])
                    for t, f in zip(stamps, frames)]}


def static_tf(msgs: Messages, stamp: float) -> list[Any]:
    """The rig on /tf_static: base -> mount -> cam, and cam -> body."""
    return [msgs.tf([msgs.transform(stamp, "base", "mount", BASE_FROM_MOUNT),
                     msgs.transform(stamp, "mount", CAM, MOUNT_FROM_CAM),
                     msgs.transform(stamp, CAM, "body", CAM_FROM_BODY)])]


def write_bag(dataset: Dataset, frames: list[Frame], path: Path, version: int = 2,
              compressed: bool = True, depth: bool | str = True, poses: str | None = "pose",
              camera: Camera | None = None, camera_info: bool = True, static: bool = True,
              extra: dict[str, list[Any]] | None = None, mcap: bool = False) -> Path:
    """A bag of `frames` (from `dataset`): images (PNG/JPEG bytes as CompressedImage, else raw
    rgb8), depth (16UC1 mm; "32FC1": metres), CameraInfo of `camera` (default: the frames'),
    poses "pose" | "odometry" | "tf" | None at the image stamps, /tf_static with the rig when
    `static`, and `extra` topics."""
    msgs = Messages(version)
    t0 = frame_stamp(frames[0])
    topics = {(IMAGE_TOPIC + "/compressed" if compressed else IMAGE_TOPIC):
              [_image(msgs, f, compressed) for f in frames]}
    if depth:
        encoding = depth if isinstance(depth, str) else "16UC1"
        topics[DEPTH_TOPIC] = [_depth(msgs, f, encoding, dataset.depth_units_per_metre)
                               for f in frames]
    if camera_info:
        topics[INFO_TOPIC] = [msgs.camera_info(frame_stamp(f), camera or f.camera)
                              for f in frames]
    if poses:
        topics.update(_poses(msgs, frames, poses))
    if static:
        topics["/tf_static"] = static_tf(msgs, t0)
    topics.update(extra or {})
    return write_messages(path, msgs, topics, mcap)


@pytest.fixture(autouse=True)
def automatic_topics():
    """`--topic` (and `set_topics`) hold process-wide: reset them after each test (a test
    module takes this fixture by importing it)."""
    yield
    set_topics(BagTopics())


def first_test_frames(scene_dir: Path, n: int) -> tuple[Dataset, list[Frame]]:
    """(the synthetic scene's dataset, its first `n` test frames): what bag tests write."""
    dataset = load_dataset(scene_dir)
    return dataset, dataset.frames("test")[:n]
