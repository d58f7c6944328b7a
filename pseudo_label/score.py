"""Scoring pseudo-labels and registered poses against the truth (never used to make them)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from slamreloc.geometry import Rigid3, pose_error
from slamreloc.map.labels import LabelConfig, build_labels, depth_points
from slamreloc.map.format import NEW, PSEUDO
from slamreloc.map.scene_map import MapDatabase
from slamreloc.types import Features, Frame


def map_views(base: MapDatabase, camera, rows: np.ndarray) -> tuple[list[Frame], list[Features]]:
    """The map's labelled frames as posed frames with their labelled keypoints (database rows
    `rows` only): views the truth can be triangulated with."""
    frames, feats = [], []
    fi = base.frame_index[rows]
    for k in np.unique(fi):
        sel = rows[fi == k]
        frames.append(Frame(base.frame_names[k], Path(""), camera,
                            world_from_cam=Rigid3.from_matrix(base.world_from_cam[k])))
        feats.append(Features(base.keypoints[sel].astype(np.float32),
                              base.descriptors[sel].astype(np.float32)))
    return frames, feats


def score(frames, feats, states, truth_poses, depths, label_config: LabelConfig,
          views: tuple[list[Frame], list[Features]] = ([], []), progress: bool = False) -> dict:
    """Pseudo-label precision against the truth of each labelled keypoint: its depth reading
    (registered depth, or depth warped into the RGB camera) lifted with the true pose; where it
    has none, the same keypoints triangulated with the true poses (core labels code: tracks of
    these frames and of the map's labelled `views`, whose wide baselines pin the points down).
    Also the precision against the triangulation alone, and the pose errors of registered
    frames. `progress`: the reference triangulation's bars."""
    gt_frames = [replace(f, world_from_cam=p) for f, p in zip(frames, truth_poses)]
    v_frames, v_feats = views
    tri = build_labels([*v_frames, *gt_frames], [*v_feats, *feats], None, label_config,
                       progress=progress).points[len(v_frames):]
    errs = {PSEUDO: [], NEW: []}
    tri_errs, n_by_depth, n_labels = [], 0, 0
    for i, s in enumerate(states):
        lab = s.source >= 0
        n_labels += int(lab.sum())
        truth = tri[i]
        if depths is not None and frames[i].depth_path is not None:
            dep = depth_points(gt_frames[i], feats[i].keypoints, depths[i])
            has_dep = ~np.isnan(dep[:, 0])
            n_by_depth += int((lab & has_dep).sum())
            truth = np.where(has_dep[:, None], dep, truth)
        ok = lab & ~np.isnan(truth[:, 0])
        e = np.linalg.norm(s.points[ok] - truth[ok], axis=1)
        for src in (PSEUDO, NEW):
            errs[src].append(e[s.source[ok] == src])
        ok_tri = lab & ~np.isnan(tri[i][:, 0])
        tri_errs.append(np.linalg.norm(s.points[ok_tri] - tri[i][ok_tri], axis=1))
    e_all = np.concatenate(errs[PSEUDO] + errs[NEW])
    e_tri = np.concatenate(tri_errs)
    per = {src: np.concatenate(v) for src, v in errs.items()}
    pose_t, pose_r = [], []
    for s, p in zip(states, truth_poses):
        if s.registered:
            dt, dr = pose_error(s.world_from_cam, p)
            pose_t.append(dt)
            pose_r.append(dr)
    pose_t, pose_r = np.array(pose_t), np.array(pose_r)
    prec = lambda e: float(np.mean(e < 0.10)) if len(e) else None  # noqa: E731
    return {
        "pseudo_label_precision_10cm": prec(e_all),
        "pseudo_label_precision_5cm": float(np.mean(e_all < 0.05)) if len(e_all) else None,
        "precision_inherited_10cm": prec(per[PSEUDO]),
        "precision_new_10cm": prec(per[NEW]),
        "n_pseudo_labels_scored": int(len(e_all)),
        "scored_fraction": float(len(e_all) / max(n_labels, 1)),
        "n_scored_by_depth": n_by_depth,
        "precision_triangulation_reference_10cm": prec(e_tri),
        "n_scored_by_triangulation_reference": int(len(e_tri)),
        "median_label_error_m": float(np.median(e_all)) if len(e_all) else None,
        "median_pose_error_m": float(np.median(pose_t)) if len(pose_t) else None,
        "median_pose_error_deg": float(np.median(pose_r)) if len(pose_r) else None,
        "registered_within_5cm2deg": float(np.mean((pose_t <= 0.05) & (pose_r <= 2.0)))
        if len(pose_t) else None,
        "max_pose_error_m": float(pose_t.max()) if len(pose_t) else None,
    }
