"""Depth in the RGB camera's pixels: warping unregistered depth with the rig calibration."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from slamreloc.datasets import load_dataset, read_depth
from slamreloc.geometry import Rigid3, axis_angle_to_matrix
from slamreloc.rgbd import frame_depth, registered_depths, warp_depth
from slamreloc.types import Camera
from tests.conftest import STAIRS, needs

DEPTH_CAM = Camera(160, 120, 146.25, 146.25, 80.0, 60.0)  # 7-Scenes' depth camera, 1/4 size
RGB_CAM = Camera(160, 120, 131.25, 131.25, 80.0, 60.0)  # and its RGB camera


def plane_depth(cam: Camera, normal: np.ndarray, offset: float) -> np.ndarray:
    """Depth (z, metres) of the plane normal . X = offset seen by `cam` (camera frame)."""
    u, v = np.meshgrid(np.arange(cam.width), np.arange(cam.height))
    rays = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u, float)], -1)
    return (offset / (rays @ normal)).astype(np.float32)


@given(st.lists(st.floats(-0.035, 0.035), min_size=3, max_size=3),
       st.lists(st.floats(-0.05, 0.05), min_size=3, max_size=3),
       st.floats(-0.4, 0.4), st.floats(1.0, 3.0))
@settings(max_examples=30, deadline=None)
def test_warped_depth_is_the_plane_the_rgb_camera_sees(rotvec, shift, tilt, distance):
    """A plane seen by the depth camera, warped into an RGB camera up to 2 deg / 5 cm away:
    every RGB pixel well inside the view gets the depth of its own ray's intersection."""
    normal = np.array([np.sin(tilt), 0.0, np.cos(tilt)])
    rgb_from_depth = Rigid3(axis_angle_to_matrix(np.array(rotvec)), np.array(shift))
    got = warp_depth(plane_depth(DEPTH_CAM, normal, distance), DEPTH_CAM, rgb_from_depth,
                     RGB_CAM)
    n_rgb = rgb_from_depth.rotation @ normal  # the plane in the RGB camera's frame
    want = plane_depth(RGB_CAM, n_rgb, distance + n_rgb @ rgb_from_depth.translation)
    inner = np.s_[20:-20, 20:-20]
    filled = got[inner] > 0
    assert filled.mean() > 0.97  # the depth camera's finer pixels leave no holes
    rel = np.abs(got[inner][filled] - want[inner][filled]) / want[inner][filled]
    assert np.percentile(rel, 99) < 0.01  # within a pixel's rounding on the slope


def test_nearest_surface_wins_and_identity_keeps_the_depth():
    depth = np.full((120, 160), 3.0, np.float32)
    depth[50:70, 70:90] = 1.0  # a box in front of a wall
    depth[0:10, 0:10] = 0.0  # no reading
    same = warp_depth(depth, DEPTH_CAM, Rigid3.identity(), DEPTH_CAM)
    np.testing.assert_allclose(same, depth)
    moved = warp_depth(depth, DEPTH_CAM, Rigid3(np.eye(3), np.array([-0.05, 0, 0])), RGB_CAM)
    # seen from 5 cm to the side, the box still covers its centre and hides the wall there
    assert moved[60, 77] == np.float32(1.0)
    assert np.all(moved[moved > 0] >= 1.0 - 1e-6)


@needs(STAIRS)
def test_7scenes_depth_is_warped_into_the_rgb_image(scene_dir):
    ds = load_dataset(STAIRS)
    frames = ds.frames("all")[:2]
    depths = registered_depths(ds, frames)
    raw = read_depth(frames[0].depth_path)
    cam = frames[0].camera
    assert depths[0].shape == (cam.height, cam.width) and depths[0].dtype == np.float32
    assert (depths[0] > 0).mean() > 0.5 and not np.array_equal(depths[0], raw)
    # the depth camera's narrower view leaves a border of the RGB image without depth
    assert (depths[0][:, :10] > 0).mean() < (depths[0][:, 300:340] > 0).mean()
    synthetic = load_dataset(scene_dir)  # registered: read as it is
    f = synthetic.frames("all")[0]
    np.testing.assert_array_equal(frame_depth(f, synthetic), read_depth(f.depth_path))
