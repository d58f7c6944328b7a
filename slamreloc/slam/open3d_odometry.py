"""open3d's multi-scale RGB-D odometry (tensor API), frame to frame. With depth registered to
the image (`depth_camera` None) it uses the hybrid photometric + geometric loss; otherwise
(7-Scenes: depth from another camera) point-to-plane on depth only."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slamreloc.geometry import Rigid3
from slamreloc.rgbd import camera_of_depth
from slamreloc.slam.odometry import Odometry, OdometryStep
from slamreloc.types import Camera


@dataclass(frozen=True)
class Open3dConfig:
    """`depth_camera`: the camera that took the depth where it is not registered to the image
    (`Frame.depth_camera`, any pixel size: scaled to the depth map), None: registered."""

    depth_max_m: float = 4.0  # metres
    iterations: tuple[int, int, int] = (10, 5, 3)  # fine to coarse
    depth_camera: Camera | None = None


class Open3dOdometry(Odometry):
    name = "open3d"

    def __init__(self, config: Open3dConfig = Open3dConfig()):
        self.config = config
        self.reset()

    def reset(self) -> None:
        self._prev, self._pose, self._delta = None, np.eye(4), np.eye(4)

    def step(self, depth, camera: Camera, image=None, timestamp=0.0, index=0) -> OdometryStep:
        import open3d as o3d
        from open3d.t.pipelines import odometry as o3o

        cam = camera_of_depth(camera, depth.shape, self.config.depth_camera)
        d = o3d.core.Tensor(np.ascontiguousarray(depth, dtype=np.float32))
        hybrid = self.config.depth_camera is None and image is not None
        rgb = (image.astype(np.float32) / 255.0 if hybrid
               else np.zeros((*depth.shape, 3), np.float32))
        color = o3d.core.Tensor(np.ascontiguousarray(rgb))
        rgbd = o3d.t.geometry.RGBDImage(o3d.t.geometry.Image(color), o3d.t.geometry.Image(d))
        fitness = None
        if self._prev is not None:
            try:
                res = o3o.rgbd_odometry_multi_scale(
                    rgbd, self._prev, o3d.core.Tensor(cam.K), o3d.core.Tensor(self._delta),
                    1.0, self.config.depth_max_m,
                    [o3o.OdometryConvergenceCriteria(n) for n in self.config.iterations],
                    o3o.Method.Hybrid if hybrid else o3o.Method.PointToPlane)
            except RuntimeError:  # open3d: "Singular 6x6 linear system ... tracking failed"
                res = None
            if res is None:  # no overlap to register on: the health check reports the loss
                self._delta, fitness = np.eye(4), 0.0
            else:
                self._delta = res.transformation.numpy()  # prev_from_cur
                self._pose = self._pose @ self._delta
                fitness = float(res.fitness)
        self._prev = rgbd
        return OdometryStep(Rigid3(self._pose[:3, :3].copy(), self._pose[:3, 3].copy()), fitness,
                            int(np.count_nonzero(depth)))
