"""Depth maps: the camera that took them, their back-projection to points, and depth in the
RGB camera's pixels (registered depth as it is, unregistered depth warped).

A frame's depth is either registered to its image (`Frame.depth_camera` None: the RGB camera,
scaled to the depth map, took it) or comes from a camera of its own (`Frame.depth_camera`,
`Frame.rgb_from_depth`). 7-Scenes' depth comes from the Kinect's other camera (585 px focal
length at 640x480, not registered to the RGB images). With the rig calibration
(`Frame.rgb_from_depth`) each depth pixel is back-projected, moved into the RGB camera and
splatted into the RGB image (nearest surface wins), the "calibrated depth" that DSAC* and ACE
use for 7-Scenes. Scene points of RGB keypoints follow the package's convention for 7-Scenes:
the dataset's pose is the RGB camera's world_from_cam, so a keypoint's label is
world_from_cam * (its depth in the RGB camera)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slamreloc.datasets import Dataset, read_depth
from slamreloc.geometry import Rigid3, project
from slamreloc.types import Camera, Frame


@dataclass(frozen=True)
class DepthSampling:
    """Back-projection of a depth map: every `stride`-th pixel, depths in [min_m, max_m]."""

    stride: int = 4
    min_m: float = 0.2
    max_m: float = 4.0


def camera_of_depth(camera: Camera, depth_shape: tuple[int, int],
                    depth_camera: Camera | None) -> Camera:
    """The camera in whose pixels a depth map of `depth_shape` (rows, columns) lies: its own
    `depth_camera` where the depth is not registered to the image (7-Scenes: 585, 585, 320,
    240 at 640x480), else the RGB `camera`; either scaled to the depth map's size (pixels)."""
    h, w = depth_shape
    return (camera if depth_camera is None else depth_camera).scaled_to(w, h)


def backproject(depth: np.ndarray, camera: Camera, sampling: DepthSampling) -> np.ndarray:
    """(N, 3) float64 points of a depth map (metres along z) in the frame of the `camera` that
    took it (OpenCV axes: x right, y down, z forward; metres); `camera` in the depth map's
    pixels (its lens distortion, if any, is not applied)."""
    s = sampling.stride
    d = depth[::s, ::s]
    v, u = np.nonzero((d > sampling.min_m) & (d < sampling.max_m))
    z = d[v, u].astype(np.float64)
    x = (u * s - camera.cx) / camera.fx * z
    y = (v * s - camera.cy) / camera.fy * z
    return np.stack([x, y, z], axis=1)


WARP_SAMPLING = DepthSampling(stride=1, min_m=0.2, max_m=8.0)  # every valid depth pixel


def warp_depth(depth: np.ndarray, depth_cam: Camera, rgb_from_depth: Rigid3,
               camera: Camera) -> np.ndarray:
    """(camera.height, camera.width) float32 depth in metres along the RGB camera's z, 0 where
    no depth pixel lands; `depth` (metres) is taken by `depth_cam` (in the depth map's pixels),
    whose pose in the RGB `camera`'s frame is `rgb_from_depth` (metres)."""
    pts = rgb_from_depth.transform(backproject(depth, depth_cam, WARP_SAMPLING))
    pts = pts[pts[:, 2] > 0.05]
    z = pts[:, 2]
    u, v = np.round(project(pts, *camera.params())).astype(np.int64).T
    inside = (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    out = np.full(camera.height * camera.width, np.inf, np.float32)
    np.minimum.at(out, v[inside] * camera.width + u[inside], z[inside].astype(np.float32))
    out[np.isinf(out)] = 0.0
    return out.reshape(camera.height, camera.width)


def frame_depth(frame: Frame, dataset: Dataset) -> np.ndarray:
    """A frame's depth (metres, 0 = invalid) in its RGB camera's pixels; zeros without depth.
    Depth of its own camera (`frame.depth_camera`) is warped with `frame.rgb_from_depth`."""
    cam = frame.camera
    if frame.depth_path is None:
        return np.zeros((cam.height, cam.width), np.float32)
    depth = read_depth(frame.depth_path, dataset.depth_units_per_metre)
    if frame.depth_camera is None:  # registered: into the pinhole pixels that the keypoints
        return cam.undistort_image(depth)  # are undistorted into
    rgb_from_depth = frame.rgb_from_depth or Rigid3.identity()
    return warp_depth(depth, camera_of_depth(cam, depth.shape, frame.depth_camera),
                      rgb_from_depth, cam)


def registered_depths(dataset: Dataset, frames: list[Frame]) -> list[np.ndarray] | None:
    """Depth maps of `frames` in their RGB pixels (registered, or warped with the rig
    calibration); None when no frame has depth."""
    if not any(f.depth_path is not None for f in frames):
        return None
    return [frame_depth(f, dataset) for f in frames]
