"""One rule per kind of value, across the CLI, the files and the wire (issue 43).

A quaternion, wherever a pose is read: pose and trajectory files, COLMAP models, ROS bag
messages and the service's messages all take a unit quaternion within `QUATERNION_NORM_TOL`
(then normalised) and refuse any other, naming where it came from. A camera meeting an image
(`Camera.for_image`): scaled to an image of its aspect ratio, refused for another, in
`localize`, `sfm --camera` and the service."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slamreloc.datasets.colmap_check import _check_image_pose
from slamreloc.datasets.poses import read_poses
from slamreloc.datasets.rosbag import _rigid
from slamreloc.errors import InputError
from slamreloc.geometry import QUATERNION_NORM_TOL, parse_tum_line, quat_to_matrix
from slamreloc.proto import relocalizer_pb2 as pb
from slamreloc.proto.messages import ServiceError, rigid_from_msg
from tests.conftest import REDKITCHEN, needs


class _Xyz:
    def __init__(self, x, y, z, w=None):
        self.x, self.y, self.z, self.w = x, y, z, w


def _readers(q):
    """The rotation each reader makes of quaternion q (x, y, z, w), or the exception."""
    x, y, z, w = (float(v) for v in q)
    out = {}
    calls = {
        "pose file": lambda: parse_tum_line(f"f 0 0 0 {x!r} {y!r} {z!r} {w!r}", "poses.txt")[1],
        "colmap": lambda: _check_image_pose("images.txt", 1, (w, x, y, z, 0.0, 0.0, 0.0)),
        "ros bag": lambda: _rigid(_Xyz(0.0, 0.0, 0.0), _Xyz(x, y, z, w), "bag /pose"),
        "service": lambda: rigid_from_msg(pb.Transform(qx=x, qy=y, qz=z, qw=w), "prior"),
    }
    for name, call in calls.items():
        try:
            out[name] = call()
        except (InputError, ServiceError) as err:
            out[name] = err
    return out


@settings(max_examples=60, deadline=None, derandomize=True, database=None)
@given(q=st.tuples(*[st.floats(-1, 1)] * 4).filter(lambda q: sum(v * v for v in q) > 0.01),
       norm=st.one_of(st.floats(0, 5), st.floats(1 - 2 * QUATERNION_NORM_TOL,
                                                 1 + 2 * QUATERNION_NORM_TOL)))
def test_every_reader_takes_the_same_quaternions(q, norm):
    q = np.asarray(q) / np.linalg.norm(q) * norm
    off = abs(float(np.linalg.norm(q)) - 1)
    if abs(off - QUATERNION_NORM_TOL) < 1e-12:
        return  # on the boundary: rounding of the sum's order decides
    got = _readers(q)
    unit = off <= QUATERNION_NORM_TOL
    for name, result in got.items():
        refused = isinstance(result, Exception)
        assert refused != unit, (name, norm, result)
        if refused:
            assert "quaternion norm" in str(result), (name, result)
    if unit:
        want = quat_to_matrix(q / np.linalg.norm(q))
        for name in ("pose file", "ros bag", "service"):
            assert np.allclose(got[name].rotation, want, atol=1e-12), name


def test_a_pose_file_with_a_quaternion_of_norm_2_is_refused(tmp_path):
    """The example of issue 43: normalised silently before, while the service refused it."""
    path = tmp_path / "poses.txt"
    path.write_text("seq-01/frame-000000 0 0 0 0 0 0 1\nseq-01/frame-000001 0 0 0 0 0 0 2\n")
    with pytest.raises(InputError, match=r"poses.txt:2: quaternion norm 2, not 1"):
        read_poses(path)
    for bad in ("nan", "inf", "0"):  # nan and inf are not numbers to the one text rule
        path.write_text(f"seq-01/frame-000000 0 0 0 0 0 {bad} 0\n")
        with pytest.raises(InputError, match="poses.txt:1: (quaternion|non-numeric pose value)"):
            read_poses(path)
    # four decimals, as TUM's ground truth files are written: within the rule
    path.write_text("1305031102.1753 1.3405 0.6266 1.6575 0.6574 0.6126 -0.2949 -0.3248\n")
    read_poses(path)


@needs(REDKITCHEN)
def test_the_real_pose_files_keep_loading():
    from slamreloc.datasets import load_dataset

    for poses in (None, REDKITCHEN / "sfm_pgt" / "poses.txt"):
        frames = load_dataset(REDKITCHEN, poses).frames("all")
        assert len(frames) == 600 and all(f.world_from_cam is not None for f in frames)


@settings(max_examples=60, deadline=None, derandomize=True, database=None)
@given(cam=st.tuples(st.integers(16, 4096), st.integers(16, 4096)),
       image=st.tuples(st.integers(16, 4096), st.integers(16, 4096)))
def test_every_camera_user_takes_the_same_images(cam, image):
    """The map's default camera and a COLMAP camera string in a request (the service), and
    `Camera.for_image` (localize, sfm): the same sizes scaled, the same refused."""
    from slamreloc.proto.messages import camera_from_msg
    from slamreloc.types import ASPECT_TOL, Camera

    (cw, ch), (w, h) = cam, image
    camera = Camera(cw, ch, 0.8 * cw, 0.8 * cw, cw / 2, ch / 2)
    sx, sy = w / cw, h / ch
    gap = abs(sx - sy) / max(sx, sy)
    if abs(gap - ASPECT_TOL) < 1e-9:
        return  # on the boundary
    same = gap <= ASPECT_TOL
    results = []
    for call in (lambda: camera.for_image(w, h, "camera"),
                 lambda: camera_from_msg(None, w, h, camera),
                 lambda: camera_from_msg(pb.Camera(colmap=camera.colmap_string()), w, h,
                                         camera)):
        try:
            results.append(call())
        except (InputError, ServiceError) as err:
            assert "aspect ratio" in str(err)
            if isinstance(err, ServiceError):
                assert err.kind == pb.BAD_CAMERA
            results.append(None)
    if same:
        assert all(r is not None and (r.width, r.height) == (w, h) for r in results), results
        assert results[1] == results[0]
        assert results[2].params() == pytest.approx(results[0].params())
    else:
        assert results == [None, None, None]


def test_localize_refuses_an_image_of_another_aspect_ratio_than_its_camera(tmp_path):
    """`localize`: the map's camera (64x48) or a --camera string is never stretched onto an
    image of another aspect ratio: that image's error line, exit 2."""
    import cv2

    from tests.fuzzing import run_cli_output
    from tests.test_fuzz_inputs import _tiny_map

    tiny = _tiny_map(tmp_path / "map")
    image = tmp_path / "wide.png"
    cv2.imwrite(str(image), np.random.default_rng(0).integers(0, 255, (36, 64, 3), np.uint8))
    for extra in ([], ["--camera", "PINHOLE 640 480 500 500 320 240"]):
        code, out, err = run_cli_output(["localize", str(tiny), str(image), *extra])
        assert code == 2 and out == "", (out, err)
        lines = err.strip().splitlines()
        assert len(lines) == 1 and str(image) in lines[0] and "aspect ratio" in lines[0], err


def test_a_slam_report_pose_takes_the_same_quaternion_rule(tmp_path):
    """The viewer's `pose: [tx ty tz qx qy qz qw]` of a slam report's event."""
    from slamreloc.viewer.slam_report import read_slam_report

    path = tmp_path / "r.json"
    for q, ok in (([0, 0, 0, 1.0004], True), ([0, 0, 0, 2], False), ([0, 0, 0, 0], False)):
        data = {"ate_rmse_m": 0.1, "events": [{"frame": 0, "kind": "kidnap",
                                               "pose": [1.0, 2.0, 3.0, *q]}]}
        if ok:
            read_slam_report(path, data, [])
        else:
            with pytest.raises(InputError, match=r"r.json: events\[0\].pose: quaternion norm"):
                read_slam_report(path, data, [])


def test_the_default_7scenes_camera_is_not_stretched_onto_other_images(tmp_path):
    import cv2

    from slamreloc.datasets import load_dataset
    from tests.test_fuzz_inputs import make_sevenscenes

    root = make_sevenscenes(tmp_path / "ds")
    (root / "intrinsics.txt").unlink()
    camera = load_dataset(root).frames("all")[0].camera  # 64x48: 7-Scenes' 640x480, scaled
    assert (camera.width, camera.height, camera.fx, camera.cx) == (64, 48, 52.5, 32.0)
    for path in root.glob("seq-*/frame-*.color.*"):
        cv2.imwrite(str(path), np.zeros((36, 64, 3), np.uint8))
    with pytest.raises(InputError,
                       match="default 7-Scenes camera.*intrinsics.txt.*another aspect ratio"):
        load_dataset(root).frames("all")
