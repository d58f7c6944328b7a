"""The map's surface: depth of the posed training frames fused into one voxelised point cloud
with normals (map frame, metres), and point-to-plane ICP of a new depth frame against it.

The regressor places a camera to a few centimetres; where the frame has depth, ICP against the
surface the map was built from pulls that estimate onto the map's geometry (sub-centimetre to a
few millimetres where the view sees enough structure). The surface fuses each training frame's
depth cloud in its depth camera's frame, placed with the frame's world_from_cam; on 7-Scenes
the ground-truth poses are the depth camera's (KinectFusion), so the refined pose is in exactly
their frame.

`refine_with_depth` is the one depth refinement of a pose: `slamreloc evaluate --depth`, the
relocalization plugin (SLAM) and the service's Localize all call it with an `IcpConfig`.

    surface = build_surface(depth_frames)            # [(world_from_cam, points_cam), ...]
    fit = refine_with_depth(surface, depth, camera, depth_camera, world_from_cam_guess)
    fit.chosen(), fit.accepted, fit.fitness, fit.rmse_m"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from slamreloc.datasets import Dataset, read_frame_depth
from slamreloc.errors import InputError
from slamreloc.geometry import MAX_COORDINATE, Rigid3, axis_angle_to_matrix, rotation_angle_deg
from slamreloc.runtime.progress import track
from slamreloc.rgbd import DepthSampling, backproject, camera_of_depth
from slamreloc.types import Camera, Frame


@dataclass(frozen=True)
class SurfaceConfig:
    """How training depth is fused into the surface (lengths in metres)."""

    voxel_m: float = 0.025  # one point per voxel of the fused cloud
    normal_radius_m: float = 0.075
    frame_stride: int = 2  # every n-th training frame's depth enters the surface


@dataclass(frozen=True)
class IcpConfig:
    """The depth refinement of a pose (`refine_with_depth`, `refine_pose`): coarse-to-fine
    correspondence distances (metres, map frame); a fit is accepted when at least
    `min_fitness` of the frame's points lie within the last distance of the surface and the
    correction stays within (max_shift_m metres, max_turn_deg degrees) of the guess."""

    distances_m: tuple[float, ...] = (0.10, 0.05, 0.025)
    iterations: int = 15  # at most, Gauss-Newton steps per distance
    source_voxel_m: float = 0.04  # the frame's cloud is thinned to one point per voxel ...
    max_source_points: int = 600  # ... and to this many (more points cost time for little;
    # docs/history.md, "Depth refinement against the map's surface"); a fit whose fitness
    # stays below min_fitness landed elsewhere (guesses far off) and is not accepted
    min_fitness: float = 0.6
    max_shift_m: float = 0.5
    max_turn_deg: float = 15.0


# |length - 1| a stored normal may have: float16 rounding of a unit vector stays within 5e-4
NORMAL_TOLERANCE = 1e-3
DEGENERATE = 1e-3  # an ICP direction whose curvature is below this share of the largest


@dataclass
class Surface:
    points: np.ndarray  # (N, 3) float32, map frame, metres
    normals: np.ndarray  # (N, 3) float32, unit

    @cached_property
    def tree(self):
        from scipy.spatial import cKDTree

        return cKDTree(self.points.astype(np.float64))

    def to_arrays(self) -> dict[str, np.ndarray]:
        return {"points": self.points.astype(np.float32),
                "normals": self.normals.astype(np.float16)}

    @staticmethod
    def from_arrays(arrays: dict[str, np.ndarray], source: str) -> Surface:
        """Check shapes and values (a damaged file raises InputError naming `source`)."""
        pts, nrm = arrays.get("points"), arrays.get("normals")
        if pts is None or nrm is None:
            raise InputError(f"{source}: surface needs 'points' and 'normals' arrays")
        if pts.ndim != 2 or pts.shape[1:] != (3,) or nrm.shape != pts.shape:
            raise InputError(f"{source}: surface points {pts.shape} and normals {nrm.shape} "
                             "must both be (N, 3)")
        if pts.dtype.kind != "f" or nrm.dtype.kind != "f":
            raise InputError(f"{source}: surface arrays must be floating point")
        if not (np.isfinite(pts).all() and np.isfinite(nrm).all()):
            raise InputError(f"{source}: surface has non-finite values")
        if len(pts) and np.abs(pts).max() > MAX_COORDINATE:  # the database points' bound
            raise InputError(f"{source}: surface 'points' beyond {MAX_COORDINATE:g} m")
        # ICP weighs each residual by its normal: a zero or scaled normal would refine poses
        # against a wrong plane without a word
        lengths = np.linalg.norm(nrm.astype(np.float64), axis=1)
        bad = np.flatnonzero(np.abs(lengths - 1) > NORMAL_TOLERANCE)
        if len(bad):
            raise InputError(f"{source}: surface 'normals' must be unit vectors (length 1 within "
                             f"{NORMAL_TOLERANCE:g}); {len(bad)} of {len(nrm)} are not, row "
                             f"{bad[0]} has length {lengths[bad[0]]:.3g}")
        return Surface(pts.astype(np.float32), nrm.astype(np.float32))


def voxel_thin(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """One point (the first) per occupied voxel."""
    if len(points) == 0:
        return points
    _, first = np.unique(np.floor(points / voxel_m).astype(np.int64), axis=0, return_index=True)
    return points[np.sort(first)]


def depth_cloud(depth: np.ndarray, camera: Camera, depth_camera: Camera | None,
                sampling: DepthSampling = DepthSampling()) -> np.ndarray:
    """(N, 3) float64 points (metres) of a depth map (metres along z, 0 = none) in the frame of
    the camera that took it (OpenCV axes). `depth_camera`: that camera where the depth is not
    registered to the image (`Frame.depth_camera`, any pixel size: scaled to the depth map);
    None: registered to the RGB `camera`, whose lens distortion is undone first."""
    if depth_camera is None:
        depth = camera.undistort_image(depth)
    return backproject(depth, camera_of_depth(camera, depth.shape, depth_camera), sampling)


def frame_cloud(frame: Frame, dataset: Dataset) -> np.ndarray:
    """The points of a dataset frame's depth image in its depth camera's frame (metres)."""
    depth = read_frame_depth(frame, dataset.depth_units_per_metre)
    return depth_cloud(depth, frame.camera, frame.depth_camera)


def dataset_surface(dataset: Dataset, frames: list[Frame],
                    config: SurfaceConfig = SurfaceConfig(), progress: bool = True
                    ) -> Surface | None:
    """The surface of a dataset's posed frames with depth; None without depth."""
    chosen = [f for f in frames[::config.frame_stride]
              if f.depth_path is not None and f.world_from_cam is not None]
    return build_surface(((f.world_from_cam, frame_cloud(f, dataset))
                          for f in track(chosen, "surface", enabled=progress)), config)


def build_surface(depth_frames: Iterable[tuple[Rigid3, np.ndarray]],
                  config: SurfaceConfig = SurfaceConfig(), base: Surface | None = None
                  ) -> Surface | None:
    """Fuse (world_from_cam, points in that camera's frame) pairs, with the points of `base`
    (a surface to grow); None if nothing is left."""
    import open3d as o3d

    clouds = [voxel_thin(pose.transform(pts), config.voxel_m / 2)
              for pose, pts in depth_frames if len(pts)]
    if base is not None:
        clouds.append(base.points.astype(np.float64))
    if not clouds:
        return None
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.concatenate(clouds)))
    cloud = cloud.voxel_down_sample(config.voxel_m)
    if len(cloud.points) < 100:
        return None
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(config.normal_radius_m, 30))
    return Surface(np.asarray(cloud.points, np.float32), np.asarray(cloud.normals, np.float32))


def extend_surface(surface: Surface, depth_frames: list[tuple[Rigid3, np.ndarray]],
                   config: SurfaceConfig = SurfaceConfig(), min_gap_m: float = 0.05) -> Surface:
    """`surface` plus the parts of new posed depth frames it does not cover (points farther
    than `min_gap_m` from it): the new area joins, the old geometry is not blurred by a second
    copy at slightly other poses."""
    new = [voxel_thin(pose.transform(pts), config.voxel_m / 2) for pose, pts in depth_frames]
    new = np.concatenate([p for p in new if len(p)] or [np.zeros((0, 3))])
    if len(new):
        new = new[surface.tree.query(new, distance_upper_bound=min_gap_m)[0] > min_gap_m]
    if len(new) < 100:
        return surface
    return build_surface([(Rigid3.identity(), new)], config, base=surface) or surface


@dataclass
class IcpFit:
    """A depth refinement: poses are world_from_cam (map frame from the camera, metres)."""

    world_from_cam: Rigid3  # where ICP converged
    fitness: float  # share of the frame's (thinned) points within the last distance
    rmse_m: float  # point-to-plane residual of those points (metres; inf without any)
    accepted: bool
    guess: Rigid3  # the pose ICP started from

    def chosen(self) -> Rigid3:
        """The fit where it was accepted, else the guess."""
        return self.world_from_cam if self.accepted else self.guess


def _residuals(surface: Surface, pts_world: np.ndarray, max_m: float):
    """(mask of points with a surface point within max_m, those points, their surface normals,
    point-to-plane residuals)."""
    dist, idx = surface.tree.query(pts_world, distance_upper_bound=max_m)
    ok = np.isfinite(dist)
    p, n = pts_world[ok], surface.normals[idx[ok]].astype(np.float64)
    return ok, p, n, np.einsum("ij,ij->i", p - surface.points[idx[ok]], n)


def _step(surface: Surface, pts_world: np.ndarray, max_m: float, centre: np.ndarray):
    """One point-to-plane Gauss-Newton step: (rotation vector about `centre`, translation), in
    the map frame (rotating about the points' centre keeps the two apart); None with fewer
    than 6 correspondences."""
    _, p, n, r = _residuals(surface, pts_world, max_m)
    if len(r) < 6:
        return None
    J = np.hstack([np.cross(p - centre, n), n])
    w = 1.0 / np.maximum(1.0, np.abs(r) / (0.3 * max_m))  # Huber-like weights
    H, g = (J * w[:, None]).T @ J, -(J * w[:, None]).T @ r
    # degeneracy-aware step: directions the geometry leaves free (sliding along a wall) keep
    # the guess's values instead of following noise
    ev, vec = np.linalg.eigh(H)
    keep = ev > DEGENERATE * max(ev[-1], 1e-12)
    return vec[:, keep] @ ((vec[:, keep].T @ g) / ev[keep])


def refine_pose(surface: Surface, points_cam: np.ndarray, world_from_cam: Rigid3,
                config: IcpConfig = IcpConfig()) -> IcpFit:
    """Point-to-plane ICP of a depth frame's points (metres, in the frame of the camera that
    took them) onto `surface` from a pose guess (world_from_cam, map frame, metres)."""
    src = voxel_thin(points_cam, config.source_voxel_m)
    if len(src) > config.max_source_points:
        src = src[np.linspace(0, len(src) - 1, config.max_source_points).astype(int)]
    rot, trans = world_from_cam.rotation.copy(), world_from_cam.translation.copy()
    for max_m in config.distances_m:
        for _ in range(config.iterations):
            centre = rot @ src.mean(axis=0) + trans
            x = _step(surface, src @ rot.T + trans, max_m, centre)
            if x is None:
                break
            d_rot = axis_angle_to_matrix(x[:3])
            rot, trans = d_rot @ rot, d_rot @ (trans - centre) + centre + x[3:]
            if np.linalg.norm(x[:3]) < 1e-4 and np.linalg.norm(x[3:]) < 1e-4:
                break
    ok, _, _, r = _residuals(surface, src @ rot.T + trans, config.distances_m[-1])
    fit = Rigid3(rot, trans)
    fitness = float(ok.mean()) if len(ok) else 0.0
    shift = float(np.linalg.norm(trans - world_from_cam.translation))
    turn = rotation_angle_deg(world_from_cam.rotation.T @ rot)
    accepted = (fitness >= config.min_fitness and shift <= config.max_shift_m
                and turn <= config.max_turn_deg)
    return IcpFit(fit, fitness, float(np.sqrt(np.mean(r ** 2))) if len(r) else np.inf, accepted,
                  world_from_cam)


def refine_with_depth(surface: Surface, depth: np.ndarray, camera: Camera,
                      depth_camera: Camera | None, world_from_cam: Rigid3,
                      config: IcpConfig = IcpConfig()) -> IcpFit:
    """The depth refinement of a pose: point-to-plane ICP of a depth map onto the map's surface
    from the guess `world_from_cam` (map frame from the camera, metres; e.g. PnP's). `depth`:
    float32 metres along z (0 = none) in the pixels of the camera that took it, `depth_camera`
    (`Frame.depth_camera`, any pixel size: scaled to the depth map), or of the image's `camera`
    where `depth_camera` is None (registered depth, whose lens distortion is undone first).

    The surface is fused from training depth in the depth camera's own frame, placed with each
    frame's world_from_cam (7-Scenes: the depth camera's pose, KinectFusion), so the depth is
    fitted in its own camera's frame and the rig extrinsics (`Frame.rgb_from_depth`) do not
    enter. A depth map without a valid pixel gives a fit that is not accepted: `chosen()` is
    then the guess, as for any fit not accepted (`IcpConfig`)."""
    for name, value, kind in (("camera", camera, Camera), ("world_from_cam", world_from_cam,
                                                            Rigid3)):
        if not isinstance(value, kind):
            raise InputError(f"{name}: must be a {kind.__name__}, got {type(value).__name__}")
    if depth_camera is not None and not isinstance(depth_camera, Camera):
        raise InputError(f"depth_camera: must be a Camera or None, got "
                         f"{type(depth_camera).__name__}")
    if not isinstance(depth, np.ndarray) or depth.ndim != 2:
        raise InputError("depth: must be a numpy array (H x W, metres), got "
                         f"{type(depth).__name__}{getattr(depth, 'shape', '')}")
    points = depth_cloud(depth, camera, depth_camera)
    if len(points) == 0:
        return IcpFit(world_from_cam, 0.0, np.inf, False, world_from_cam)
    return refine_pose(surface, points, world_from_cam, config)
