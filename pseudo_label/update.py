"""`update_map`: a map + an unlabelled sequence -> a better, larger map (pseudo-labelling).

1. Features of the unlabelled frames (the map's extractor). Their poses are stripped here:
   nothing below reads them; the truth (the dataset's own poses, or another dataset's)
   only scores (score.py).
2. Rounds of registration and extension (rounds.py): frames register against the growing
   correspondence database (register.py); then the core labelling code (`build_labels`)
   triangulates multi-view tracks among all registered frames with the *estimated* poses,
   which labels keypoints the map never had (the new area) and joins the database (merge.py),
   so the next round can register frames further out. A continuity sweep drops registrations
   that jump.
3. Where the frames have depth, registrations on the map's own labels alone become robust
   priors in the SLAM backend's odometry pose graph (smooth.py), and the chain's registrations
   become priors of the frames without one (`chain_prior_sigma_scale`): odometry is precise
   over short stretches, the chain holds over long ones beyond the map; every frame takes the
   fused pose (frames no registration reached included) and inherits only map labels that fit
   it. Without depth, a final pass re-registers every frame against the final database
   instead. Inherited labels that disagree with their own re-triangulation (or registered
   depth) are dropped, and the tracks are triangulated once more with the final poses.
4. The regressor is fine-tuned from its weights (regions moved onto the new area) or retrained,
   on labelled + pseudo-labelled data; NEW_MAP is written atomically with per-point provenance
   (write.py).
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from slamreloc.pseudo_label.config import PseudoLabelConfig
from slamreloc.pseudo_label.merge import count_new_points
from slamreloc.pseudo_label.rounds import register_sequence
from slamreloc.pseudo_label.score import map_views, score
from slamreloc.pseudo_label.smooth import smooth_poses
from slamreloc.pseudo_label.write import PseudoLabels, base_provenance, write_updated_map

from slamreloc.datasets import Dataset
from slamreloc.errors import InputError
from slamreloc.features.extract import extract_frames
from slamreloc.features import make_extractor
from slamreloc.map.labels import LabelConfig
from slamreloc.map.format import LABELLED, NEW, PSEUDO
from slamreloc.map.joining import check_joining, refuse_held
from slamreloc.map.lock import map_write_lock
from slamreloc.map.write import check_map_target
from slamreloc.rgbd import registered_depths
from slamreloc.map.scene_map import MapDatabase, SceneMap
from slamreloc.map.surface import extend_surface, frame_cloud
from slamreloc.types import Frame


def _frames_for_registration(frames: list[Frame]) -> list[Frame]:
    return [replace(f, world_from_cam=None) for f in frames]  # the truth is not ours to read


def _truth_poses(dataset: Dataset, frames: list[Frame], truth: Dataset | None
                 ) -> tuple[list | None, str]:
    """Ground-truth world_from_cam per frame for scoring (None when not every frame has one)
    and where it comes from: `truth`'s poses, matched by frame name, else `dataset`'s own."""
    if truth is None:
        poses, source = [f.world_from_cam for f in frames], "dataset"
    else:
        by_name = {f.name: f.world_from_cam for f in truth.frames("all")}
        poses = [by_name.get(f.name) for f in frames]
        source = (truth.poses_source if truth.poses_source != "dataset"
                  else str(Path(truth.root).resolve()))
    return (poses if all(p is not None for p in poses) else None), source


def pseudo_label(old: SceneMap, dataset: Dataset, split: str | None = None,
                 config: PseudoLabelConfig = PseudoLabelConfig(), truth: Dataset | None = None,
                 progress: bool = True) -> PseudoLabels:
    """Register `dataset`'s split (default: its 'unlabelled' role, else all) in the map `old`,
    label and extend (no training). The report is scored against `truth`'s poses (a dataset
    holding the same frames, matched by name), else `dataset`'s own; neither is read
    otherwise."""
    base = old.database
    if split is None:
        split = "unlabelled" if "unlabelled" in dataset.roles.values() else "all"
    frames_in = dataset.frames(split)
    if len(frames_in) < 2:
        raise InputError(f"{dataset.root}: split '{split}' has {len(frames_in)} frames; "
                         "pseudo-labelling needs a sequence")
    held = check_joining(old, old.root, dataset, frames_in)  # one camera, names apart
    pictures = dict(zip((f.name for f in frames_in),  # each frame once (by name or picture)
                        refuse_held(old.root, dataset, frames_in, held)))
    frames = _frames_for_registration(frames_in)
    truth_world_from_cam, reference = _truth_poses(dataset, frames_in, truth)
    timings = {}
    t_all = time.perf_counter()
    extractor = make_extractor(old.info.feature_name, **old.info.feature_options)
    t0 = time.perf_counter()
    feats = extract_frames(frames, extractor, progress)
    timings["features_s"] = time.perf_counter() - t0
    depths = registered_depths(dataset, frames) if config.labels.use_depth else None
    base_source, base_quality = base_provenance(old)

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
    n_new_points = count_new_points(states, reg_stats["extension"])

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
                                       if reg else np.zeros((0, 4, 4))]),
        frame_pictures=[*(base.frame_pictures or [""] * n_old_frames),
                        *[pictures[frames[i].name] for i in reg]])
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
        "map": str(Path(old.root).resolve()),
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
        # what the scores below are against: "dataset", --truth's folder or the --poses file
        "reference": reference,
    }
    if truth_world_from_cam is not None:
        t0 = time.perf_counter()
        labelled_rows = np.flatnonzero(base_source == LABELLED)
        # the reference uses the core's default labelling, whatever the update's settings
        truth_depths = depths if depths is not None else registered_depths(dataset, frames)
        report.update(score(frames, feats, states, truth_world_from_cam, truth_depths,
                            LabelConfig(),
                            map_views(base, old.camera, labelled_rows), progress))
        report["timings_s"]["scoring_s"] = time.perf_counter() - t0
    else:
        report["pseudo_label_precision_10cm"] = None
        report["note"] = "the dataset has no poses: precision and pose errors not scored"
    return PseudoLabels(old, db, weights, source, report, surface)


def update_map(old: SceneMap, dataset: Dataset, out: Path, split: str | None = None,
               config: PseudoLabelConfig = PseudoLabelConfig(), truth: Dataset | None = None,
               progress: bool = True, report: Path | None = None) -> tuple[SceneMap, dict]:
    """Pseudo-label `dataset`'s split against the map `old`, write NEW_MAP at `out` (`old`'s
    folder is kept). Returns (the new map, the report). NEW_MAP's write lock is held from the
    start: a second writer of it fails at once, not after the work. `split`, `truth`:
    `pseudo_label`; `report`: write the report there, together with the map."""
    out = Path(out)
    with map_write_lock(out):
        check_map_target(out)
        labels = pseudo_label(old, dataset, split, config, truth, progress)
        return write_updated_map(labels, out, config, progress, report)
