"""Registration of unlabelled frames in the map frame, growing outward from the labelled map.

Each frame's descriptors are matched to a correspondence database (the map's labelled
descriptors plus everything already labelled in the new sequence) by mutual nearest neighbour
with a ratio test, and to the labelled keypoints of its registered neighbours in the sequence
(which carries poses through frames that match the database poorly). PnP-RANSAC verifies; a
registration must agree with its registered neighbours' motion (sequence continuity) or, with
no registered neighbour yet, have many inliers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from slamreloc.features.matcher import match_descriptors
from slamreloc.geometry import Rigid3, rotation_angle_deg
from slamreloc.map.labels import MIN_DEPTH_M
from slamreloc.map.format import PSEUDO
from slamreloc.geometry import reprojection_px
from slamreloc.localize.pnp import PnPConfig, estimate_pose
from slamreloc.types import Camera, Features


@dataclass(frozen=True)
class RegistrationConfig:
    ratio: float = 0.8  # Lowe's ratio, database and neighbour matching
    same_point_m: float = 0.05  # two nearest database entries this close count as one point
    pnp_max_error_px: float = 8.0  # RANSAC threshold
    label_max_error_px: float = 4.0  # an inlier must reproject this well to become a label
    min_inliers: int = 40  # below this the frame stays unregistered
    max_trials: int = 5000  # RANSAC
    seed_inliers: int = 80  # needed by a frame with no registered neighbour in the window
    anchor_inliers: int = 40  # inliers of a registration on the map's own labels alone that
    # make it a prior of the pose graph, if it is within this of the chain's pose (gross check)
    prior_agreement_m: float = 0.15
    prior_agreement_deg: float = 5.0
    # frames without such a prior give their chain registration (through the sequence's own
    # pseudo-labels) as a prior with the graph's relocalization sigmas times this; 0: none
    # (odometry alone carries the graph between map priors, and drifts over long stretches)
    chain_prior_sigma_scale: float = 1.0
    window: int = 5  # frames either side that count as neighbours
    neighbours: int = 2  # registered neighbours matched directly, each side
    # continuity: deviation from the neighbours' motion allowed, base + per frame of gap
    jump_m: float = 0.05
    jump_m_per_frame: float = 0.05
    jump_deg: float = 3.0
    jump_deg_per_frame: float = 3.0


class Database:
    """Labelled descriptors (torch, float32) with their world points. `rows`: per entry, the
    map database row its point comes from (-1: triangulated in the new sequence)."""

    def __init__(self, descriptors: np.ndarray, points: np.ndarray,
                 rows: np.ndarray | None = None) -> None:
        self.desc = torch.as_tensor(np.asarray(descriptors, np.float32))
        self.points = np.asarray(points, np.float32)
        self.rows = np.arange(len(points)) if rows is None else np.asarray(rows, np.int64)

    def __len__(self) -> int:
        return len(self.points)

    def match(self, query: np.ndarray, ratio: float, same_point_m: float) -> np.ndarray:
        """(M, 2) pairs (query index, database index): mutual nearest neighbours that pass the
        ratio test (or whose two nearest entries are one 3D point)."""
        return match_descriptors(query, self.desc, ratio, db_points=self.points,
                                 same_point_m=same_point_m)

    def correspondences(self, query: np.ndarray, config: RegistrationConfig
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """`match` as (query indices, world points (float64), map rows)."""
        m = self.match(query, config.ratio, config.same_point_m)
        return m[:, 0], self.points[m[:, 1]].astype(np.float64), self.rows[m[:, 1]]


@dataclass
class FrameState:
    """Per unlabelled frame: estimated pose and one label per keypoint (NaN: none)."""

    world_from_cam: Rigid3 | None
    points: np.ndarray  # (N, 3) float32
    source: np.ndarray  # (N,) int8: -1 none, PSEUDO (inherited by a match), NEW (triangulated)
    error_px: np.ndarray  # (N,) reprojection error of the label under the estimated pose
    row: np.ndarray  # (N,) int64: map database row an inherited label comes from, else -1
    num_inliers: int = 0
    via: str = ""  # "database", "neighbours", "both" or "odometry"

    @staticmethod
    def empty(n: int) -> FrameState:
        return FrameState(None, np.full((n, 3), np.nan, np.float32), np.full(n, -1, np.int8),
                          np.full(n, np.nan, np.float32), np.full(n, -1, np.int64))

    def drop(self, mask: np.ndarray) -> None:
        """Remove the labels of the keypoints in `mask`."""
        self.source[mask], self.points[mask], self.error_px[mask], self.row[mask] = (
            -1, np.nan, np.nan, -1)

    @property
    def registered(self) -> bool:
        return self.world_from_cam is not None


def neighbour_correspondences(i: int, feats: list[Features], states: list[FrameState],
                              config: RegistrationConfig
                              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(query keypoint indices, world points, map rows) from mutual-NN matches to the labelled
    keypoints of the nearest registered frames on each side within the window."""
    picked = []
    for direction in (-1, 1):
        found = 0
        for gap in range(1, config.window + 1):
            j = i + direction * gap
            if not 0 <= j < len(states) or found >= config.neighbours:
                break
            if states[j].registered:
                picked.append(j)
                found += 1
    q_idx, pts, rows = [], [], []
    for j in picked:
        lab = np.flatnonzero(states[j].source >= 0)
        if len(lab) < 2:
            continue
        m = match_descriptors(feats[i].descriptors, feats[j].descriptors[lab], config.ratio)
        q_idx.append(m[:, 0])
        pts.append(states[j].points[lab[m[:, 1]]])
        rows.append(states[j].row[lab[m[:, 1]]])
    if not q_idx:
        return np.zeros(0, np.int64), np.zeros((0, 3), np.float32), np.zeros(0, np.int64)
    return np.concatenate(q_idx), np.concatenate(pts), np.concatenate(rows)


def register_frame(i: int, feats: list[Features], cameras: list[Camera], states: list[FrameState],
                   db: Database, config: RegistrationConfig) -> FrameState | None:
    """Try to register frame i; returns its new state, or None.

    The registered neighbours' labels are tried first (cheap); the whole database is matched
    only when they are missing or not enough."""
    f = feats[i]
    nb_q, nb_pts, nb_rows = neighbour_correspondences(i, feats, states, config)
    if len(nb_q) >= config.min_inliers:
        state = _pnp_state(i, f, cameras[i], nb_q, nb_pts.astype(np.float64), nb_rows, config)
        if state is not None and state.num_inliers >= config.seed_inliers:
            state.via = "neighbours"
            return state
    db_q, db_pts, db_rows = db.correspondences(f.descriptors, config)
    # neighbour matches first: on a keypoint matched both ways, the neighbour's label wins
    q_idx = np.concatenate([nb_q, db_q])
    pts = np.concatenate([nb_pts, db_pts]).astype(np.float64)
    rows = np.concatenate([nb_rows, db_rows])
    _, first = np.unique(q_idx, return_index=True)
    q_idx, pts, rows = q_idx[first], pts[first], rows[first]
    state = _pnp_state(i, f, cameras[i], q_idx, pts, rows, config)
    if state is None:
        return None
    from_nb = np.isin(np.flatnonzero(state.source == PSEUDO), nb_q)
    state.via = ("both" if from_nb.any() and (~from_nb).any()
                 else "neighbours" if from_nb.any() else "database")
    return state


def _pnp_state(i, f, camera, q_idx, pts, rows, config) -> FrameState | None:
    if len(q_idx) < config.min_inliers:
        return None
    est = estimate_pose(f.keypoints[q_idx], pts, camera,
                        PnPConfig(max_error_px=config.pnp_max_error_px,
                                  min_inliers=config.min_inliers, max_trials=config.max_trials))
    if not est.success:
        return None
    state = inherit_labels(est.world_from_cam, f, camera, q_idx, pts, rows, config)
    return state if state.num_inliers >= config.min_inliers else None


def inherit_labels(world_from_cam: Rigid3, f: Features, camera: Camera, q_idx: np.ndarray,
                   pts: np.ndarray, rows: np.ndarray, config: RegistrationConfig) -> FrameState:
    """The frame at this pose, labelled with the matched points that reproject within
    `label_max_error_px`."""
    err = reprojection_px(world_from_cam.inverse(), f.keypoints[q_idx], pts, camera.params(),
                          min_depth_m=MIN_DEPTH_M)
    good = err <= config.label_max_error_px
    state = FrameState.empty(len(f))
    state.world_from_cam = world_from_cam
    state.points[q_idx[good]] = pts[good]
    state.source[q_idx[good]] = PSEUDO
    state.error_px[q_idx[good]] = err[good]
    state.row[q_idx[good]] = rows[good]
    state.num_inliers = int(good.sum())
    return state


def register_on(corr: tuple, f: Features, camera: Camera,
                config: RegistrationConfig) -> FrameState | None:
    """A frame registered by PnP-RANSAC on its `Database.correspondences` alone; None when
    that fails."""
    return _pnp_state(-1, f, camera, *corr, config)


def label_at_pose(f: Features, camera: Camera, world_from_cam: Rigid3, corr: tuple,
                  config: RegistrationConfig) -> FrameState:
    """A frame whose pose is known (smoothed): inherit the points of its
    `Database.correspondences` that reproject within `label_max_error_px` (no PnP)."""
    return inherit_labels(world_from_cam, f, camera, *corr, config)


def _nearest_registered(i: int, states: list[FrameState], direction: int, window: int,
                        exclude: int | None = None) -> int | None:
    for gap in range(1, window + 1):
        j = i + direction * gap
        if not 0 <= j < len(states):
            return None
        if j != exclude and states[j].registered:
            return j
    return None


def pose_deviation(i: int, pose: Rigid3, states: list[FrameState], window: int,
                   exclude: int | None = None) -> tuple[float, float, int] | None:
    """(translation m, rotation deg, frame gap) of `pose` from what its registered neighbours
    predict (linear interpolation between the two sides, or the nearer side alone); None when
    no registered neighbour is within the window."""
    p = _nearest_registered(i, states, -1, window, exclude)
    n = _nearest_registered(i, states, 1, window, exclude)
    if p is None and n is None:
        return None
    if p is not None and n is not None:
        a, b = states[p].world_from_cam, states[n].world_from_cam
        w = (i - p) / (n - p)
        centre = (1 - w) * a.translation + w * b.translation
        ref = a if i - p <= n - i else b
        gap = min(i - p, n - i)
        dt = float(np.linalg.norm(pose.translation - centre))
    else:
        j = p if p is not None else n
        ref, gap = states[j].world_from_cam, abs(i - j)
        dt = float(np.linalg.norm(pose.translation - ref.translation))
    dr = rotation_angle_deg(ref.rotation.T @ pose.rotation)
    return dt, dr, gap


def typical_step(states: list[FrameState], config: RegistrationConfig
                 ) -> tuple[float, float] | None:
    """Per-frame motion allowance (m, deg): the configured one, or twice the sequence's median
    motion per frame between strongly registered frames when that is larger (sparse sequences,
    fast motion); None while fewer than 3 such pairs exist."""
    strong = [i for i, s in enumerate(states) if s.registered
              and s.num_inliers >= config.seed_inliers]
    steps_t, steps_r = [], []
    for a, b in zip(strong, strong[1:]):
        if b - a <= config.window:
            pa, pb = states[a].world_from_cam, states[b].world_from_cam
            steps_t.append(np.linalg.norm(pa.translation - pb.translation) / (b - a))
            steps_r.append(rotation_angle_deg(pa.rotation.T @ pb.rotation) / (b - a))
    if len(steps_t) < 3:
        return None
    return (max(config.jump_m_per_frame, 2 * float(np.median(steps_t))),
            max(config.jump_deg_per_frame, 2 * float(np.median(steps_r))))


def consistent(i: int, pose: Rigid3, states: list[FrameState], config: RegistrationConfig,
               num_inliers: int, exclude: int | None = None, step=None) -> bool:
    dev = pose_deviation(i, pose, states, config.window, exclude)
    if dev is None:
        return num_inliers >= config.seed_inliers
    dt, dr, gap = dev
    step = step or typical_step(states, config)
    if step is None:  # the sequence's motion is not known yet: the sweep judges it later
        return True
    step_m, step_deg = step
    return (dt <= config.jump_m + step_m * gap and dr <= config.jump_deg + step_deg * gap)


def continuity_sweep(states: list[FrameState], config: RegistrationConfig) -> list[int]:
    """Unregister frames that disagree with their registered neighbours; returns their indices.

    Worst offenders go first, so one wrong frame does not condemn its correct neighbours."""
    dropped = []
    step_m, step_deg = typical_step(states, config) or (config.jump_m_per_frame,
                                                        config.jump_deg_per_frame)
    while True:
        worst, worst_score = None, 1.0
        for i, s in enumerate(states):
            if not s.registered:
                continue
            dev = pose_deviation(i, s.world_from_cam, states, config.window, exclude=i)
            if dev is None:
                if s.num_inliers < config.seed_inliers:  # isolated and weak
                    score = 2.0
                else:
                    continue
            else:
                dt, dr, gap = dev
                score = max(dt / (config.jump_m + step_m * gap),
                            dr / (config.jump_deg + step_deg * gap))
            if score > worst_score:
                worst, worst_score = i, score
        if worst is None:
            return dropped
        states[worst] = FrameState.empty(len(states[worst].source))
        dropped.append(worst)
