"""ROS 1 and ROS 2 bags as datasets: bags written with rosbags from the synthetic scene's
frames load to the same images, depth, camera and poses as the scene's folder; topics are
found automatically or named with `--topic`; bad bags end in one error line naming the bag."""

from __future__ import annotations

import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from slamreloc.datasets import load_dataset
from slamreloc.datasets.rosbag import (
    BagTopics,
    bag_trajectory,
    interpolate_pose,
    is_rosbag,
    load_rosbag,
    parse_topics,
    ros_lens,
    set_topics,
)
from slamreloc.errors import InputError
from slamreloc.geometry import Rigid3, axis_angle_to_matrix
from slamreloc.io.images import read_depth, read_image
from slamreloc.slam.run import make_odometry
from slamreloc.types import Camera
from tests.fuzzing import run_cli
from tests.rosbag_support import (  # noqa: F401 - automatic_topics: a fixture
    automatic_topics,
    first_test_frames,
    CAM_FROM_BODY,
    DEPTH_TOPIC,
    IMAGE_TOPIC,
    INFO_TOPIC,
    Messages,
    frame_stamp,
    write_bag,
    write_messages,
)
from tests.test_fuzz_inputs import _tiny_map

REPO = Path(__file__).resolve().parents[1]
N_FRAMES = 8


@pytest.fixture(scope="module")
def scene(scene_dir):
    """(the synthetic scene's dataset, the first test frames)."""
    return first_test_frames(scene_dir, N_FRAMES)


@pytest.fixture(scope="module")
def tiny_map(tmp_path_factory) -> Path:
    return _tiny_map(tmp_path_factory.mktemp("rosbag") / "map")




def bag_path(tmp_path: Path, version: int, name: str = "run") -> Path:
    return tmp_path / (f"{name}.bag" if version == 1 else name)


def assert_same_frames(folder_frames, bag_frames, depth: bool = True, poses: bool = True):
    assert len(bag_frames) == len(folder_frames)
    for i, (f, g) in enumerate(zip(folder_frames, bag_frames)):
        assert g.name.endswith(f"/{i:06d}") and g.sequence == g.name.split("/")[0]
        assert g.timestamp == pytest.approx(frame_stamp(f), abs=1e-6)
        assert g.camera == f.camera
        assert np.array_equal(read_image(g.image_path), read_image(f.image_path))
        if depth:
            assert np.array_equal(read_depth(g.depth_path), read_depth(f.depth_path))
        if poses:
            assert np.abs(g.world_from_cam.matrix() - f.world_from_cam.matrix()).max() < 1e-9


# --- loading -----------------------------------------------------------------------------------

@pytest.mark.parametrize("version,compressed,poses", [
    (2, True, "pose"), (1, False, "odometry"), (2, False, "tf"), (1, True, "tf")])
def test_bag_loads_like_the_folder(scene, tmp_path, version, compressed, poses):
    """Images pixel for pixel, depth, camera, poses within 1e-9 (odometry: the rig's body,
    composed back to the camera through /tf_static in reverse; tf: map -> base and the static
    base -> mount -> cam chain)."""
    dataset, frames = scene
    bag = write_bag(dataset, frames, bag_path(tmp_path, version), version, compressed,
                    poses=poses)
    assert is_rosbag(bag)
    if poses == "tf":
        set_topics(parse_topics(["pose=tf:map:base"]))
    loaded = load_dataset(bag)
    assert (loaded.kind, loaded.root, loaded.depth_registered) == ("rosbag", bag, True)
    assert loaded.depth_units_per_metre == 1000.0
    assert loaded.splits == {"train": [bag.stem], "test": [bag.stem]}
    assert_same_frames(frames, loaded.frames("test"))
    suffix = ".png" if not compressed else frames[0].image_path.suffix
    assert all(f.image_path.suffix == suffix for f in loaded.frames())


def test_frames_are_extracted_apart_from_the_bag_and_removed_at_exit(scene, tmp_path):
    dataset, frames = scene
    bag = write_bag(dataset, frames[:2], tmp_path / "run", poses=None)
    code = ("from slamreloc.datasets.rosbag import load_rosbag; "
            f"print(load_rosbag({str(bag)!r}).frames()[0].image_path)")
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True,
                         text=True, check=True)
    image = Path(out.stdout.strip())
    assert image.parent.parent.name.startswith("slamreloc-bag-")
    assert bag not in image.parents and not image.parent.parent.exists()
    assert sorted(p.name for p in bag.iterdir()) == ["metadata.yaml", "run.db3"]


def test_ros2_storage_files_and_mcap(scene, tmp_path):
    dataset, frames = scene
    sqlite = write_bag(dataset, frames[:3], tmp_path / "sqlite")
    mcap = write_bag(dataset, frames[:3], tmp_path / "mcap", mcap=True)
    for bag in (sqlite / "sqlite.db3", mcap, mcap / "mcap.mcap"):
        assert is_rosbag(bag)
        assert_same_frames(frames[:3], load_dataset(bag).frames())


def test_depth_in_metres(scene, tmp_path):
    dataset, frames = scene
    bag = write_bag(dataset, frames[:3], tmp_path / "run", depth="32FC1", poses=None)
    assert_same_frames(frames[:3], load_rosbag(bag).frames(), poses=False)


def test_images_without_pose_nearby_stay_unposed(scene, tmp_path):
    dataset, frames = scene
    msgs = Messages(2)
    poses = [msgs.pose_stamped(frame_stamp(f), "map", f.world_from_cam) for f in frames[:4]]
    bag = write_bag(dataset, frames, tmp_path / "run", poses=None, extra={"/pose": poses})
    loaded = load_rosbag(bag).frames()
    assert_same_frames(frames[:4], loaded[:4])
    assert all(f.world_from_cam is None for f in loaded[4:])


def test_interpolation_between_pose_messages():
    a = Rigid3(np.eye(3), np.zeros(3))
    b = Rigid3(axis_angle_to_matrix([0, 0, 0.2]), np.array([1.0, 0, 0]))
    mid = interpolate_pose(np.array([10.0, 10.1]), [a, b], 10.05)
    assert np.allclose(mid.rotation, axis_angle_to_matrix([0, 0, 0.1]), atol=1e-9)
    assert np.allclose(mid.translation, [0.5, 0, 0])
    assert interpolate_pose(np.array([10.0, 10.1]), [a, b], 10.1) is b
    for stamps, t in (([10.0, 10.25], 10.05), ([10.0, 10.1], 9.99), ([10.0, 10.1], 10.11)):
        assert interpolate_pose(np.array(stamps), [a, b], t) is None


# --- topics ------------------------------------------------------------------------------------

def test_auto_detection_and_listing(scene, tmp_path, capsys):
    """The colour topic with the most messages, the aligned depth, the CameraInfo of the
    image's namespace, the only pose topic; one line each."""
    dataset, frames = scene
    msgs = Messages(2)
    ir = [msgs.raw(frame_stamp(f), read_image(f.image_path)[..., 0], "mono8")
          for f in frames[:3]]
    extra = {"/cam/ir/image_raw": ir,
             "/cam/ir/camera_info": [msgs.camera_info(frame_stamp(f), f.camera) for f in frames],
             "/cam/depth/image_rect_raw": [msgs.raw(frame_stamp(f), np.zeros((20, 30), np.uint16),
                                                    "16UC1") for f in frames]}
    bag = write_bag(dataset, frames, tmp_path / "run", compressed=False, extra=extra)
    assert_same_frames(frames, load_rosbag(bag).frames())
    assert capsys.readouterr().err.splitlines() == [
        f"bag: image {IMAGE_TOPIC} (sensor_msgs/msg/Image, 8 messages)",
        f"bag: depth {DEPTH_TOPIC} (sensor_msgs/msg/Image, 8 messages)",
        f"bag: camera_info {INFO_TOPIC} (sensor_msgs/msg/CameraInfo, 8 messages)",
        "bag: pose /pose (geometry_msgs/msg/PoseStamped, 8 messages)"]


def test_a_choice_that_would_be_a_guess_is_refused(scene, tmp_path):
    """Two colour cameras with as many messages, two depth topics alike, or a CameraInfo only
    under another camera's namespace: refused, naming the topics, until `--topic` names one;
    then the bag loads."""
    dataset, frames = scene
    msgs = Messages(2)
    second = {"/cam2/color/image_raw": [msgs.raw(frame_stamp(f), read_image(f.image_path),
                                                 "rgb8") for f in frames]}
    bag = write_bag(dataset, frames, tmp_path / "two_cameras", compressed=False, extra=second)
    with pytest.raises(InputError, match=r"2 image topics could be the one to read \("
                       r"/cam/color/image_raw, /cam2/color/image_raw\): name one"):
        load_rosbag(bag)
    loaded = load_rosbag(bag, parse_topics([f"image={IMAGE_TOPIC}"])).frames()
    assert_same_frames(frames, loaded)

    depth = {"/cam/depth2/image_raw": [msgs.raw(frame_stamp(f), np.zeros((20, 30), np.uint16),
                                                "16UC1") for f in frames]}
    bag = write_bag(dataset, frames, tmp_path / "two_depths", depth=False, extra={
        **depth, "/cam/depth/image_raw": depth["/cam/depth2/image_raw"]})
    with pytest.raises(InputError, match="2 depth topics could be the one to read"):
        load_rosbag(bag)

    other = {"/cam2/camera_info": [msgs.camera_info(frame_stamp(f), f.camera) for f in frames]}
    bag = write_bag(dataset, frames, tmp_path / "other_info", camera_info=False, extra=other)
    with pytest.raises(InputError, match=r"CameraInfo topics, /cam2/camera_info, are of other "
                       r"cameras or several\): add /cam/color/camera_info"):
        load_rosbag(bag).frames()
    loaded = load_rosbag(bag, parse_topics(["camera_info=/cam2/camera_info"])).frames()
    assert_same_frames(frames, loaded)


def test_listing_says_what_was_not_found(scene, tmp_path, capsys):
    dataset, frames = scene
    msgs = Messages(1)
    odometry = [msgs.odometry(frame_stamp(f), "map", "body", f.world_from_cam) for f in frames]
    bag = write_bag(dataset, frames, tmp_path / "run.bag", 1, depth=False,
                    extra={"/odom": odometry})
    with pytest.warns(UserWarning, match="no pose topic chosen from the candidates /odom, "
                      "/pose: the frames have no poses unless one is named"):
        loaded = load_rosbag(bag).frames()
    assert all(f.depth_path is None and f.world_from_cam is None for f in loaded)
    lines = capsys.readouterr().err.splitlines()
    assert lines[1] == "bag: no depth topic found"
    assert lines[3] == "bag: no pose topic found"
    # on the command line: the warning names the option as it is typed
    done = subprocess.run([sys.executable, "-m", "slamreloc.cli", "map", str(bag), "--out",
                           str(tmp_path / "m")], capture_output=True, text=True)
    code, err = done.returncode, done.stderr
    assert code == 2 and "warning: " in err and "named with slamreloc --topic pose=NAME" in err
    assert err.splitlines()[-1].startswith("error: ") and "has no pose" in err


def test_pose_without_a_static_chain_is_the_cameras(scene, tmp_path, capsys):
    dataset, frames = scene
    bag = write_bag(dataset, frames[:3], tmp_path / "run", poses="odometry", static=False)
    loaded = load_rosbag(bag).frames()
    assert "no /tf_static chain from the pose's frame 'body' to the image frame 'cam'" in \
        capsys.readouterr().err
    for f, g in zip(frames, loaded):
        expected = (f.world_from_cam @ CAM_FROM_BODY).matrix()
        assert np.abs(g.world_from_cam.matrix() - expected).max() < 1e-9


def test_parse_topics():
    assert parse_topics(["image=cam/x", "camera-info=/ci", "pose=tf:map:cam", "depth=/d"]) == \
        BagTopics(image="/cam/x", depth="/d", camera_info="/ci", pose="tf:map:cam")
    for bad in ("image", "colour=/x", "image=", "pose=tf:map", "pose=tf::cam"):
        with pytest.raises(InputError, match="`topic`") as err:
            parse_topics([bad])
        assert "\n" not in str(err.value)


def test_topic_option_of_the_cli(scene, tmp_path, tiny_map):
    """`slamreloc --topic KIND=NAME CMD`: the named topics, the others found automatically."""
    dataset, frames = scene
    msgs = Messages(2)
    ir = [msgs.raw(frame_stamp(f), read_image(f.image_path)[..., 0], "mono8") for f in frames]
    info = [msgs.camera_info(frame_stamp(f), f.camera) for f in frames]
    bag = write_bag(dataset, frames[:3], tmp_path / "run", poses="tf",
                    extra={"/ir/image_raw": ir[:2], "/ir/camera_info": info})
    code, err = run_cli(["--topic", "image=/ir/image_raw", "--topic", "depth=/ir/image_raw",
                         "--topic", "pose=tf:map:base", "evaluate", str(tiny_map), str(bag),
                         "--report", str(tmp_path / "r.json"), "--method", "matching"])
    assert code == 2 and err.splitlines()[-1] == (
        f"error: {bag}: depth topic /ir/image_raw, message 0: depth encoding 'mono8' is not "
        "read (known: 16UC1, 32FC1)")
    assert "bag: image /ir/image_raw (sensor_msgs/msg/Image, 2 messages)" in err
    assert "bag: camera_info /ir/camera_info (sensor_msgs/msg/CameraInfo, 8 messages)" in err
    assert "bag: pose tf:map:base (/tf, tf2_msgs/msg/TFMessage, 3 messages)" in err
    code, err = run_cli(["--topic", "image=/ir/image_raw", "--topic", "pose=tf:map:base",
                         "evaluate", str(tiny_map), str(bag), "--report", str(tmp_path / "r.json"),
                         "--method", "matching"])
    assert code == 0 and (tmp_path / "r.json").is_file(), err


# --- cameras -----------------------------------------------------------------------------------

@pytest.mark.parametrize("model,d,expected", [
    ("plumb_bob", [0, 0, 0, 0, 0], ("PINHOLE", ())),
    ("", [], ("PINHOLE", ())),
    ("plumb_bob", [0.1, -0.01, 0.001, 0.002, 0], ("OPENCV", (0.1, -0.01, 0.001, 0.002))),
    ("plumb_bob", [0.1, -0.01, 0.001, 0.002, 0.003],
     ("FULL_OPENCV", (0.1, -0.01, 0.001, 0.002, 0.003, 0, 0, 0))),
    ("rational_polynomial", [0.1, -0.01, 0.001, 0.002, 0.003, 0.2, 0.01, 0.004],
     ("FULL_OPENCV", (0.1, -0.01, 0.001, 0.002, 0.003, 0.2, 0.01, 0.004))),
    ("equidistant", [0.1, -0.01, 0.003, 0.001], ("OPENCV_FISHEYE", (0.1, -0.01, 0.003, 0.001)))])
def test_distortion_models(model, d, expected):
    assert ros_lens(model, d, "bag") == expected


@pytest.mark.parametrize("model,distortion", [
    ("OPENCV", (0.1, -0.01, 0.001, 0.002)),
    ("FULL_OPENCV", (0.1, -0.01, 0.001, 0.002, 0.003, 0.2, 0.01, 0.004)),
    ("OPENCV_FISHEYE", (0.1, -0.01, 0.003, 0.001))])
def test_camera_info_to_camera(scene, tmp_path, model, distortion):
    dataset, frames = scene
    camera = replace(frames[0].camera, model=model, distortion=distortion)
    bag = write_bag(dataset, frames[:2], tmp_path / "run", poses=None, camera=camera)
    assert all(f.camera == camera for f in load_rosbag(bag).frames())


# --- odometry from a bag -----------------------------------------------------------------------

def test_odometry_topic(scene, tmp_path, tiny_map):
    """`--odometry topic:/odom`: the topic's poses (composed to the camera) at each frame."""
    dataset, frames = scene
    bag = write_bag(dataset, frames, tmp_path / "run.bag", 1, poses="odometry")
    stamps, poses = bag_trajectory(bag, "/odom")
    assert np.allclose(stamps, [frame_stamp(f) for f in frames], atol=1e-6)
    odometry = make_odometry("topic:/odom", None, bag)
    for f in frames:
        step = odometry.step(None, f.camera, timestamp=float(frame_stamp(f)))
        assert np.abs(step.odom_from_cam.matrix() - f.world_from_cam.matrix()).max() < 1e-9
    with pytest.raises(InputError, match="ROS bag"):
        make_odometry("topic:/odom", None, None)
    code, err = run_cli(["slam", str(bag), "--map", str(tiny_map), "--report",
                         str(tmp_path / "r.json"), "--odometry", "topic:/odom"])
    assert code == 0 and (tmp_path / "r.json").is_file(), err


# --- bad bags ----------------------------------------------------------------------------------

def _messages_bag(tmp, version, topics) -> Path:
    return write_messages(bag_path(tmp, version), Messages(version), topics)


def _junk_bag(ds, frames, tmp):
    (tmp / "run.bag").write_bytes(b"#ROSBAG V2.0\n" + bytes(range(256)) * 8)
    return tmp / "run.bag", [], "not a readable ROS bag"


def _bad_metadata(ds, frames, tmp):
    (tmp / "run").mkdir()
    (tmp / "run" / "metadata.yaml").write_text("rosbag2_bagfile_information: [")
    return tmp / "run", [], "not a readable ROS bag"


def _no_image_topic(ds, frames, tmp):
    msgs = Messages(2)
    bag = _messages_bag(tmp, 2, {INFO_TOPIC: [msgs.camera_info(1.0, frames[0].camera)]})
    return bag, [], f"no image topic (sensor_msgs/Image or CompressedImage with colour " \
                    f"images; topics: {INFO_TOPIC} (sensor_msgs/msg/CameraInfo, 1))"


def _missing_topic(ds, frames, tmp):
    bag = write_bag(ds, frames[:2], tmp / "run")
    return bag, ["--topic", "depth=/nope"], "depth topic /nope is not in the bag (topics: "


def _wrong_type(ds, frames, tmp):
    bag = write_bag(ds, frames[:2], tmp / "run.bag", 1)
    return bag, ["--topic", f"pose={INFO_TOPIC}"], \
        f"pose topic {INFO_TOPIC} is sensor_msgs/msg/CameraInfo, not nav_msgs/msg/Odometry or"


def _unknown_encoding(ds, frames, tmp):
    msgs = Messages(1)
    image = msgs.raw(1.0, np.zeros((240, 320, 2), np.uint8), "yuv422")
    bag = _messages_bag(tmp, 1, {IMAGE_TOPIC: [image],
                                 INFO_TOPIC: [msgs.camera_info(1.0, frames[0].camera)]})
    return bag, [], f"image topic {IMAGE_TOPIC}, message 0: image encoding 'yuv422' is not read"


def _camera_info_bag(ds, frames, tmp, model, d):
    msgs = Messages(2)
    info = [msgs.camera_info(frame_stamp(f), f.camera, model, d) for f in frames[:2]]
    return write_bag(ds, frames[:2], tmp / "run", camera_info=False, extra={INFO_TOPIC: info})


def _unknown_distortion(ds, frames, tmp):
    bag = _camera_info_bag(ds, frames, tmp, "kannala_brandt", [0.1, 0.01, 0.0, 0.0])
    return bag, [], (f"camera_info topic {INFO_TOPIC}: distortion model 'kannala_brandt' is "
                     "not read (known: plumb_bob, rational_polynomial, equidistant)")


def _coefficient_count(ds, frames, tmp):
    bag = _camera_info_bag(ds, frames, tmp, "plumb_bob", [0.1, 0.01, 0.0, 0.0])
    return bag, [], (f"camera_info topic {INFO_TOPIC}: distortion model plumb_bob has 5 "
                     "coefficients, D has 4")


def _no_camera_info(ds, frames, tmp):
    bag = write_bag(ds, frames[:2], tmp / "run", camera_info=False)
    return bag, [], (f"no sensor_msgs/CameraInfo for image topic {IMAGE_TOPIC}/compressed: add "
                     f"{INFO_TOPIC} to the bag, or name one with slamreloc --topic "
                     "camera_info=NAME")


def _depth_size(ds, frames, tmp):
    msgs = Messages(2)
    depth = [msgs.raw(frame_stamp(f), np.ones((120, 160), np.uint16), "16UC1")
             for f in frames[:2]]
    bag = write_bag(ds, frames[:2], tmp / "run", depth=False, extra={DEPTH_TOPIC: depth})
    return bag, [], (f"depth topic {DEPTH_TOPIC}, message 0: depth is 160x120 pixels, the "
                     "images are 320x240 (depth must be registered to the images)")


def _huge_image(ds, frames, tmp):
    msgs = Messages(2)
    image = msgs.raw(1.0, np.zeros((240, 320, 3), np.uint8), "rgb8", size=(100000, 100000))
    bag = _messages_bag(tmp, 2, {IMAGE_TOPIC: [image],
                                 INFO_TOPIC: [msgs.camera_info(1.0, frames[0].camera)]})
    return bag, [], (f"image topic {IMAGE_TOPIC}, message 0: image is 100000x100000 = "
                     "10000.0 MP, over the 16.8 MP limit")


def _odometry_topic_missing(ds, frames, tmp):
    bag = write_bag(ds, frames[:2], tmp / "run")
    return bag, ["slam", "--odometry", "topic:/odom"], "pose topic /odom is not in the bag"


CASES = [_junk_bag, _bad_metadata, _no_image_topic, _missing_topic, _wrong_type,
         _unknown_encoding, _unknown_distortion, _coefficient_count, _no_camera_info,
         _depth_size, _huge_image, _odometry_topic_missing]


@pytest.mark.parametrize("case", CASES, ids=[c.__name__.strip("_") for c in CASES])
def test_bad_bag_is_one_error_line_naming_it(scene, tmp_path, tiny_map, case):
    dataset, frames = scene
    bag, options, problem = case(dataset, frames, tmp_path)
    report = tmp_path / "r.json"
    if options[:1] == ["slam"]:
        argv = ["slam", str(bag), "--map", str(tiny_map), "--report", str(report), *options[1:]]
    else:
        argv = [*options, "evaluate", str(tiny_map), str(bag), "--report", str(report),
                "--method", "matching"]
    code, err = run_cli(argv)
    assert "Traceback" not in err, err
    errors = [line for line in err.splitlines() if line.startswith("error:")]
    assert code == 2 and len(errors) == 1 and err.splitlines()[-1] == errors[0], err
    assert errors[0].startswith(f"error: {bag}: {problem}"), errors[0]
    assert not report.exists()


def test_bad_topic_option_is_one_error_line(tmp_path, tiny_map):
    code, err = run_cli(["--topic", "colour=/x", "evaluate", str(tiny_map), str(tmp_path),
                         "--report", str(tmp_path / "r.json")])
    assert code == 2 and err.strip() == ("error: slamreloc --topic 'colour=/x': expected KIND=NAME with "
                                         "KIND one of image, depth, camera_info, pose")


def test_camera_of_a_bag_is_checked(scene, tmp_path):
    """K's values go through Camera's checks, the error naming the bag and topic."""
    dataset, frames = scene
    camera = Camera(320, 240, 262.5, 262.5, 159.5, 119.5)
    msgs = Messages(2)
    info = msgs.camera_info(frame_stamp(frames[0]), camera)
    info.k[0] = np.nan
    bag = write_bag(dataset, frames[:2], tmp_path / "run", camera_info=False,
                    extra={INFO_TOPIC: [info]})
    with pytest.raises(InputError, match=f"^{bag}: camera_info topic {INFO_TOPIC}: K must be "
                                         "finite numbers"):
        load_rosbag(bag)


def test_a_bag_file_that_is_a_named_pipe_is_refused_not_waited_on(tmp_path):
    """A ROS 2 bag folder whose storage file is a FIFO: one error naming it, at once (a
    reader opening it would wait for a writer for ever)."""
    import os

    from slamreloc.datasets.rosbag import load_rosbag
    from slamreloc.errors import InputError

    bag = tmp_path / "bag"
    bag.mkdir()
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    os.mkfifo(bag / "bag_0.db3")
    with pytest.raises(InputError, match="bag_0.db3: ROS bag file is not a regular file"):
        load_rosbag(bag)


def test_localize_and_view_read_a_bag_as_the_other_commands_do(scene, tmp_path, tiny_map):
    """Attack round 17: `localize` on a bag of two image topics asked for `--topic image=`,
    then refused it ("'localize' reads no dataset", Q2); `view --dataset` refused a ROS 1
    bag as "a file, not a folder" (Q11). Both read the bag as every command does."""
    dataset, frames = scene
    msgs = Messages(2)
    second = [msgs.raw(frame_stamp(f), read_image(f.image_path), "rgb8") for f in frames[:3]]
    bag = write_bag(dataset, frames[:3], tmp_path / "two", extra={"/cam2/image_raw": second})
    code, err = run_cli(["localize", str(tiny_map), str(bag), "--method", "matching"])
    assert code == 2 and "--topic image=NAME" in err.splitlines()[-1], err
    code, err = run_cli(["--topic", "image=/cam2/image_raw", "--topic",
                         "camera_info=/cam/color/camera_info", "localize", str(tiny_map),
                         str(bag), "--method", "matching"])
    assert code == 0, err
    ros1 = write_bag(dataset, frames[:3], tmp_path / "run.bag", version=1)
    code, err = run_cli(["view", str(tiny_map), "--dataset", str(ros1), "--port", "0"])
    last = err.strip().splitlines()[-1]  # the map's frames are not the bag's: refused for that
    assert code == 2 and last == (f"error: --dataset {ros1}: holds none of the map's 2 frames "
                                  "(such as 'seq-01/frame-000000'): not the dataset it was built "
                                  "from"), err
