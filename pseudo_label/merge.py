"""Labels of the registered frames from the core's triangulation, merged with the inherited ones.

The core labelling code (`build_labels`) triangulates multi-view tracks among the registered
frames with their *estimated* poses: keypoints without a label take the triangulated point
(NEW); inherited labels (PSEUDO) that disagree with it, or with the frame's depth, are dropped.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from slamreloc.map.labels import MIN_DEPTH_M, build_labels, depth_points
from slamreloc.map.format import NEW, PSEUDO
from slamreloc.geometry import reprojection_px
from slamreloc.pseudo_label.config import PseudoLabelConfig


def label_frames(frames, feats, states, depths, config: PseudoLabelConfig,
                 progress: bool = False):
    """Triangulate tracks among registered frames with their estimated poses (core labels)."""
    reg = [i for i, s in enumerate(states) if s.registered]
    if len(reg) < 2:
        return reg, None
    posed = [replace(frames[i], world_from_cam=states[i].world_from_cam) for i in reg]
    labels = build_labels(posed, [feats[i] for i in reg],
                          None if depths is None else [depths[i] for i in reg],
                          config.labels, progress=progress)
    return reg, labels


def apply_labels(frames, feats, states, depths, config: PseudoLabelConfig,
                 final: bool = False, progress: bool = False) -> dict:
    """Merge triangulated labels into the frame states: keypoints without a label get the
    triangulated point (NEW); inherited labels that disagree with it (or with the frame's
    depth) are dropped; in the `final` labelling, with `config.depth_required`, so are the
    labels of keypoints without a depth reading in frames with depth (the rounds before keep
    them: they help register frames further out). Returns counts. `progress`: the
    labelling's bars."""
    reg, labels = label_frames(frames, feats, states, depths, config, progress)
    n_new = n_conflict = n_unread = 0
    for k, i in enumerate(reg):
        s = states[i]
        cam = frames[i].camera
        z = None
        if labels is not None:
            tri = labels.points[k]
            has_tri = ~np.isnan(tri[:, 0])
            inh = s.source == PSEUDO
            if np.any(has_tri & inh):
                z = s.world_from_cam.inverse().transform(tri)[:, 2]
                gap = np.linalg.norm(tri - s.points, axis=1)
                bad = has_tri & inh & ~(gap < config.label_agreement_m + 0.02 * np.abs(z))
                n_conflict += int(bad.sum())
                s.drop(bad)
            add = has_tri & (s.source < 0)
            s.points[add] = tri[add]
            s.source[add] = NEW
            s.error_px[add] = reprojection_px(s.world_from_cam.inverse(), feats[i].keypoints[add],
                                              tri[add], cam.params(), min_depth_m=MIN_DEPTH_M)
            n_new += int(add.sum())
        if depths is not None and frames[i].depth_path is not None:
            # the frame's depth verifies every label
            dep = depth_points(replace(frames[i], world_from_cam=s.world_from_cam),
                               feats[i].keypoints, depths[i])
            z = s.world_from_cam.inverse().transform(dep)[:, 2]
            has = ~np.isnan(dep[:, 0])
            gap = np.linalg.norm(dep - s.points, axis=1)
            bad = has & (s.source >= 0) & ~(gap < config.label_agreement_m + 0.02 * np.abs(z))
            n_conflict += int(bad.sum())
            unread = ~has & (s.source >= 0) & (final and config.depth_required)
            n_unread += int(unread.sum())
            s.drop(bad | unread)
    return {"n_new_labels": n_new, "n_conflicts": n_conflict, "n_without_depth": n_unread,
            "track_ids": None if labels is None else (reg, labels.track_ids)}


def count_new_points(states, extension) -> int:
    """Triangulated tracks none of whose observations inherited a map label."""
    if not extension or extension.get("track_ids") is None:
        return 0
    reg, tids = extension["track_ids"]
    ids, srcs = [], []
    for k, i in enumerate(reg):
        t = tids[k]
        keep = (t >= 0) & (states[i].source >= 0)
        ids.append(t[keep])
        srcs.append(states[i].source[keep])
    ids, srcs = np.concatenate(ids), np.concatenate(srcs)
    if len(ids) == 0:
        return 0
    has_pseudo = np.zeros(ids.max() + 1, bool)
    has_pseudo[ids[srcs == PSEUDO]] = True
    new_ids = np.unique(ids[srcs == NEW])
    return int((~has_pseudo[new_ids]).sum())
