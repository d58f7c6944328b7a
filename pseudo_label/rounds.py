"""Rounds of registration and extension of an unlabelled sequence in the map frame.

Frames register against the growing correspondence database (the map's labels plus the
sequence's own, register.py); then the registered frames' tracks are triangulated with the
estimated poses (merge.py), which labels keypoints the map never had (the new area) and joins
the database, so the next round can register frames further out. A continuity sweep drops
registrations that jump. At the end the registrations are fused with depth odometry where the
frames have depth (smooth.py), else every frame is registered once more against the final
database.
"""

from __future__ import annotations

import numpy as np

from slamreloc.runtime.progress import console, track
from slamreloc.pseudo_label.config import PseudoLabelConfig
from slamreloc.pseudo_label.merge import apply_labels
from slamreloc.pseudo_label.register import (Database, FrameState, consistent,
                                             continuity_sweep, register_frame)
from slamreloc.pseudo_label.smooth import smooth_states
from slamreloc.map.scene_map import MapDatabase
from slamreloc.types import Frame


def _database(base: MapDatabase, feats, states) -> Database:
    """The map's labels plus every label of the registered frames (with their map rows)."""
    extra_d = [feats[i].descriptors[s.source >= 0] for i, s in enumerate(states) if s.registered]
    extra_p = [s.points[s.source >= 0] for s in states if s.registered]
    extra_r = [s.row[s.source >= 0] for s in states if s.registered]
    return Database(np.concatenate([base.descriptors.astype(np.float32), *extra_d]),
                    np.concatenate([base.points, *extra_p]),
                    np.concatenate([np.arange(len(base.points)), *extra_r]))


def register_sequence(frames: list[Frame], feats, base: MapDatabase, depths,
                      config: PseudoLabelConfig, progress: bool = True,
                      anchored: np.ndarray | None = None, smoother=None):
    """Register frames (poses unknown) and label their keypoints. Returns (states, stats).

    anchored: per map database row, whether it is one of the map's own (true-pose) labels
    (default: all). smoother: `priors -> poses` (per frame world_from_cam or None), the
    odometry + pose-graph fusion of smooth.py; without it every frame is re-registered alone."""
    anchored = np.ones(len(base.points), bool) if anchored is None else anchored
    rc = config.registration
    cameras = [f.camera for f in frames]
    states = [FrameState.empty(len(f)) for f in feats]
    history = []
    extension = {}
    tried: dict[int, tuple] = {}  # frame -> (database size, registered neighbours) at its last try

    def context(i: int, db_size: int) -> tuple:
        """A failed frame is tried again when a neighbour registered or the database grew by
        a quarter since its last try."""
        lo, hi = max(0, i - rc.window), min(len(states), i + rc.window + 1)
        nb = tuple(j for j in range(lo, hi) if states[j].registered)
        last = tried.get(i)
        if last is not None and last[1] == nb and db_size < 1.25 * last[0]:
            return last
        return db_size, nb

    for r in range(max(1, config.rounds)):
        db = _database(base, feats, states)
        before = sum(s.registered for s in states)
        # forward then backward through the sequence, so registrations propagate both ways
        order = list(range(len(frames))) + list(range(len(frames) - 1, -1, -1))
        for i in track(order, f"registering, round {r + 1}", enabled=progress):
            if states[i].registered:
                continue
            ctx = context(i, len(db))
            if tried.get(i) == ctx:  # nothing it could match has changed since it failed
                continue
            tried[i] = ctx
            new = register_frame(i, feats, cameras, states, db, rc)
            if new is not None and consistent(i, new.world_from_cam, states, rc, new.num_inliers):
                states[i] = new
        dropped = continuity_sweep(states, rc)
        extension = apply_labels(frames, feats, states, depths, config, progress=progress)
        after = sum(s.registered for s in states)
        history.append({"round": r + 1, "registered": after, "dropped": len(dropped),
                        "database": len(db), "new_labels": extension["n_new_labels"]})
        console.print(f"round {r + 1}: {after}/{len(frames)} frames registered "
                      f"({len(dropped)} dropped by continuity), database {len(db)} points, "
                      f"{extension['n_new_labels']} keypoints triangulated")
        if after == before and r > 0:
            break
    smoothed = smooth_states(frames, feats, states, base, anchored, smoother,
                             config.registration, progress)
    if smoothed is not None:
        states, n_priors = smoothed
        extension = apply_labels(frames, feats, states, depths, config, final=True,
                                 progress=progress)
        history.append({"round": "smoothed", "registered": sum(s.registered for s in states),
                        "priors": n_priors, "dropped": 0, "database": len(base.points),
                        "new_labels": extension["n_new_labels"]})
        return states, {"history": history, "extension": extension}
    # final pass: every registered frame again against the final database and its neighbours
    db = _database(base, feats, states)
    for i in track(range(len(frames)), "final registration", enabled=progress):
        if not states[i].registered:
            continue
        new = register_frame(i, feats, cameras, states, db, rc)
        ok = new is not None and consistent(i, new.world_from_cam, states, rc, new.num_inliers)
        states[i] = new if ok else FrameState.empty(len(feats[i]))
    dropped = continuity_sweep(states, rc)
    extension = apply_labels(frames, feats, states, depths, config, final=True,
                                 progress=progress)
    history.append({"round": "final", "registered": sum(s.registered for s in states),
                    "dropped": len(dropped), "database": len(db),
                    "new_labels": extension["n_new_labels"]})
    return states, {"history": history, "extension": extension}
