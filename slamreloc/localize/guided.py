"""Guided matching: query keypoints to the map's database near a camera pose.

Regressed world points scatter by a few centimetres; the map's database holds each labelled
training keypoint's descriptor and its triangulated (or depth) world point, which are as
precise as the labels. Once the regressor's pose is known to a few pixels, the database rows
seen by the training cameras nearest to it are projected into the query, and each query
keypoint takes the row nearest in descriptor space among those projecting within a few
pixels of it. The pose gating makes this cheap (about a thousand rows, not the whole map)
and unambiguous (a repeated texture elsewhere in the map never competes), and the final
refinement then runs on the database's world points instead of the regressed ones.

A second gate does not use the pose at all: the rows whose world points lie within a few
centimetres of a keypoint's regressed world point (`near_points`). Choosing rows by the pose
alone favours, among candidates a few pixels apart, those that agree with the pose's own
error, so the refinement stays near where it started; the point gate has no such bias and
takes rows from every training camera that saw the place, not only the nearest few. The
refinement uses both sets (held-out measurements: BENCHMARKS.md, "Held-out folds").
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
    # rows whose world points lie within this of a keypoint's regressed world point (metres)
    # are its candidates for the pose-free gate (`near_points`); 0 leaves that gate out
    point_radius_m: float = 0.10
    point_neighbours: int = 8  # rows considered per keypoint there (nearest points first)

    def applies_to(self, label_reproj_error_px: float | None) -> bool:
        """Whether the step runs on a map whose labels reproject with this median (pixels)."""
        return label_reproj_error_px is None or label_reproj_error_px <= self.max_label_error_px


class GuidedMatcher:
    """Query keypoints -> the map's database world points, gated by a camera pose."""

    def __init__(self, database: MapDatabase, config: GuidedConfig = GuidedConfig(),
                 descriptors: np.ndarray | None = None):
        """`descriptors`: the database's descriptors as float32 (N, D) where the caller holds
        them already (a live map keeps them as it grows), else converted here."""
        self.db = database
        self.config = config
        world_from_cam = np.asarray(database.world_from_cam, np.float64)
        self.centers = world_from_cam[:, :3, 3]  # training camera centres, world metres
        self.axes = world_from_cam[:, :3, 2]  # their optical axes (+z), world frame
        self.rows = rows_by_frame(database.frame_index, len(world_from_cam))
        self._tree: cKDTree | None = None  # over the rows' world points (`near_points`)
        # the descriptors as float32 (twice the float16 map's bytes: 55 MB for RedKitchen's
        # 107k rows): converting the gathered rows at each query cost 4 ms of its ~40
        self._descriptors = np.asarray(database.descriptors if descriptors is None
                                       else descriptors, np.float32)

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

    def correspondences(self, cam_from_world: Rigid3, feats: Features, camera: Camera,
                        points: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(points2d (K, 2) undistorted pixels, points3d (K, 3) world metres): the query
        keypoints matched to database rows near `cam_from_world` (`matches`) and, given the
        regressed world points (N, 3) of all of `feats`' keypoints, to rows near those points
        (`near_points`): a keypoint appears once per gate that matched it. `camera`'s pinhole
        intrinsics project (keypoints are undistorted)."""
        keypoints, rows = self.matches(cam_from_world, feats, camera)
        if points is not None:
            index, near = self.near_points(feats, points)
            keypoints = np.concatenate([keypoints, np.asarray(feats.keypoints, np.float64)[index]])
            rows = np.concatenate([rows, near])
        return keypoints, self.db.points[rows].astype(np.float64)

    def matches(self, cam_from_world: Rigid3, feats: Features, camera: Camera,
                allowed: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(points2d (K, 2) undistorted pixels, database rows (K,)): the keypoints matched to
        rows of the training cameras near `cam_from_world` that project within `radius_px`
        of them; `allowed`: as `nearby_rows`."""
        cfg = self.config
        empty = np.zeros((0, 2)), np.zeros(0, np.int64)
        rows = self.nearby_rows(cam_from_world, allowed)
        if len(rows) == 0 or len(feats) == 0:
            return empty
        in_cam = cam_from_world.transform(self.db.points[rows].astype(np.float64))
        rows = rows[in_cam[:, 2] > 1e-3]
        if len(rows) == 0:
            return empty
        uv = project(in_cam[in_cam[:, 2] > 1e-3], *camera.pinhole.params())
        keypoints = np.asarray(feats.keypoints, np.float64)
        dist, nb = _query(cKDTree(uv), keypoints, min(cfg.neighbours, len(rows)), cfg.radius_px)
        index, chosen = self._choose(feats, dist, rows[np.minimum(nb, len(rows) - 1)])
        return keypoints[index], chosen

    def near_points(self, feats: Features, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(keypoint indices (K,), database rows (K,)): each keypoint matched, by descriptor, to
        the rows whose world points lie within `point_radius_m` of its regressed world point
        (`points`, (N, 3) world metres, one per keypoint of `feats`). No pose is involved."""
        cfg = self.config
        if cfg.point_radius_m <= 0 or len(feats) == 0 or len(self.db.points) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        if self._tree is None:
            self._tree = cKDTree(np.asarray(self.db.points, np.float64))
        k = min(cfg.point_neighbours, len(self.db.points))
        dist, nb = _query(self._tree, np.asarray(points, np.float64), k, cfg.point_radius_m)
        return self._choose(feats, dist, nb)

    def _choose(self, feats: Features, dist: np.ndarray, candidates: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
        """(keypoint indices, rows): for each keypoint, of its candidate rows (N, k) where
        `dist` (N, k) is finite, the one nearest in descriptor space, kept when it passes the
        ratio test against the best row of another world point (`same_point_m` apart)."""
        cfg = self.config
        valid = np.isfinite(dist)
        index = np.flatnonzero(valid[:, 0])  # nearest first: a keypoint with any row in reach
        if len(index) == 0:
            return index, np.zeros(0, np.int64)
        valid, candidates = valid[index], np.where(valid[index], candidates[index], 0)
        # descriptor similarity of each (keypoint, candidate) pair; unit descriptors
        q, c = np.nonzero(valid)
        query_desc = np.asarray(feats.descriptors, np.float32)[index]
        sims = np.full(valid.shape, -2.0, np.float32)
        sims[q, c] = np.einsum("pd,pd->p", self._descriptors[candidates[q, c]], query_desc[q])
        best = np.argmax(sims, axis=1)
        s1 = sims[np.arange(len(sims)), best]
        best_row = candidates[np.arange(len(candidates)), best]
        points = self.db.points
        other = (np.linalg.norm(points[candidates] - points[best_row][:, None], axis=2)
                 > cfg.same_point_m)
        s2 = np.where(other & valid, sims, -2.0).max(axis=1)
        d1, d2 = (np.sqrt(np.clip(2.0 - 2.0 * s, 0.0, None)) for s in (s1, s2))
        ok = (s2 <= -2.0) | (d1 < cfg.ratio * d2)
        return index[ok], best_row[ok]


def _query(tree: cKDTree, x: np.ndarray, k: int, radius: float
           ) -> tuple[np.ndarray, np.ndarray]:
    """cKDTree.query as (N, k) arrays whatever k (inf distance: nothing in reach)."""
    dist, nb = tree.query(x, k=k, distance_upper_bound=radius)
    return dist.reshape(len(x), k), nb.reshape(len(x), k)
