"""Absolute pose from 2D-3D correspondences: pycolmap LO-RANSAC P3P + non-linear refinement."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pycolmap

from slamreloc.geometry import Rigid3, reprojection_px
from slamreloc.types import Camera


@dataclass(frozen=True)
class PnPConfig:
    max_error_px: float = 12.0  # RANSAC inlier threshold (the paper's value)
    min_inliers: int = 20  # fewer inliers: the frame is reported as not localized
    max_trials: int = 10000
    seed: int = 0
    # the final refinement on the inliers (Levenberg-Marquardt, Cauchy loss): the loss's scale
    # in pixels and the gradient tolerance that stops it (pycolmap's defaults: 1 px, 1.0)
    refine_loss_px: float = 1.0
    refine_gradient_tolerance: float = 1.0


@dataclass
class PoseEstimate:
    """`cam_from_world` is None when the frame could not be localized."""

    cam_from_world: Rigid3 | None
    num_inliers: int
    num_correspondences: int
    inlier_mask: np.ndarray

    @property
    def success(self) -> bool:
        return self.cam_from_world is not None

    @property
    def world_from_cam(self) -> Rigid3 | None:
        return None if self.cam_from_world is None else self.cam_from_world.inverse()

    @property
    def confidence(self) -> float:
        """Inlier ratio in [0, 1]; 0 for a failure."""
        return self.num_inliers / max(self.num_correspondences, 1) if self.success else 0.0


def _refinement_options(config: PnPConfig) -> pycolmap.AbsolutePoseRefinementOptions:
    """The pose-only refinement (the camera's intrinsics stay fixed)."""
    ref = pycolmap.AbsolutePoseRefinementOptions()
    ref.refine_focal_length = False
    ref.refine_extra_params = False
    ref.loss_function_scale = config.refine_loss_px
    ref.gradient_tolerance = config.refine_gradient_tolerance
    return ref


def _rigid(pose: pycolmap.Rigid3d) -> Rigid3:
    m = pose.matrix()
    return Rigid3(m[:, :3].copy(), m[:, 3].copy())


def estimate_pose(points2d: np.ndarray, points3d: np.ndarray, camera: Camera,
                  config: PnPConfig = PnPConfig()) -> PoseEstimate:
    """points2d: (N, 2) pixels; points3d: (N, 3) world metres."""
    n = len(points2d)
    fail = PoseEstimate(None, 0, n, np.zeros(n, bool))
    if n < 4:
        return fail
    est = pycolmap.AbsolutePoseEstimationOptions()
    est.ransac.max_error = config.max_error_px
    est.ransac.max_num_trials = config.max_trials
    est.ransac.random_seed = config.seed
    res = pycolmap.estimate_and_refine_absolute_pose(
        np.ascontiguousarray(points2d, np.float64), np.ascontiguousarray(points3d, np.float64),
        camera.to_pycolmap(), est, _refinement_options(config))
    if res is None or res["num_inliers"] < config.min_inliers:
        if res is not None:
            fail.num_inliers, fail.inlier_mask = int(res["num_inliers"]), np.asarray(res["inlier_mask"])
        fail.cam_from_world = None
        return fail
    return PoseEstimate(_rigid(res["cam_from_world"]), int(res["num_inliers"]), n,
                        np.asarray(res["inlier_mask"]))


def refine_from(cam_from_world: Rigid3, points2d: np.ndarray, points3d: np.ndarray,
                camera: Camera, config: PnPConfig = PnPConfig(),
                max_error_px: float | None = None) -> Rigid3 | None:
    """The final refinement alone, from a given pose: Levenberg-Marquardt with the Cauchy loss
    of `config` on the correspondences that reproject within `max_error_px` (default: the
    RANSAC threshold, `config.max_error_px`) of `cam_from_world`. Returns the refined
    cam_from_world, or None with fewer than `config.min_inliers` such correspondences or when
    the solver fails. points2d: (N, 2) undistorted pixels; points3d: (N, 3) world metres."""
    points2d = np.ascontiguousarray(points2d, np.float64)
    points3d = np.ascontiguousarray(points3d, np.float64)
    limit = config.max_error_px if max_error_px is None else max_error_px
    inliers = reprojection_px(cam_from_world, points2d, points3d, camera.params()) < limit
    if inliers.sum() < config.min_inliers:
        return None
    start = pycolmap.Rigid3d(pycolmap.Rotation3d(cam_from_world.rotation),
                             cam_from_world.translation)
    res = pycolmap.refine_absolute_pose(start, points2d, points3d, inliers,
                                        camera.to_pycolmap(), _refinement_options(config))
    return None if res is None else _rigid(res["cam_from_world"])
