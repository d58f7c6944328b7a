"""Scene-coordinate labels: world points (metres) for the keypoints of posed training frames.

Frames are paired by pose (similar viewing direction, overlapping look-at points, a spread of
baselines); their features are matched (mutual NN + ratio), kept if they fit the epipolar
geometry of the known poses, joined into multi-view tracks, and each track is triangulated
with pycolmap (LO-RANSAC on reprojection error) and filtered by reprojection error and
triangulation angle. Where depth is registered to the image, the back-projected depth of a
track's keypoint refines its label, and keypoints whose depth disagrees with the track drop out.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pycolmap
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from slamreloc.features.matcher import match_descriptors
from slamreloc.geometry import Rigid3, reprojection_px
from slamreloc.runtime.progress import track
from slamreloc.rgbd import keypoint_points
from slamreloc.types import Features, Frame

# a labelled point lies at least this far in front of every camera that labels it (metres)
MIN_DEPTH_M = 0.05


@dataclass(frozen=True)
class LabelConfig:
    pairs_per_frame: int = 8
    max_axis_angle_deg: float = 35.0  # between optical axes of a pair
    look_at_depth_m: float = 1.5  # typical scene depth, for the overlap test
    min_baseline_m: float = 0.03
    ratio: float = 0.85
    max_epipolar_px: float = 3.0  # Sampson distance for match verification
    max_reproj_px: float = 3.0  # per observation, after triangulation
    min_tri_angle_deg: float = 2.0
    depth_agreement_m: float = 0.05  # track vs depth, plus 2 % of depth
    use_depth: bool = True  # only where the dataset's depth is registered to RGB
    # bundle-adjust each track's point, poses fixed (`refine_track_points`): off, as it did
    # not raise the recall at 1-2 cm (docs/history.md, "Fine accuracy: labels")
    refine_points: bool = False


@dataclass
class LabelSet:
    """points[i]: (N_i, 3) float32 world points for frame i's keypoints, NaN where unlabelled."""

    points: list[np.ndarray]
    track_ids: list[np.ndarray]  # (N_i,) int64, -1 where not in a triangulated track
    stats: dict = field(default_factory=dict)


def select_pairs(poses: list[Rigid3], config: LabelConfig) -> np.ndarray:
    """(P, 2) frame index pairs i < j likely to see the same surfaces."""
    centres = np.stack([p.translation for p in poses])
    axes = np.stack([p.rotation[:, 2] for p in poses])
    look = centres + config.look_at_depth_m * axes
    cos = axes @ axes.T
    base = np.linalg.norm(centres[:, None] - centres[None], axis=2)
    look_d = np.linalg.norm(look[:, None] - look[None], axis=2)
    ok = (cos > np.cos(np.radians(config.max_axis_angle_deg))) & (base > config.min_baseline_m)
    ok &= look_d < 0.6 * config.look_at_depth_m
    pairs = set()
    for i in range(len(poses)):
        cand = np.flatnonzero(ok[i])
        if len(cand) == 0:
            continue
        cand = cand[np.argsort(base[i, cand])]  # spread of baselines: evenly spaced ranks
        pick = np.unique(np.linspace(0, len(cand) - 1, config.pairs_per_frame).round().astype(int))
        pairs.update((min(i, j), max(i, j)) for j in cand[pick])
    return np.array(sorted(pairs), dtype=np.int64).reshape(-1, 2)


def _sampson_px(x1: np.ndarray, x2: np.ndarray, fundamental: np.ndarray) -> np.ndarray:
    h1 = np.hstack([x1, np.ones((len(x1), 1))])
    h2 = np.hstack([x2, np.ones((len(x2), 1))])
    fx1, ftx2 = h1 @ fundamental.T, h2 @ fundamental
    num = np.sum(h2 * fx1, axis=1) ** 2
    den = fx1[:, 0] ** 2 + fx1[:, 1] ** 2 + ftx2[:, 0] ** 2 + ftx2[:, 1] ** 2
    return np.sqrt(num / np.maximum(den, 1e-12))


def _fundamental(frame_a: Frame, frame_b: Frame) -> np.ndarray:
    b_from_a = frame_b.world_from_cam.inverse() @ frame_a.world_from_cam
    t = b_from_a.translation
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    ka_inv, kb_inv = np.linalg.inv(frame_a.camera.K), np.linalg.inv(frame_b.camera.K)
    return kb_inv.T @ tx @ b_from_a.rotation @ ka_inv


def verified_matches(frames, feats, pairs, config, progress=True) -> np.ndarray:
    """(M, 4) rows (frame_a, kp_a, frame_b, kp_b) of epipolar-consistent matches."""
    rows = []
    for i, j in track(pairs, "matching pairs", enabled=progress):
        m = match_descriptors(feats[i].descriptors, feats[j].descriptors, config.ratio)
        if len(m) == 0:
            continue
        err = _sampson_px(feats[i].keypoints[m[:, 0]], feats[j].keypoints[m[:, 1]],
                          _fundamental(frames[i], frames[j]))
        m = m[err < config.max_epipolar_px]
        rows.append(np.column_stack([np.full(len(m), i), m[:, 0], np.full(len(m), j), m[:, 1]]))
    return np.concatenate(rows) if rows else np.zeros((0, 4), np.int64)


def build_tracks(feats: list[Features], matches: np.ndarray) -> np.ndarray:
    """Track id per keypoint (flattened over frames), -1 for keypoints in no track.

    Tracks holding two keypoints of one frame are ambiguous and dropped."""
    offsets = np.concatenate([[0], np.cumsum([len(f) for f in feats])])
    n = int(offsets[-1])
    a = offsets[matches[:, 0]] + matches[:, 1]
    b = offsets[matches[:, 2]] + matches[:, 3]
    graph = coo_matrix((np.ones(len(a)), (a, b)), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    size = np.bincount(comp)
    frame_of = np.repeat(np.arange(len(feats)), np.diff(offsets))
    # a component is ambiguous if (component, frame) occurs more than once
    key = comp.astype(np.int64) * len(feats) + frame_of
    _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    bad = np.zeros(len(size), bool)
    bad[comp[counts[inverse] > 1]] = True
    return np.where((size[comp] >= 2) & ~bad[comp], comp, -1)


def triangulate_tracks(frames, feats, track_of, config, progress=True):
    """World points (n_kp, 3) with NaN where a keypoint's track failed or it was an outlier."""
    offsets = np.concatenate([[0], np.cumsum([len(f) for f in feats])])
    frame_of = np.repeat(np.arange(len(feats)), np.diff(offsets))
    kp_xy = np.concatenate([f.keypoints for f in feats]).astype(np.float64)
    rigs = [pycolmap.Rigid3d(f.world_from_cam.inverse().matrix3x4()) for f in frames]
    cams = [f.camera.to_pycolmap() for f in frames]
    opts = pycolmap.EstimateTriangulationOptions()
    opts.residual_type = pycolmap.TriangulationResidualType.REPROJECTION_ERROR
    opts.ransac.max_error = config.max_reproj_px
    opts.min_tri_angle = np.radians(config.min_tri_angle_deg)
    points = np.full((len(kp_xy), 3), np.nan)
    members = np.flatnonzero(track_of >= 0)
    members = members[np.argsort(track_of[members], kind="stable")]
    bounds = np.flatnonzero(np.diff(track_of[members])) + 1
    for obs in track(np.split(members, bounds), "triangulating tracks", enabled=progress):
        if len(obs) < 2:  # no tracks at all (np.split of an empty array gives one empty part)
            continue
        fr = frame_of[obs]
        res = pycolmap.estimate_triangulation(kp_xy[obs], [rigs[k] for k in fr],
                                              [cams[k] for k in fr], opts)
        if res is not None and res["inliers"].sum() >= 2:
            points[obs[res["inliers"]]] = res["xyz"]
    if config.refine_points:
        points = refine_track_points(points, kp_xy, frame_of, track_of, frames)
    # final per-observation check: in front of the camera, within the reprojection bound
    errors = np.full(len(kp_xy), np.nan)
    for k, frame in enumerate(frames):
        sl = slice(offsets[k], offsets[k + 1])
        errors[sl] = reprojection_px(frame.world_from_cam.inverse(), kp_xy[sl], points[sl],
                                     frame.camera.params(), min_depth_m=MIN_DEPTH_M)
    bad = ~(errors <= config.max_reproj_px)
    points[bad] = np.nan
    return points, np.where(bad, np.nan, errors)


def refine_track_points(points: np.ndarray, kp_xy: np.ndarray, frame_of: np.ndarray,
                        track_of: np.ndarray, frames: list[Frame], iterations: int = 10,
                        huber_px: float = 1.0) -> np.ndarray:
    """Each track's world point (metres) moved to minimise the reprojection error (pixels,
    Huber loss) over the observations it was triangulated from (rows of `points` that are
    not NaN, all of a track's rows holding the same point), the frames' poses held fixed:
    Gauss-Newton, one 3x3 system per track, a step kept only where it lowers the track's
    cost. pycolmap's triangulation ends with a linear (algebraic-error) estimate; this is
    the bundle adjustment of the structure alone. Returns a refined copy."""
    obs = np.flatnonzero(~np.isnan(points[:, 0]))
    if len(obs) == 0:
        return points
    tracks, tr = np.unique(track_of[obs], return_inverse=True)
    cam_from_world = [f.world_from_cam.inverse() for f in frames]
    rot = np.stack([c.rotation for c in cam_from_world])[frame_of[obs]]
    trans = np.stack([c.translation for c in cam_from_world])[frame_of[obs]]
    intr = np.array([f.camera.params() for f in frames], np.float64)[frame_of[obs]]
    xy = kp_xy[obs]
    first = np.zeros(len(tracks), np.int64)
    first[tr[::-1]] = np.arange(len(obs))[::-1]  # one row of each track
    pt = points[obs[first]].astype(np.float64)

    def residuals(pt_tracks):
        xc = np.einsum("nij,nj->ni", rot, pt_tracks[tr]) + trans
        z = np.where(xc[:, 2] > 1e-6, xc[:, 2], np.nan)
        uv = xc[:, :2] / z[:, None] * intr[:, :2] + intr[:, 2:]
        return uv - xy, xc, z

    def track_cost(res):
        e = np.nan_to_num(np.linalg.norm(res, axis=1), nan=1e6)
        rho = np.where(e <= huber_px, 0.5 * e ** 2, huber_px * (e - 0.5 * huber_px))
        return np.bincount(tr, rho, len(tracks)), e

    fx, fy = intr[:, 0], intr[:, 1]
    for _ in range(iterations):
        res, xc, z = residuals(pt)
        cost, err = track_cost(res)
        w = np.where(err <= huber_px, 1.0, huber_px / np.maximum(err, 1e-12))
        j_proj = np.zeros((len(obs), 2, 3))
        j_proj[:, 0, 0], j_proj[:, 0, 2] = fx / z, -fx * xc[:, 0] / z ** 2
        j_proj[:, 1, 1], j_proj[:, 1, 2] = fy / z, -fy * xc[:, 1] / z ** 2
        jac = np.nan_to_num(j_proj @ rot)  # d(pixel)/d(world point)
        hess = np.zeros((len(tracks), 3, 3))
        grad = np.zeros((len(tracks), 3))
        np.add.at(hess, tr, w[:, None, None] * np.einsum("nki,nkj->nij", jac, jac))
        np.add.at(grad, tr, w[:, None] * np.einsum("nki,nk->ni", jac, np.nan_to_num(res)))
        hess += 1e-9 * np.eye(3)
        step = -np.linalg.solve(hess, grad[:, :, None])[:, :, 0]
        better = track_cost(residuals(pt + step)[0])[0] < cost
        if not better.any():
            break
        pt = np.where(better[:, None], pt + step, pt)
    out = points.copy()
    out[obs] = pt[tr]
    return out


def depth_points(frame: Frame, keypoints: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Back-project keypoints with registered depth (metres) to world; NaN where invalid or at
    a depth edge (`rgbd.keypoint_points`)."""
    return frame.world_from_cam.transform(keypoint_points(keypoints, depth, frame.camera))


def build_labels(frames: list[Frame], feats: list[Features], depths: list[np.ndarray] | None,
                 config: LabelConfig = LabelConfig(), progress: bool = True) -> LabelSet:
    """Label the keypoints of posed frames. `depths`: registered depth maps (m) or None."""
    pairs = select_pairs([f.world_from_cam for f in frames], config)
    matches = verified_matches(frames, feats, pairs, config, progress)
    track_of = build_tracks(feats, matches)
    tri, errors = triangulate_tracks(frames, feats, track_of, config, progress)
    offsets = np.concatenate([[0], np.cumsum([len(f) for f in feats])])
    points = tri.copy()
    n_depth = n_disagree = 0
    if depths is not None and config.use_depth:
        dep = np.concatenate([depth_points(f, ft.keypoints, d)
                              for f, ft, d in zip(frames, feats, depths)])
        has_dep, has_tri = ~np.isnan(dep[:, 0]), ~np.isnan(tri[:, 0])
        depth_z = np.concatenate([f.world_from_cam.inverse().transform(dep[offsets[k]:offsets[k + 1]])[:, 2]
                                  for k, f in enumerate(frames)])
        gap = np.linalg.norm(dep - tri, axis=1)
        disagree = has_dep & has_tri & ~(gap < config.depth_agreement_m + 0.02 * depth_z)
        # depth refines track points; keypoints seen in one frame only stay unlabelled (they
        # are rarely re-detected, and would spend the regressor's capacity on noise)
        points = np.where(has_dep[:, None] & has_tri[:, None], dep, tri)
        points[disagree] = np.nan
        n_depth, n_disagree = int(has_dep.sum()), int(disagree.sum())
    labelled = ~np.isnan(points[:, 0])
    tracks_kept = track_of[~np.isnan(tri[:, 0])]
    stats = {
        "n_frames": len(frames), "n_pairs": len(pairs), "n_matches": len(matches),
        "n_keypoints": int(offsets[-1]), "n_labelled": int(labelled.sum()),
        "labelled_fraction": float(labelled.mean()) if len(labelled) else 0.0,
        "n_tracks": int(len(np.unique(tracks_kept))),
        "mean_track_length": float(len(tracks_kept) / max(len(np.unique(tracks_kept)), 1)),
        "median_reproj_error_px": float(np.nanmedian(errors)) if np.any(~np.isnan(errors)) else None,
        "n_depth_labels": n_depth, "n_track_depth_disagreements": n_disagree,
    }
    split = lambda a: [a[offsets[k]:offsets[k + 1]] for k in range(len(frames))]  # noqa: E731
    return LabelSet(split(points.astype(np.float32)),
                    split(np.where(np.isnan(tri[:, 0]), -1, track_of)), stats)
