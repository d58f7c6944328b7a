"""Round 26 (F4, F5, F7): ROS bag poses whose frames are ambiguous are refused, not composed
one way silently. A pose topic whose messages name different child frames (F4) or different
world frames in header.frame_id (F5) is not one trajectory; a /tf_static whose frames are no
tree (a frame given two parents, or a loop: two chains between two frames, F7) does not say
which chain holds. Each is one error line naming the bag, the topic or /tf_static and the
frames; the consistent forms (an empty frame_id on every message, a frame spelled with and
without its leading slash, the same static transform twice) still load."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from slamreloc.datasets import load_dataset
from slamreloc.datasets.rosbag import BagTopics, bag_trajectory, parse_topics, set_topics
from slamreloc.errors import InputError
from slamreloc.geometry import Rigid3
from tests.rosbag_support import (  # noqa: F401 - automatic_topics: a fixture
    automatic_topics,
    first_test_frames,
    BASE_FROM_MOUNT,
    CAM,
    CAM_FROM_BODY,
    MOUNT_FROM_CAM,
    Messages,
    frame_stamp,
    static_tf,
    write_bag,
)
from tests.test_fuzz_inputs import _tiny_map
from tests.test_input_leftovers import one_error_line

N_FRAMES = 4
CAM_FROM_BASE = (BASE_FROM_MOUNT @ MOUNT_FROM_CAM).inverse()


@pytest.fixture(scope="module")
def scene(scene_dir):
    return first_test_frames(scene_dir, N_FRAMES)


@pytest.fixture(scope="module")
def tiny_map(tmp_path_factory) -> Path:
    return _tiny_map(tmp_path_factory.mktemp("round26_bags") / "map")


def bag_name(tmp_path: Path, version: int) -> Path:
    return tmp_path / ("run.bag" if version == 1 else "run")


def evaluate_argv(tiny_map: Path, bag: Path, report: Path, *topics: str) -> list[str]:
    options = [arg for topic in topics for arg in ("--topic", topic)]
    return [*options, "evaluate", str(tiny_map), str(bag), "--report", str(report),
            "--method", "matching"]


def assert_true_poses(bag: Path, frames) -> None:
    """The bag loads with each frame's pose the scene's (within float noise)."""
    loaded = load_dataset(bag).frames("all")
    assert len(loaded) == len(frames)
    for got, frame in zip(loaded, frames):
        assert np.abs(got.world_from_cam.matrix() - frame.world_from_cam.matrix()).max() < 1e-9


# --- F4 / F5: one pose topic, one child frame, one world frame ---------------------------------

def pose_message(msgs: Messages, kind: str, stamp: float, parent: str, child: str,
                 world_from_cam: Rigid3):
    """A pose message of `kind` of frame `child` (CAM: the camera; "body": the rig's body, whose
    /tf_static link to the camera is `static_tf`'s) in world frame `parent`."""
    pose = world_from_cam @ (CAM_FROM_BODY if child.strip("/") == "body" else Rigid3.identity())
    if kind == "odometry":
        return msgs.odometry(stamp, parent, child, pose)
    if kind == "transform":
        return msgs.transform(stamp, parent, child, pose)
    return msgs.pose_stamped(stamp, parent, pose)


TOPICS = {"odometry": "/odom", "transform": "/odom_tf", "pose": "/pose"}


def frames_bag(scene, path: Path, kind: str, parents: list[str], children: list[str],
               version: int = 2) -> Path:
    """A bag of the scene's frames whose pose topic (of `kind`, TOPICS') gives frame i's pose
    in world frame parents[i] as the pose of frame children[i], with the rig on /tf_static."""
    dataset, frames = scene
    msgs = Messages(version)
    poses = [pose_message(msgs, kind, frame_stamp(f), parent, child, f.world_from_cam)
             for f, parent, child in zip(frames, parents, children)]
    return write_bag(dataset, frames, path, version, poses=None, extra={TOPICS[kind]: poses})


@pytest.mark.parametrize("version", [1, 2])
def test_a_child_frame_changing_mid_topic_is_refused(scene, tmp_path, tiny_map, version):
    """F4: /odom gives the body's pose, then the camera's: each would need its own /tf_static
    chain, and the last message's was used for all (11 cm and a turn off)."""
    bag = frames_bag(scene, bag_name(tmp_path, version), "odometry", ["map"] * N_FRAMES,
                     ["body", "body", CAM, CAM], version)
    expected = (f"{bag}: pose /odom: messages 0 and 2 have different child_frame_id ('body' "
                "and 'cam'): the poses of one topic must be of one frame in one world frame")
    with pytest.raises(InputError) as err:
        load_dataset(bag)
    assert str(err.value) == expected
    with pytest.raises(InputError) as err:  # `slam --odometry topic:/odom`'s trajectory
        bag_trajectory(bag, "/odom")
    assert str(err.value) == expected
    report = tmp_path / "r.json"
    assert one_error_line(evaluate_argv(tiny_map, bag, report)) == f"error: {expected}"
    assert not report.exists()


@pytest.mark.filterwarnings("ignore:.*no pose topic chosen")  # the dataset's: no poses
def test_slam_odometry_topic_with_two_child_frames_is_refused(scene, tmp_path, tiny_map):
    """F4 through `slam --odometry topic:NAME` alone: a TransformStamped topic (never chosen
    as the dataset's poses) whose child frame changes is refused by the odometry's reader."""
    bag = frames_bag(scene, tmp_path / "run", "transform", ["map"] * N_FRAMES,
                     [CAM, CAM, CAM, "body"])
    report = tmp_path / "r.json"
    line = one_error_line(["slam", str(bag), "--map", str(tiny_map), "--report", str(report),
                           "--odometry", "topic:/odom_tf"])
    assert line == (f"error: {bag}: pose /odom_tf: messages 0 and 3 have different "
                    "child_frame_id ('cam' and 'body'): the poses of one topic must be of one "
                    "frame in one world frame")
    assert not report.exists()


@pytest.mark.parametrize("kind", ["pose", "odometry", "transform"])
def test_a_world_frame_changing_mid_topic_is_refused(scene, tmp_path, tiny_map, kind):
    """F5: poses in `map`, then in `odom` (5 m away): two worlds are not one trajectory, and
    interpolation across the switch would mix them."""
    bag = frames_bag(scene, tmp_path / "run", kind, ["map", "map", "map", "odom"],
                     [CAM] * N_FRAMES)
    topic = TOPICS[kind]
    expected = (f"{bag}: pose {topic}: messages 0 and 3 have different header.frame_id ('map' "
                "and 'odom'): the poses of one topic must be of one frame in one world frame")
    set_topics(parse_topics([f"pose={topic}"]))
    with pytest.raises(InputError) as err:
        load_dataset(bag)
    assert str(err.value) == expected
    report = tmp_path / "r.json"
    line = one_error_line(evaluate_argv(tiny_map, bag, report, f"pose={topic}"))
    assert line == f"error: {expected}"
    assert not report.exists()


def test_an_empty_world_frame_against_a_named_one_is_refused(scene, tmp_path):
    """An empty frame_id is a frame id like any other: '' then 'map' is two."""
    bag = frames_bag(scene, tmp_path / "run", "pose", ["", "", "map", "map"], [CAM] * N_FRAMES)
    with pytest.raises(InputError, match=r"pose /pose: messages 0 and 2 have different "
                                         r"header.frame_id \('' and 'map'\)"):
        load_dataset(bag)


@pytest.mark.parametrize("kind, parents, children", [
    ("pose", [""] * N_FRAMES, [CAM] * N_FRAMES),  # no world frame named, on every message
    ("odometry", ["map", "/map", "map", "/map"], ["body", "/body", "body", "/body"]),
    ("odometry", ["odom"] * N_FRAMES, [CAM] * N_FRAMES),
])
def test_consistent_frames_load_as_before(scene, tmp_path, kind, parents, children):
    """The documented forms load: an empty frame_id throughout, one frame spelled with and
    without its leading slash (tf2's rule: the same frame), the body composed to the camera."""
    _, frames = scene
    assert_true_poses(frames_bag(scene, tmp_path / "run", kind, parents, children), frames)


# --- F7: /tf_static is a tree ------------------------------------------------------------------

def tf_bag(scene, path: Path, static: list[tuple[str, str, Rigid3]],
           also_dynamic: list[tuple[str, str, Rigid3]] = ()) -> Path:
    """A bag of the scene's frames posed by /tf map -> base (the rig's base), with `static`
    (parent, child, parent_from_child) on /tf_static and `also_dynamic` on /tf with each
    pose."""
    dataset, frames = scene
    msgs = Messages(2)
    t0 = frame_stamp(frames[0])
    dynamic = [msgs.tf([msgs.transform(frame_stamp(f), "map", "base",
                                       f.world_from_cam @ CAM_FROM_BASE)]
                       + [msgs.transform(frame_stamp(f), parent, child, pose)
                          for parent, child, pose in also_dynamic]) for f in frames]
    transforms = msgs.tf([msgs.transform(t0, parent, child, pose)
                          for parent, child, pose in static])
    return write_bag(dataset, frames, path, poses=None, static=False,
                     extra={"/tf": dynamic, "/tf_static": [transforms]})


RIG = [("base", "mount", BASE_FROM_MOUNT), ("mount", CAM, MOUNT_FROM_CAM)]
SHIFTED = Rigid3(np.eye(3), np.array([0.3, 0.0, 0.0]))


@pytest.mark.parametrize("extra, problem", [
    # the attack: base -> cam directly besides base -> mount -> cam, 0.3 m apart
    ([("base", CAM, BASE_FROM_MOUNT @ MOUNT_FROM_CAM @ SHIFTED)],
     "/tf_static gives frame cam two parents (mount and base): a tf tree gives each frame "
     "one parent"),
    # the same chain, agreeing: still two parents, which tf2 does not build either
    ([("base", CAM, BASE_FROM_MOUNT @ MOUNT_FROM_CAM)],
     "/tf_static gives frame cam two parents (mount and base)"),
    # a loop: cam -> base closes base -> mount -> cam, and gives base (/tf: map's child) a
    # second parent
    ([(CAM, "base", MOUNT_FROM_CAM.inverse() @ BASE_FROM_MOUNT.inverse())],
     "/tf_static and /tf give frame base two parents (cam and map)"),
    # a pair given both ways, agreeing: a loop of two frames (tf2 refuses it too)
    ([("mount", "base", BASE_FROM_MOUNT.inverse())],
     "/tf_static and /tf give frame base two parents (mount and map)"),
    # ... where the reversed child has a parent already: two parents
    ([(CAM, "mount", MOUNT_FROM_CAM.inverse())],
     "/tf_static gives frame mount two parents (base and cam)"),
], ids=["second-parent", "second-parent-agreeing", "loop", "both-ways", "both-ways-parented"])
def test_a_static_frame_with_two_chains_is_refused(scene, tmp_path, tiny_map, extra, problem):
    """F7: the pose's frame `base` reaches the camera by two /tf_static chains; the one of
    fewest transforms was taken silently."""
    bag = tf_bag(scene, tmp_path / "run", RIG + extra)
    set_topics(parse_topics(["pose=tf:map:base"]))
    with pytest.raises(InputError) as err:
        load_dataset(bag)
    assert str(err.value).startswith(f"{bag}: {problem}")
    assert "\n" not in str(err.value)
    report = tmp_path / "r.json"
    line = one_error_line(evaluate_argv(tiny_map, bag, report, "pose=tf:map:base"))
    assert line.startswith(f"error: {bag}: {problem}")
    assert not report.exists()


def test_a_static_tree_loads_and_a_repeated_transform_is_read_once(scene, tmp_path):
    """The rig's tree (base -> mount -> cam, cam -> body) loads, with the same transform given
    again (latched /tf_static repeats), by /tf and by odometry of the body."""
    dataset, frames = scene
    set_topics(parse_topics(["pose=tf:map:base"]))
    assert_true_poses(tf_bag(scene, tmp_path / "tf", RIG + RIG[:1]), frames)
    set_topics(BagTopics())
    msgs = Messages(1)
    bag = write_bag(dataset, frames, tmp_path / "odom.bag", 1, poses="odometry", static=False,
                    extra={"/tf_static": static_tf(msgs, frame_stamp(frames[0])) * 2})
    assert_true_poses(bag, frames)


@pytest.mark.parametrize("static, dynamic, problem", [
    (RIG, [("base", CAM, BASE_FROM_MOUNT @ MOUNT_FROM_CAM @ SHIFTED)],
     "/tf_static and /tf give frame cam two parents (mount and base)"),
    ([("base", CAM, BASE_FROM_MOUNT @ MOUNT_FROM_CAM @ SHIFTED)], RIG,
     "/tf_static and /tf give frame cam two parents (base and mount)"),
], ids=["static-chain", "dynamic-chain"])
def test_a_frame_with_parents_on_tf_and_tf_static_is_refused(scene, tmp_path, static, dynamic,
                                                            problem):
    """Round 27, G2: one parent of the camera on /tf_static and another on /tf (0.3 m apart):
    the static chain was taken without a word. /tf and /tf_static make one tree."""
    bag = tf_bag(scene, tmp_path / "run", static, dynamic)
    set_topics(parse_topics(["pose=tf:map:base"]))
    with pytest.raises(InputError) as err:
        load_dataset(bag)
    assert str(err.value) == f"{bag}: {problem}: a tf tree gives each frame one parent"


@pytest.mark.parametrize("static, dynamic, problem", [
    # a loop of two frames apart from the rig, on /tf_static alone while /tf is there too
    (RIG + [("x", "y", SHIFTED), ("y", "x", SHIFTED.inverse())], [],
     "/tf_static has a loop (x -> y -> x)"),
    # map -> base on /tf, base -> mount -> cam on /tf_static, cam -> map on /tf: one loop
    # through both topics, each frame with one parent
    (RIG, [(CAM, "map", (BASE_FROM_MOUNT @ MOUNT_FROM_CAM).inverse())],
     "/tf and /tf_static hold a loop (cam -> map -> base -> mount -> cam)"),
], ids=["static-loop", "loop-through-both"])
def test_a_tf_loop_names_the_topics_of_its_transforms(scene, tmp_path, static, dynamic,
                                                      problem):
    """A loop in the tree /tf and /tf_static make is refused naming the topics its own
    transforms come from, not every topic of the tree."""
    bag = tf_bag(scene, tmp_path / "run", static, dynamic)
    set_topics(parse_topics(["pose=tf:map:base"]))
    with pytest.raises(InputError) as err:
        load_dataset(bag)
    assert str(err.value) == f"{bag}: {problem}: a tf tree has none"
