"""The labelled rows of a map a SLAM session builds, kept per keyframe in the keyframe's own
camera frame, so that they follow the keyframe wherever the pose graph moves it.

Each keyframe with depth contributes its keypoints (pinhole pixels), descriptors and the 3D
points of those keypoints from its depth (metres, in the keyframe's camera frame). A map the
session started from (multi-session) contributes its database as fixed frames: rows in each
training camera's frame with that camera's fixed world_from_cam. `database(poses)` places every
row in the map frame with the keyframes' current poses: the `MapDatabase` that localization,
training and the saved map use.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slamreloc.geometry import Rigid3
from slamreloc.map.scene_map import MapDatabase, rows_by_frame


@dataclass(frozen=True)
class KeyframeRows:
    """One keyframe's rows. `key`: its pose-graph key, or None for a frame of a prior map,
    whose `world_from_cam` is then fixed (map frame, metres); `frame`: its index among the
    session's processed frames (-1 for a prior map's frame)."""

    key: int | None
    frame: int
    name: str
    keypoints: np.ndarray  # (N, 2) float32 pinhole pixels
    descriptors: np.ndarray  # (N, D) float16, unit rows
    points_cam: np.ndarray  # (N, 3) float32 metres, the keyframe's camera frame
    world_from_cam: Rigid3 | None = None  # fixed pose of a prior map's frame
    picture: str = ""  # its picture (`io.images.picture_digest`), "" where not known


@dataclass
class LiveDatabase:
    """A `MapDatabase` placed with one set of keyframe poses, and where each of its frames
    came from: `keys[f]` the graph key of frame f (None: a prior map's fixed frame),
    `frames[f]` its index among the session's processed frames (-1: a prior map's)."""

    database: MapDatabase
    keys: list[int | None]
    frames: list[int]
    version: tuple


class KeyframeStore:
    """Rows of every keyframe, in order; append-only."""

    def __init__(self) -> None:
        self.keyframes: list[KeyframeRows] = []
        self.n_rows = 0
        # every row's descriptor as float32, in `database`'s row order, grown as keyframes
        # come (capacity doubling): searches need float32, and converting the whole map
        # at each of its versions cost a keyframe 24 ms at 97k rows
        self._desc32 = np.zeros((0, 0), np.float32)
        self._n_desc32 = (0, 0)  # (keyframes, rows) already in it

    @staticmethod
    def from_database(db: MapDatabase) -> KeyframeStore:
        """A prior map's database as fixed frames (rows moved into each camera's frame)."""
        store = KeyframeStore()
        world_from_cam = np.asarray(db.world_from_cam, np.float64)
        for f, rows in enumerate(rows_by_frame(db.frame_index, len(world_from_cam))):
            pose = Rigid3.from_matrix(world_from_cam[f], source="map database")
            store.keyframes.append(KeyframeRows(
                None, -1, db.frame_names[f] if f < len(db.frame_names) else f"frame{f}",
                db.keypoints[rows].astype(np.float32), db.descriptors[rows].astype(np.float16),
                pose.inverse().transform(db.points[rows].astype(np.float64)).astype(np.float32),
                pose, db.frame_pictures[f] if f < len(db.frame_pictures) else ""))
            store.n_rows += len(rows)
        return store

    def add(self, rows: KeyframeRows) -> None:
        self.keyframes.append(rows)
        self.n_rows += len(rows.keypoints)

    @property
    def n_keyframes(self) -> int:
        return len(self.keyframes)

    @property
    def n_session_keyframes(self) -> int:
        """The keyframes of this session (graph keys), not a prior map's fixed frames."""
        return sum(k.key is not None for k in self.keyframes)

    def descriptors_f32(self) -> np.ndarray:
        """(n_rows, D) float32 view of every row's descriptor, in `database`'s row order (rows
        are only appended, so a view taken earlier stays right for the rows it covers)."""
        done, n = self._n_desc32
        new = [k.descriptors for k in self.keyframes[done:] if len(k.keypoints)]
        total = n + sum(len(d) for d in new)
        if new and total > len(self._desc32):
            grown = np.empty((max(total, 2 * len(self._desc32)), new[0].shape[1]), np.float32)
            if n:
                grown[:n] = self._desc32[:n]
            self._desc32 = grown
        for d in new:
            self._desc32[n:n + len(d)] = d
            n += len(d)
        self._n_desc32 = (len(self.keyframes), n)
        return self._desc32[:n]

    def database(self, poses: dict[int, Rigid3], version: tuple = ()) -> LiveDatabase:
        """Every row in the map frame, graph keyframes placed with `poses` (key ->
        world_from_cam); frames without rows are left out."""
        kept = [k for k in self.keyframes if len(k.keypoints)]
        world = [k.world_from_cam if k.key is None else poses[k.key] for k in kept]
        if not kept:
            empty = MapDatabase(np.zeros((0, 128), np.float16), np.zeros((0, 3), np.float32),
                                np.zeros((0, 2), np.float32), np.zeros(0, np.int32), [],
                                np.zeros((0, 4, 4)))
            return LiveDatabase(empty, [], [], version)
        db = MapDatabase(
            descriptors=np.concatenate([k.descriptors for k in kept]),
            points=np.concatenate([w.transform(k.points_cam.astype(np.float64))
                                   for k, w in zip(kept, world)]).astype(np.float32),
            keypoints=np.concatenate([k.keypoints for k in kept]),
            frame_index=np.concatenate([np.full(len(k.keypoints), i, np.int32)
                                        for i, k in enumerate(kept)]),
            frame_names=[k.name for k in kept],
            world_from_cam=np.stack([w.matrix() for w in world]),
            frame_pictures=[k.picture for k in kept])
        return LiveDatabase(db, [k.key for k in kept], [k.frame for k in kept], version)
