"""`update_map`: a map + an unlabelled sequence -> a better, larger map (pseudo-labelling).

1. Features of the unlabelled frames (the map's extractor). Their poses are stripped here:
   nothing below reads them; the truth (the dataset's own poses, or --truth) only scores.
2. Rounds of registration and extension: frames register against the growing correspondence
   database (register.py); then the core labelling code (`build_labels`) triangulates
   multi-view tracks among all registered frames with the *estimated* poses, which labels
   keypoints the map never had (the new area) and joins the database, so the next round can
   register frames further out. A continuity sweep drops registrations that jump.
3. Where the frames have depth, registrations on the map's own labels alone become robust
   priors in the SLAM backend's odometry pose graph (smooth.py), and the chain's registrations
   become priors of the frames without one (`chain_prior_sigma_scale`): odometry is precise
   over short stretches, the chain holds over long ones beyond the map; every frame takes the
   fused pose (frames no registration reached included) and inherits only map labels that fit
   it. Without depth, a final pass
   re-registers every frame against the final database instead. Inherited labels that disagree
   with their own re-triangulation (or registered depth) are dropped, and the tracks are
   triangulated once more with the final poses.
4. The regressor is fine-tuned from its weights (regions moved onto the new area) or retrained,
   on labelled + pseudo-labelled data; NEW_MAP is written atomically with per-point provenance.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from slamreloc.datasets import Dataset, load_dataset
from slamreloc.errors import InputError
from slamreloc.extract import extract_frames
from slamreloc.features import make_extractor
from slamreloc.geometry import Rigid3, pose_error
from slamreloc.labels import LabelConfig, build_labels, depth_points
from slamreloc.scene_map import map_write_lock
from slamreloc.progress import console, track
from slamreloc.pseudo_label.finetune import FinetuneConfig, finetune_regressor
from slamreloc.pseudo_label.register import (LABELLED, NEW, PSEUDO, Database, FrameState,
                                             RegistrationConfig, consistent, continuity_sweep,
                                             label_at_pose, register_frame, register_on,
                                             reprojection_errors)
from slamreloc.pseudo_label.smooth import Prior, smooth_poses
from slamreloc.regressor.model import SceneCoordinateRegressor
from slamreloc.rgbd import registered_depths
from slamreloc.regressor.train import TrainConfig, train_regressor
from slamreloc.scene_map import SURFACE, MapDatabase, SceneMap, check_map_target, save_map
from slamreloc.surface import Surface, extend_surface, frame_cloud
from slamreloc.types import Features, Frame

PROVENANCE = "provenance.npz"
UPDATES = ("finetune", "retrain")


@dataclass(frozen=True)
class PseudoLabelConfig:
    rounds: int = 8  # registration + extension rounds (stops early when nothing changes)
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)
    labels: LabelConfig = field(default_factory=LabelConfig)
    label_agreement_m: float = 0.05  # inherited label vs re-triangulation / depth, + 2 % depth
    depth_required: bool = True  # frames with depth: keypoints without a depth reading unlabelled
    update: str = "finetune"  # or "retrain" (from scratch, the map's own epochs)
    finetune: FinetuneConfig = field(default_factory=FinetuneConfig)
    finetune_epoch_fraction: float = 0.25  # of the map's training epochs, when epochs unset
    epochs: int | None = None  # override for the update (fine-tune or retrain)
    error_scale_px: float = 2.0  # quality weight 1 / (1 + (err / scale)^2)
    smooth: bool = True  # fuse registrations with depth odometry (where frames have depth)
    extend_surface: bool = True  # registered frames' depth joins the map's surface (new area)
    device: str = "auto"


def _frames_for_registration(frames: list[Frame]) -> list[Frame]:
    return [replace(f, world_from_cam=None) for f in frames]  # the truth is not ours to read


def _truth_poses(frames: list[Frame], truth: Path | None) -> list | None:
    """Ground-truth world_from_cam per frame for scoring: from --truth (matched by frame name)
    or the dataset's own pose files; None when not every frame has one."""
    if truth is not None:
        by_name = {f.name: f.world_from_cam for f in load_dataset(truth).frames("all")}
        poses = [by_name.get(f.name) for f in frames]
    else:
        poses = [f.world_from_cam for f in frames]
    return poses if all(p is not None for p in poses) else None


def _label_frames(frames, feats, states, depths, config: PseudoLabelConfig):
    """Triangulate tracks among registered frames with their estimated poses (core labels)."""
    reg = [i for i, s in enumerate(states) if s.registered]
    if len(reg) < 2:
        return reg, None
    posed = [replace(frames[i], world_from_cam=states[i].world_from_cam) for i in reg]
    labels = build_labels(posed, [feats[i] for i in reg],
                          None if depths is None else [depths[i] for i in reg],
                          config.labels, progress=False)
    return reg, labels


def _apply_labels(frames, feats, states, depths, config: PseudoLabelConfig,
                  final: bool = False) -> dict:
    """Merge triangulated labels into the frame states: keypoints without a label get the
    triangulated point (NEW); inherited labels that disagree with it (or with the frame's
    depth) are dropped; in the `final` labelling, with `config.depth_required`, so are the
    labels of keypoints without a depth reading in frames with depth (the rounds before keep
    them: they help register frames further out). Returns counts."""
    reg, labels = _label_frames(frames, feats, states, depths, config)
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
            s.error_px[add] = reprojection_errors(s.world_from_cam, cam, feats[i].keypoints[add],
                                                  tri[add])
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


def _database(base: MapDatabase, feats, states) -> Database:
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
        extension = _apply_labels(frames, feats, states, depths, config)
        after = sum(s.registered for s in states)
        history.append({"round": r + 1, "registered": after, "dropped": len(dropped),
                        "database": len(db), "new_labels": extension["n_new_labels"]})
        console.print(f"round {r + 1}: {after}/{len(frames)} frames registered "
                      f"({len(dropped)} dropped by continuity), database {len(db)} points, "
                      f"{extension['n_new_labels']} keypoints triangulated")
        if after == before and r > 0:
            break
    smoothed = _smooth(frames, feats, states, base, anchored, smoother, config)
    if smoothed is not None:
        states, n_priors = smoothed
        extension = _apply_labels(frames, feats, states, depths, config, final=True)
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
    extension = _apply_labels(frames, feats, states, depths, config, final=True)
    history.append({"round": "final", "registered": sum(s.registered for s in states),
                    "dropped": len(dropped), "database": len(db),
                    "new_labels": extension["n_new_labels"]})
    return states, {"history": history, "extension": extension}


def _smooth(frames, feats, states, base: MapDatabase, anchored: np.ndarray, smoother,
            config: PseudoLabelConfig):
    """Each registered frame is registered again on the map's own labels alone; where that
    holds (enough inliers, near the chain's pose) it becomes a prior of the odometry pose graph,
    independent of the chain (registrations through the sequence's own pseudo-labels drift with
    the chain that made them). The other registered frames give their chain pose as a prior
    `rc.chain_prior_sigma_scale` times less certain: beyond the map the chain drifts less than
    long stretches of odometry. Every frame then takes the graph's pose and inherits only map
    labels that fit it. Returns (states, number of map priors), or None without a smoother."""
    rc = config.registration
    if smoother is None:
        return None
    rows = np.flatnonzero(anchored)
    db = Database(base.descriptors[rows].astype(np.float32), base.points[rows], rows)
    corr = [db.correspondences(f.descriptors, rc) for f in feats]  # for priors and labels
    on_map = [_map_prior(s, f, frame.camera, c, rc) if s.registered else None
              for s, f, frame, c in zip(states, feats, frames, corr)]
    n_priors = sum(p is not None for p in on_map)
    priors = [_graph_prior(p, s, rc) for p, s in zip(on_map, states)]
    poses = smoother(priors) if n_priors else None
    if poses is None:
        return None
    out = []
    for f, s, pose, frame, c in zip(feats, states, poses, frames, corr):
        pose = pose if pose is not None else s.world_from_cam  # off the graph: keep the chain's
        if pose is None:
            out.append(FrameState.empty(len(f)))
            continue
        new = label_at_pose(f, frame.camera, pose, c, rc)
        new.via = s.via if s.registered else "odometry"
        out.append(new)
    return out, n_priors


def _map_prior(state: FrameState, f: Features, camera, corr: tuple,
               rc: RegistrationConfig) -> Rigid3 | None:
    """The frame's registration on its correspondences with the map's labels alone, if it has
    `anchor_inliers` and lies near the chain's pose; else None."""
    on_map = register_on(corr, f, camera, rc)
    if on_map is None or on_map.num_inliers < rc.anchor_inliers:
        return None
    dt, dr = pose_error(on_map.world_from_cam, state.world_from_cam)
    ok = dt <= rc.prior_agreement_m and dr <= rc.prior_agreement_deg
    return on_map.world_from_cam if ok else None


def _graph_prior(on_map: Rigid3 | None, state: FrameState, rc: RegistrationConfig
                 ) -> Prior | None:
    """The frame's prior in the pose graph: its registration on the map's labels, else its
    chain registration with `chain_prior_sigma_scale` times the sigmas (0: none)."""
    if on_map is not None:
        return Prior(on_map)
    if state.registered and rc.chain_prior_sigma_scale > 0:
        return Prior(state.world_from_cam, rc.chain_prior_sigma_scale)
    return None


def _count_new_points(states, extension) -> int:
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
          views: tuple[list[Frame], list[Features]] = ([], [])) -> dict:
    """Pseudo-label precision against the truth of each labelled keypoint: its depth reading
    (registered depth, or depth warped into the RGB camera) lifted with the true pose; where it
    has none, the same keypoints triangulated with the true poses (core labels code: tracks of
    these frames and of the map's labelled `views`, whose wide baselines pin the points down).
    Also the precision against the triangulation alone, and the pose errors of registered
    frames."""
    gt_frames = [replace(f, world_from_cam=p) for f, p in zip(frames, truth_poses)]
    v_frames, v_feats = views
    tri = build_labels([*v_frames, *gt_frames], [*v_feats, *feats], None, label_config,
                       progress=False).points[len(v_frames):]
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


def _base_provenance(map_dir: Path, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The map's own per-point source and weight (all labelled, weight 1, unless it was itself
    updated)."""
    path = map_dir / PROVENANCE
    if path.is_file():
        try:
            with np.load(path) as z:
                if len(z["source"]) == n and len(z["quality"]) == n:
                    return z["source"].astype(np.int8), z["quality"].astype(np.float32)
        except (OSError, KeyError, ValueError):
            pass
        raise InputError(f"{path}: unreadable or does not match the map's database")
    return np.full(n, LABELLED, np.int8), np.ones(n, np.float32)


def _save(out: Path, meta: dict, model, db: MapDatabase, provenance: dict,
          surface: Surface | None) -> Path:
    """The map's own atomic, locked write, with provenance.npz (and the surface) inside it."""
    extra = {PROVENANCE: provenance}
    if surface is not None:
        extra[SURFACE] = surface.to_arrays()
    return save_map(out, meta, model, db, extra=extra)


@dataclass
class PseudoLabels:
    """What registration and extension produced, before the regressor update."""

    old: SceneMap
    map_dir: Path
    db: MapDatabase  # the map's labels + the new ones
    weights: np.ndarray  # per database row
    source: np.ndarray  # per database row: LABELLED, PSEUDO, NEW
    report: dict
    surface: Surface | None = None  # the map's surface, grown by the registered frames


def pseudo_label(map_dir: Path, dataset: Dataset, split: str | None = None,
                 config: PseudoLabelConfig = PseudoLabelConfig(), truth: Path | None = None,
                 progress: bool = True) -> PseudoLabels:
    """Register `dataset`'s split in the map at `map_dir`, label and extend (no training)."""
    map_dir = Path(map_dir)
    if config.update not in UPDATES:
        raise InputError(f"unknown update '{config.update}' (known: {', '.join(UPDATES)})")
    if config.rounds < 1:
        raise InputError(f"--rounds must be at least 1, got {config.rounds}")
    old = SceneMap.load(map_dir)
    base = old.database
    if split is None:
        split = "unlabelled" if "unlabelled" in dataset.roles.values() else "all"
    frames_in = dataset.frames(split)
    if len(frames_in) < 2:
        raise InputError(f"{dataset.root}: split '{split}' has {len(frames_in)} frames; "
                         "pseudo-labelling needs a sequence")
    frames = _frames_for_registration(frames_in)
    truth_poses = _truth_poses(frames_in, truth)
    timings = {}
    t_all = time.perf_counter()
    feat_cfg = dict(old.meta["features"])
    extractor = make_extractor(feat_cfg.pop("name"), **feat_cfg)
    t0 = time.perf_counter()
    feats = extract_frames(frames, extractor, progress)
    timings["features_s"] = time.perf_counter() - t0
    depths = registered_depths(dataset, frames) if config.labels.use_depth else None
    base_source, base_quality = _base_provenance(map_dir, len(base.points))

    def smoother(priors):
        res = smooth_poses(dataset, frames, priors, progress) if config.smooth else None
        return None if res is None else res.world_from_cam

    t0 = time.perf_counter()
    states, reg_stats = register_sequence(frames, feats, base, depths, config, progress,
                                          base_source == LABELLED, smoother)
    timings["registration_s"] = time.perf_counter() - t0
    reg = [i for i, s in enumerate(states) if s.registered]
    n_pseudo = int(sum((s.source == PSEUDO).sum() for s in states))
    n_new_obs = int(sum((s.source == NEW).sum() for s in states))
    n_new_points = _count_new_points(states, reg_stats["extension"])

    # training set: the map's labels + every label of the registered frames, quality-weighted
    lab_idx = [np.flatnonzero(states[i].source >= 0) for i in reg]
    new_desc = [feats[i].descriptors[k] for i, k in zip(reg, lab_idx)]
    new_pts = [states[i].points[k] for i, k in zip(reg, lab_idx)]
    new_err = np.concatenate([states[i].error_px[k] for i, k in zip(reg, lab_idx)] or [[]])
    new_src = np.concatenate([states[i].source[k] for i, k in zip(reg, lab_idx)] or [[]])
    n_old_frames = len(base.frame_names)
    db = MapDatabase(
        descriptors=np.concatenate([base.descriptors, *[d.astype(np.float16) for d in new_desc]]),
        points=np.concatenate([base.points, *new_pts]).astype(np.float32),
        keypoints=np.concatenate([base.keypoints, *[feats[i].keypoints[k]
                                                     for i, k in zip(reg, lab_idx)]]),
        frame_index=np.concatenate([base.frame_index, *[np.full(len(k), n_old_frames + r)
                                                        for r, k in enumerate(lab_idx)]]),
        frame_names=[*base.frame_names, *[frames[i].name for i in reg]],
        world_from_cam=np.concatenate([base.world_from_cam.reshape(-1, 4, 4),
                                       np.stack([states[i].world_from_cam.matrix() for i in reg])
                                       if reg else np.zeros((0, 4, 4))]))
    quality = 1.0 / (1.0 + (np.nan_to_num(new_err, nan=config.registration.label_max_error_px)
                            / config.error_scale_px) ** 2)
    weights = np.concatenate([base_quality, quality]).astype(np.float32)
    source = np.concatenate([base_source, new_src]).astype(np.int8)
    surface = old.surface
    if surface is not None and config.extend_surface:
        surface = extend_surface(surface, [(states[i].world_from_cam,
                                            frame_cloud(frames[i], dataset))
                                           for i in reg if frames[i].depth_path is not None])
    timings["pseudo_label_s"] = time.perf_counter() - t_all

    report = {
        "map": str(map_dir.resolve()),
        "dataset": {"root": str(Path(dataset.root).resolve()), "split": split},
        "n_frames": len(frames), "n_frames_registered": len(reg),
        "registered_fraction": len(reg) / len(frames),
        "n_pseudo_labels": n_pseudo + n_new_obs,
        "n_inherited_labels": n_pseudo, "n_triangulated_labels": n_new_obs,
        "n_new_points": n_new_points,
        "n_database_before": int(len(base.points)), "n_database_after": int(len(db.points)),
        "rounds": reg_stats["history"], "timings_s": timings,
        "registered_via": {v: sum(s.via == v for s in states if s.registered)
                           for v in ("database", "neighbours", "both", "odometry")},
        "n_surface_points_before": 0 if old.surface is None else len(old.surface.points),
        "n_surface_points_after": 0 if surface is None else len(surface.points),
        "poses": {frames[i].name: states[i].world_from_cam.matrix().tolist() for i in reg},
    }
    if truth_poses is not None:
        t0 = time.perf_counter()
        labelled_rows = np.flatnonzero(base_source == LABELLED)
        # the reference uses the core's default labelling, whatever the update's settings
        truth_depths = depths if depths is not None else registered_depths(dataset, frames)
        report.update(score(frames, feats, states, truth_poses, truth_depths, LabelConfig(),
                            map_views(base, old.camera, labelled_rows)))
        report["timings_s"]["scoring_s"] = time.perf_counter() - t0
    else:
        report["pseudo_label_precision_10cm"] = None
        report["note"] = "the dataset has no poses: precision and pose errors not scored"
    return PseudoLabels(old, map_dir, db, weights, source, report, surface)


def write_updated_map(labels: PseudoLabels, out: Path,
                      config: PseudoLabelConfig = PseudoLabelConfig(),
                      progress: bool = True) -> tuple[SceneMap, dict]:
    """Update the regressor (fine-tune or retrain) and write NEW_MAP; returns it and the
    report (with the update's stats and timing)."""
    out = Path(out)
    if out.resolve() == labels.map_dir.resolve():
        raise InputError(f"{out}: the new map must not replace the map it updates")
    check_map_target(out)
    old, db, rep = labels.old, labels.db, dict(labels.report)
    rep["timings_s"] = dict(rep["timings_s"])
    map_epochs = int(old.meta.get("train", {}).get("epochs", 100))
    t0 = time.perf_counter()
    if config.update == "finetune":
        # a fresh copy of the old weights: the old map's files and object stay as they were
        model = SceneMap.load(labels.map_dir).regressor
        epochs = config.epochs or max(1, round(config.finetune_epoch_fraction * map_epochs))
        train_stats = finetune_regressor(model, db.descriptors, db.points, labels.weights,
                                         replace(config.finetune, epochs=epochs), config.device,
                                         progress)
    else:
        model = SceneCoordinateRegressor(old.regressor.config)
        # the map's own training settings, except its precision: that was resolved for the
        # machine that trained it (bf16 recorded on an AMX machine would be emulated, ~30x
        # slower, on an AVX2-only one); this machine chooses its own
        known = set(TrainConfig.__dataclass_fields__) - {"betas", "precision"}
        tc = TrainConfig(**{k: v for k, v in old.meta.get("train", {}).items() if k in known})
        tc = replace(tc, epochs=config.epochs or map_epochs)
        train_stats = {"mode": "retrain", **train_regressor(
            model, db.descriptors, db.points, tc, config.device, progress,
            weights=labels.weights)}
    rep["timings_s"]["update_s"] = time.perf_counter() - t0
    rep["timings_s"]["total_s"] = rep["timings_s"]["pseudo_label_s"] + rep["timings_s"]["update_s"]
    rep["update"] = train_stats
    rep["new_map"] = str(out.resolve())
    meta = {k: v for k, v in old.meta.items() if k not in ("format", "version", "frame_names")}
    meta["labels"] = {**old.meta.get("labels", {}), "n_labelled": int(len(db.points)),
                      "n_labelled_map": int(len(old.database.points)),
                      "n_pseudo": rep["n_inherited_labels"],
                      "n_triangulated": rep["n_triangulated_labels"]}
    meta["train"] = {**old.meta.get("train", {}), "update": train_stats}
    meta["pseudo_label"] = {
        "source_map": str(labels.map_dir.resolve()), "dataset": rep["dataset"],
        "n_frames": rep["n_frames"], "n_frames_registered": rep["n_frames_registered"],
        "n_inherited_labels": rep["n_inherited_labels"],
        "n_triangulated_labels": rep["n_triangulated_labels"],
        "n_new_points": rep["n_new_points"], "update": config.update,
        "provenance": f"{PROVENANCE}: source per database row (0 labelled, 1 inherited "
                      "pseudo-label, 2 triangulated from registered frames), quality weight",
        "history": old.meta.get("pseudo_label", {}).get("history", [])
        + [str(labels.map_dir.resolve())],
    }
    if labels.surface is not None:
        meta["surface"] = {**old.meta.get("surface", {}), "n_points": len(labels.surface.points)}
    _save(out, meta, model, db, {"source": labels.source, "quality": labels.weights},
          labels.surface)
    return SceneMap.load(out), rep


def update_map(map_dir: Path, dataset: Dataset, out: Path, split: str | None = None,
               config: PseudoLabelConfig = PseudoLabelConfig(), truth: Path | None = None,
               progress: bool = True) -> tuple[SceneMap, dict]:
    """Pseudo-label `dataset`'s split against the map at `map_dir`, write NEW_MAP at `out`.
    Returns (the new map, the report). NEW_MAP's write lock is held from the start: a second
    writer of it fails at once, not after the work."""
    map_dir, out = Path(map_dir), Path(out)
    SceneMap.load(map_dir)  # fail early on a bad map or target, before the work
    if out.resolve() == map_dir.resolve():
        raise InputError(f"{out}: the new map must not replace the map it updates")
    with map_write_lock(out):
        check_map_target(out)
        labels = pseudo_label(map_dir, dataset, split, config, truth, progress)
        return write_updated_map(labels, out, config, progress)
