"""Guided matching: query keypoints to the map's database near a camera pose.

Regressed world points scatter by a few centimetres; the map's database holds each labelled
training keypoint's descriptor and its triangulated (or depth) world point, which are as
precise as the labels. Once the regressor's pose is known to a few pixels, the database rows
seen by the training cameras nearest to it are projected into the query, and each query
keypoint takes the row nearest in descriptor space among those projecting within a few
pixels of it. The pose gating makes this cheap (about a thousand rows, not the whole map)
and unambiguous (a repeated texture elsewhere in the map never competes), and the final
refinement then runs on the database's world points instead of the regressed ones.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from slamreloc.geometry import Rigid3, project
from slamreloc.map.scene_map import MapDatabase, rows_by_frame
from slamreloc.types import Camera, Features


@dataclass(frozen=True)
class GuidedConfig:
    n_frames: int = 6  # training cameras whose database rows are projected
    max_angle_deg: float = 45.0  # between their optical axis and the query's
    radius_px: float = 6.0  # a row gates a query keypoint within this many pixels
    neighbours: int = 16  # rows considered per query keypoint (nearest projections first)
    ratio: float = 0.9  # descriptor distance ratio to the best row of another world point
    same_point_m: float = 0.01  # rows whose world points lie closer are one point
    # The step refines onto the labels, so it only helps where they are more precise than the
    # regression: it runs on maps whose training tracks reproject within this median (pixels)
    # with the map's poses (`MapMeta.label_reproj_error_px`; a map that did not record it
    # counts as within). RedKitchen's two references fall on either side of it
    # (BENCHMARKS.md, "Localization on RedKitchen, against both references").
    max_label_error_px: float = 1.0

    def applies_to(self, label_reproj_error_px: float | None) -> bool:
        """Whether the step runs on a map whose labels reproject with this median (pixels)."""
        return label_reproj_error_px is None or label_reproj_error_px <= self.max_label_error_px


class GuidedMatcher:
    """Query keypoints -> the map's database world points, gated by a camera pose."""

    def __init__(self, database: MapDatabase, config: GuidedConfig = GuidedConfig()):
        self.db = database
        self.config = config
        world_from_cam = np.asarray(database.world_from_cam, np.float64)
        self.centers = world_from_cam[:, :3, 3]  # training camera centres, world metres
        self.axes = world_from_cam[:, :3, 2]  # their optical axes (+z), world frame
        self.rows = rows_by_frame(database.frame_index, len(world_from_cam))

    def nearby_rows(self, cam_from_world: Rigid3, allowed: np.ndarray | None = None,
                    n_frames: int | None = None, max_angle_deg: float | None = None
                    ) -> np.ndarray:
        """Database rows of the `n_frames` training cameras nearest to the pose's centre
        among those looking within `max_angle_deg` of its direction (and `allowed`, a mask
        over the training cameras, where given); both default to the config's."""
        n_frames = self.config.n_frames if n_frames is None else n_frames
        max_angle_deg = self.config.max_angle_deg if max_angle_deg is None else max_angle_deg
        world_from_cam = cam_from_world.inverse()
        axis = world_from_cam.rotation[:, 2]
        distance = np.linalg.norm(self.centers - world_from_cam.translation, axis=1)
        distance[self.axes @ axis < np.cos(np.radians(max_angle_deg))] = np.inf
        if allowed is not None:
            distance[~allowed] = np.inf
        near = np.argsort(distance, kind="stable")[:n_frames]
        near = near[np.isfinite(distance[near])]
        if len(near) == 0:
            return np.zeros(0, np.int64)
        return np.concatenate([self.rows[i] for i in near])

    def correspondences(self, cam_from_world: Rigid3, feats: Features, camera: Camera
                        ) -> tuple[np.ndarray, np.ndarray]:
        """(points2d (K, 2) undistorted pixels, points3d (K, 3) world metres): the query
        keypoints matched to database rows near `cam_from_world`, one row per keypoint.
        `camera`'s pinhole intrinsics project (keypoints are undistorted)."""
        keypoints, rows = self.matches(cam_from_world, feats, camera)
        return keypoints, self.db.points[rows].astype(np.float64)

    def matches(self, cam_from_world: Rigid3, feats: Features, camera: Camera,
                allowed: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(points2d (K, 2) undistorted pixels, database rows (K,)): `correspondences` with
        the rows the keypoints matched; `allowed`: as `nearby_rows`."""
        cfg = self.config
        empty = np.zeros((0, 2)), np.zeros(0, np.int64)
        rows = self.nearby_rows(cam_from_world, allowed)
        if len(rows) == 0 or len(feats) == 0:
            return empty
        points = self.db.points[rows].astype(np.float64)
        in_cam = cam_from_world.transform(points)
        front = in_cam[:, 2] > 1e-3
        rows, points, in_cam = rows[front], points[front], in_cam[front]
        if len(rows) == 0:
            return empty
        uv = project(in_cam, *camera.pinhole.params())
        k = min(cfg.neighbours, len(rows))
        keypoints = np.asarray(feats.keypoints, np.float64)
        dist, nb = cKDTree(uv).query(keypoints, k=k, distance_upper_bound=cfg.radius_px)
        dist, nb = dist.reshape(len(keypoints), k), nb.reshape(len(keypoints), k)
        gated = np.isfinite(dist[:, 0])  # nearest first: a keypoint with any row in reach
        if not gated.any():
            return empty
        keypoints, valid, nb = keypoints[gated], np.isfinite(dist[gated]), nb[gated]
        # descriptor similarity of each (keypoint, row in reach) pair; unit descriptors
        q, c = np.nonzero(valid)
        query_desc = np.asarray(feats.descriptors, np.float32)[gated]
        sims = np.full(valid.shape, -2.0, np.float32)
        sims[q, c] = np.einsum("pd,pd->p", self.db.descriptors[rows[nb[q, c]]]
                               .astype(np.float32), query_desc[q])
        nb = np.where(valid, nb, 0)
        best = np.argmax(sims, axis=1)
        s1 = sims[np.arange(len(sims)), best]
        best_row = nb[np.arange(len(nb)), best]
        other = np.linalg.norm(points[nb] - points[best_row][:, None], axis=2) > cfg.same_point_m
        s2 = np.where(other & valid, sims, -2.0).max(axis=1)
        d1, d2 = (np.sqrt(np.clip(2.0 - 2.0 * s, 0.0, None)) for s in (s1, s2))
        ok = (s2 <= -2.0) | (d1 < cfg.ratio * d2)
        return keypoints[ok], rows[best_row[ok]]
