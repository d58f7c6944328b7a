"""ROS CameraInfo's binning_x / binning_y and roi (attack round 28, J6): K, width and height are
the full-resolution calibration's, the image delivered is the roi's window (all zero: the full
image) divided by the binning. A bag's camera is that image's; a CameraInfo whose window does
not fit, does not divide by the binning, or gives images of another size is refused in one
line naming the bag and the topic."""

from __future__ import annotations

from dataclasses import replace
from functools import cache

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from slamreloc.datasets import load_dataset
from slamreloc.datasets.rosbag import camera_from_info
from slamreloc.errors import InputError
from slamreloc.geometry import project
from slamreloc.types import Camera
from tests.fuzzing import fuzz_settings, run_cli
from tests.rosbag_support import (  # noqa: F401 - automatic_topics: a fixture
    INFO_TOPIC,
    Messages,
    automatic_topics,
    first_test_frames,
    frame_stamp,
    full_resolution,
    write_bag,
)
from tests.test_fuzz_inputs import _tiny_map

N_FRAMES = 3


@pytest.fixture(scope="module")
def scene(scene_dir):
    return first_test_frames(scene_dir, N_FRAMES)


@pytest.fixture(scope="module")
def tiny_map(tmp_path_factory):
    return _tiny_map(tmp_path_factory.mktemp("window") / "map")


@cache
def messages(version: int) -> Messages:
    return Messages(version)


def window_bag(scene, path, version: int, full: Camera, binning=(0, 0), roi=(0, 0, 0, 0),
               size=None):
    """A bag of the scene's frames (images, poses) whose one CameraInfo per frame is of the
    full-resolution camera `full` with `binning`, `roi` and `size` (width, height; default
    full's, (0, 0): not given)."""
    dataset, frames = scene
    msgs = messages(version)
    info = [msgs.camera_info(frame_stamp(f), full, binning=binning, roi=roi, size=size)
            for f in frames]
    path = path.with_suffix(".bag") if version == 1 else path
    return write_bag(dataset, frames, path, version=version, depth=False, camera_info=False,
                     extra={INFO_TOPIC: info})


def close_cameras(a: Camera, b: Camera) -> bool:
    return ((a.width, a.height, a.model) == (b.width, b.height, b.model)
            and np.allclose(a.params(), b.params(), rtol=0, atol=1e-9)
            and np.allclose(a.distortion, b.distortion, rtol=0, atol=1e-12))


LENS = ("OPENCV", (-0.05, 0.01, 0.001, -0.002))


@pytest.mark.parametrize("version, binning, offset, window, size, lens", [
    (1, (2, 2), (0, 0), False, None, None),        # 640x480 calibration binned 2x2
    (2, (2, 2), (0, 0), False, (0, 0), None),      # the same, width/height not given
    (2, (0, 0), (100, 80), True, (640, 480), None),  # a 320x240 window at (100, 80)
    (1, (0, 0), (100, 80), True, (0, 0), LENS),    # the same, size not given, a lens
    (2, (2, 2), (40, 30), True, (1000, 600), LENS),  # a 640x480 window binned to 320x240
    (1, (4, 3), (8, 6), True, (0, 0), None),       # unequal binning in a window
    (2, (1, 1), (0, 0), True, None, None),         # binning 1 and a roi of the whole image
])
def test_a_binned_or_windowed_camera_info_gives_the_camera_of_the_images(
        scene, tmp_path, version, binning, offset, window, size, lens):
    """The bag's camera is the scene's true camera of its 320x240 images (to 1e-9), though
    the CameraInfo holds the full-resolution calibration; the poses are the scene's."""
    dataset, frames = scene
    true = frames[0].camera if lens is None else replace(frames[0].camera, model=lens[0],
                                                         distortion=lens[1])
    full = full_resolution(true, binning, offset, None if size in (None, (0, 0)) else size)
    b = [v or 1 for v in binning]
    roi = (*offset, true.width * b[0], true.height * b[1]) if window else (0, 0, 0, 0)
    bag = window_bag(scene, tmp_path / "run", version, full, binning, roi, size)
    loaded = load_dataset(bag).frames()
    assert len(loaded) == len(frames)
    for f, g in zip(frames, loaded):
        assert close_cameras(g.camera, true), (g.camera, true)
        assert np.abs(g.world_from_cam.matrix() - f.world_from_cam.matrix()).max() < 1e-9
    # a scene point lands on the same pixel through the bag's camera as through the true one
    point = np.array([[0.3, -0.2, 2.0]])
    assert np.allclose(loaded[0].camera.distort(project(point, *loaded[0].camera.params())),
                       true.distort(project(point, *true.params())), rtol=0, atol=1e-9)


@fuzz_settings(200)
@given(bx=st.integers(0, 4), by=st.integers(0, 4), x0=st.integers(0, 200),
       y0=st.integers(0, 200), w=st.integers(64, 400), h=st.integers(48, 300),
       margin=st.integers(0, 50), given_size=st.booleans(),
       f=st.floats(100, 1000), aspect=st.floats(0.8, 1.25),
       tx=st.floats(0.2, 0.8), ty=st.floats(0.2, 0.8),
       xy=st.tuples(st.floats(-0.3, 0.3), st.floats(-0.3, 0.3)), depth=st.floats(0.5, 20))
def test_the_reduced_camera_projects_where_the_full_resolution_camera_does(
        bx, by, x0, y0, w, h, margin, given_size, f, aspect, tx, ty, xy, depth):
    """The definition of the camera of a binned, windowed image: a delivered pixel u_b sums
    the full-resolution pixels x_offset + b u_b ... x_offset + b u_b + b - 1, so its centre
    (pixel centres at integer coordinates, OpenCV's convention) is at u_f = x_offset + b u_b
    + (b - 1) / 2. A point the full-resolution camera projects to u_f must therefore project
    through the reduced camera to u_b = (u_f - x_offset - (b - 1) / 2) / b (v likewise with
    y_offset, binning_y). (Pinhole here: lens distortion, in normalized coordinates, is
    the same for both; the bag test above checks a lens.) A CameraInfo said to deliver one
    pixel more than the images have is refused."""
    b = (bx or 1, by or 1)
    window = (w * b[0], h * b[1])
    full_size = (x0 + window[0] + margin, y0 + window[1] + margin)
    full = Camera(*full_size, f, f * aspect, x0 + tx * window[0], y0 + ty * window[1])
    info = messages(2).camera_info(0.0, full, binning=(bx, by), roi=(x0, y0, *window),
                                   size=None if given_size else (0, 0))
    reduced = camera_from_info(info, (w, h), "bag")
    point = np.array([[xy[0] * depth, xy[1] * depth, depth]])
    u_f = project(point, *full.params())[0]
    u_b = project(point, *reduced.params())[0]
    expected = (u_f - np.array([x0, y0]) - (np.array(b) - 1) / 2) / np.array(b)
    assert np.allclose(u_b, expected, rtol=0, atol=1e-7), (u_b, expected)
    assert (reduced.width, reduced.height) == (w, h)
    with pytest.raises(InputError, match=rf"^bag: CameraInfo gives {w}x{h} images \(the "):
        camera_from_info(info, (w + 1, h), "bag")


PLAIN = Camera(320, 240, 262.5, 262.5, 159.5, 119.5)
FULL = Camera(640, 480, 525.0, 525.0, 319.5, 239.5)


@pytest.mark.parametrize("full, binning, roi, size, problem", [
    (FULL, (0, 0), (400, 80, 320, 240), None,
     "CameraInfo's roi (320x240 at (400, 80)) does not fit its 640x480 image"),
    (FULL, (3, 3), (0, 0, 0, 0), None,
     r"CameraInfo's window (its full 640x480 image with binning_x 3, binning_y 3) is not a "
     "whole number of binned pixels: 640x480 does not divide by 3x3"),
    (FULL, (2, 2), (100, 80, 641, 480), (0, 0),
     "CameraInfo's window (the 641x480 roi at (100, 80) with binning_x 2, binning_y 2) is not "
     "a whole number of binned pixels: 641x480 does not divide by 2x2"),
    (PLAIN, (2, 2), (0, 0, 0, 0), None,  # images of the CameraInfo's size, binned: 160x120
     "CameraInfo gives 160x120 images (its full 320x240 image with binning_x 2, binning_y 2), "
     "the images are 320x240"),
    (FULL, (0, 0), (100, 80, 300, 240), (0, 0),
     "CameraInfo gives 300x240 images (the 300x240 roi at (100, 80)), the images are 320x240"),
    (FULL, (0, 0), (100, 80, 320, 0), None,
     "CameraInfo's roi is 320x0: a window has a width and a height, or neither (0x0 at (0, 0): "
     "the full image)"),
    (FULL, (0, 0), (100, 80, 0, 0), (0, 0),
     "CameraInfo's roi at (100, 80) has no size (0x0 is the full image, at (0, 0))"),
])
def test_a_window_that_does_not_give_the_images_is_refused(scene, tmp_path, full, binning,
                                                           roi, size, problem):
    bag = window_bag(scene, tmp_path / "run", 2, full, binning, roi, size)
    with pytest.raises(InputError) as err:
        load_dataset(bag)
    assert str(err.value) == f"{bag}: camera_info topic {INFO_TOPIC}: {problem}"


def test_plain_camera_info_of_another_size_keeps_its_message(scene, tmp_path):
    bag = window_bag(scene, tmp_path / "run", 1, FULL)
    with pytest.raises(InputError) as err:
        load_dataset(bag)
    assert str(err.value) == (f"{bag}: camera_info topic {INFO_TOPIC}: CameraInfo is for "
                              "640x480 images, the images are 320x240")


def test_the_cli_refuses_a_binning_that_does_not_give_the_images(scene, tmp_path, tiny_map):
    """The attack's bag: width/height of the images and binning 2 (160x120 images): one error
    line, exit 2, no report."""
    bag = window_bag(scene, tmp_path / "run", 1, PLAIN, binning=(2, 2))
    report = tmp_path / "report.json"
    code, err = run_cli(["evaluate", str(tiny_map), str(bag), "--report", str(report),
                         "--method", "matching"])
    assert "Traceback" not in err, err
    errors = [line for line in err.splitlines() if line.startswith("error:")]
    assert code == 2 and len(errors) == 1 and err.splitlines()[-1] == errors[0], err
    assert errors[0] == (f"error: {bag}: camera_info topic {INFO_TOPIC}: CameraInfo gives "
                         "160x120 images (its full 320x240 image with binning_x 2, "
                         "binning_y 2), the images are 320x240")
    assert not report.exists()
