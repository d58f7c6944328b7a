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

from slamreloc.datasets import Dataset, read_frame_depth
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
    depth = read_frame_depth(frame, dataset.depth_units_per_metre)
    return depth_in_image(depth, cam, frame.depth_camera, frame.rgb_from_depth)


def depth_in_image(depth: np.ndarray, camera: Camera, depth_camera: Camera | None,
                   rgb_from_depth: Rigid3 | None) -> np.ndarray:
    """Depth (metres, 0 = none) in the pinhole pixels of the RGB `camera`: registered depth
    (`depth_camera` None) with the lens distortion undone, depth of its own camera (any pixel
    size) warped with `rgb_from_depth` (identity where None)."""
    if depth_camera is None:  # registered: into the pinhole pixels that the keypoints
        return camera.undistort_image(depth)  # are undistorted into
    return warp_depth(depth, camera_of_depth(camera, depth.shape, depth_camera),
                      rgb_from_depth or Rigid3.identity(), camera)


def keypoint_points(keypoints: np.ndarray, depth: np.ndarray, camera: Camera) -> np.ndarray:
    """(N, 3) float64 points of keypoints (pinhole pixels of `camera`) in that camera's frame
    (metres), from depth registered to it (metres along z, 0 = none); NaN rows where the
    depth is missing or at a depth edge (3x3 neighbourhood spread > 3 % of the depth)."""
    h, w = depth.shape
    u = np.clip(np.round(keypoints[:, 0]).astype(int), 1, w - 2)
    v = np.clip(np.round(keypoints[:, 1]).astype(int), 1, h - 2)
    win = np.stack([depth[v + dv, u + du] for dv in (-1, 0, 1) for du in (-1, 0, 1)], axis=1)
    z = depth[v, u].astype(np.float64)
    ok = (win.min(axis=1) > 0) & (win.max(axis=1) - win.min(axis=1) < 0.03 * z)
    pts = np.column_stack([(keypoints[:, 0] - camera.cx) / camera.fx * z,
                           (keypoints[:, 1] - camera.cy) / camera.fy * z, z])
    pts[~ok] = np.nan
    return pts


def keypoint_points_from(keypoints: np.ndarray, depth: np.ndarray, camera: Camera,
                         depth_camera: Camera | None, rgb_from_depth: Rigid3 | None,
                         iterations: int = 3, max_px: float = 1.5) -> np.ndarray:
    """`keypoint_points` for depth as a frame holds it (`FrameData`): registered depth
    (`depth_camera` None) through `depth_in_image`; depth of its own camera without warping
    the whole map: each keypoint's ray is intersected with the depth surface by fixed-point
    iteration (the point on the ray at depth z, seen by the depth camera, reads a depth there,
    which gives the next z), kept where the last step lands within `max_px` pixels of the
    keypoint and the depth camera's 3x3 neighbourhood spreads less than 3 %. (N, 3) float64
    metres in the RGB camera's frame; NaN rows where no depth is found."""
    if depth_camera is None:
        return keypoint_points(keypoints, depth_in_image(depth, camera, None, None), camera)
    rgb_from_depth = rgb_from_depth or Rigid3.identity()
    depth_from_rgb = rgb_from_depth.inverse()
    cam_d = camera_of_depth(camera, depth.shape, depth_camera)
    h, w = depth.shape
    rays = np.column_stack([(keypoints[:, 0] - camera.cx) / camera.fx,
                            (keypoints[:, 1] - camera.cy) / camera.fy, np.ones(len(keypoints))])
    z = np.full(len(keypoints), 2.0)
    ok = np.ones(len(keypoints), bool)
    for _ in range(iterations):
        uv = project(depth_from_rgb.transform(rays * z[:, None]), *cam_d.params())
        u = np.clip(np.round(uv[:, 0]).astype(int), 1, w - 2)
        v = np.clip(np.round(uv[:, 1]).astype(int), 1, h - 2)
        zd = depth[v, u].astype(np.float64)
        ok = ((zd > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1)
              & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1))
        q = rgb_from_depth.transform(np.column_stack([(u - cam_d.cx) / cam_d.fx * zd,
                                                      (v - cam_d.cy) / cam_d.fy * zd, zd]))
        z = np.where(ok & (q[:, 2] > 0.05), q[:, 2], z)
    lands = project(q, camera.fx, camera.fy, camera.cx, camera.cy)
    win = np.stack([depth[v + dv, u + du] for dv in (-1, 0, 1) for du in (-1, 0, 1)], axis=1)
    ok &= ((win.min(axis=1) > 0) & (win.max(axis=1) - win.min(axis=1) < 0.03 * zd)
           & (np.linalg.norm(lands - keypoints, axis=1) <= max_px))
    points = rays * z[:, None]
    points[~ok] = np.nan
    return points


def registered_depths(dataset: Dataset, frames: list[Frame]) -> list[np.ndarray] | None:
    """Depth maps of `frames` in their RGB pixels (registered, or warped with the rig
    calibration); None when no frame has depth."""
    if not any(f.depth_path is not None for f in frames):
        return None
    return [frame_depth(f, dataset) for f in frames]
