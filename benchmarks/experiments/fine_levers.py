"""Levers for fine accuracy (1 cm / 1 deg), side by side on one map and one set of queries.

    python -m benchmarks.experiments.fine_levers MAP DATASET [--poses FILE] [--split test] --out levers.md

Every variant starts from the same extracted features (extracted once) and is scored against
the poses the map was trained on (the dataset's, or `--poses`, as `evaluate` does). Variants:
- `regressor`: the default localizer (the most confident half of the predictions,
  PnP-RANSAC at 12 px, refinement on the inliers with a Cauchy loss of scale 4 px, then the
  guided refinement on the map's database points near that pose);
- `unguided`: the same without the guided refinement (the default before 2026-12-04); the
  variants below start from its pose where they refine further;
- `refine loss S px`: another scale of that loss (1 px: pycolmap's default, and the
  localizer's before 2026-12-03), also with a tighter gradient tolerance (default 1.0);
- `keep K`: PnP on another share of the predictions;
- `PnP T px`: another RANSAC threshold;
- `re-match`: a second stage that matches each query keypoint to the map's database
  descriptors within `radius` of its predicted world point (ratio test among those), then
  refines the coarse pose on those database points (inliers within 12 px of the coarse pose,
  Levenberg-Marquardt from it), or runs RANSAC on them (`+ RANSAC`);
- `union`: the coarse pose's regressor inliers plus the re-matched database points;
- `scale K x median residual`: the refinement's Cauchy scale set per query to K times the
  median reprojection residual of the RANSAC inliers at the coarse pose;
- `all predictions within T px`: the refinement once more, from the default's pose, on
  every prediction (not only the confident share RANSAC saw) that reprojects within T px of
  it (12 px: the localizer's `refine_on_all`);
- `query SIFT contrast C`: the default localizer on query keypoints detected with a lower
  contrast threshold than the map's (more, weaker keypoints; the map is unchanged);
- `matching`: the classical baseline (nearest database descriptor over the whole map).
`extra ms` is each variant's time beyond extraction, regression and the coarse PnP (for
`matching`: its matching and PnP). Timings are medians per query on one thread.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree

from slamreloc.datasets import load_dataset, read_image
from slamreloc.localize.evaluate import THRESHOLDS, recalls
from slamreloc.features import make_extractor
from slamreloc.geometry import pose_error
from slamreloc.localize.localizer import make_localizer
from slamreloc.geometry import reprojection_px
from slamreloc.localize.pnp import PnPConfig, estimate_pose, refine_from
from slamreloc.map.scene_map import SceneMap


class DatabaseRematcher:
    """Query keypoint -> the database row nearest in descriptor space among the rows whose
    world point (metres) lies within `radius_m` of the keypoint's predicted world point."""

    def __init__(self, scene_map: SceneMap, radius_m: float = 0.1, neighbours: int = 32,
                 ratio: float = 0.9):
        db = scene_map.database
        self.points = db.points.astype(np.float64)
        self.tree = cKDTree(self.points)
        self.descriptors = torch.as_tensor(db.descriptors.astype(np.float32))
        self.radius_m, self.neighbours, self.ratio = radius_m, neighbours, ratio

    def __call__(self, keypoints, descriptors, predicted):
        dist, idx = self.tree.query(predicted.astype(np.float64), k=self.neighbours,
                                    distance_upper_bound=self.radius_m, workers=1)
        valid = np.isfinite(dist)
        idx = np.where(valid, idx, 0)
        q = torch.as_tensor(descriptors, dtype=torch.float32)
        sims = torch.bmm(self.descriptors[torch.as_tensor(idx)], q[:, :, None])[:, :, 0].numpy()
        sims[~valid] = -2
        order = np.argsort(-sims, axis=1)[:, :2]
        s1, s2 = (np.take_along_axis(sims, order[:, i:i + 1], 1)[:, 0] for i in (0, 1))
        j1, j2 = (np.take_along_axis(idx, order[:, i:i + 1], 1)[:, 0] for i in (0, 1))
        d1, d2 = (np.sqrt(np.clip(2 - 2 * s, 0, None)) for s in (s1, s2))
        same = np.linalg.norm(self.points[j1] - self.points[j2], axis=1) < 0.01
        ok = (s1 > -2) & ((d1 < self.ratio * d2) | (s2 <= -2) | same)
        return keypoints[ok].astype(np.float64), self.points[j1[ok]]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("map", type=Path)
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--poses", type=Path, default=None)
    ap.add_argument("--split", default="test")
    ap.add_argument("--out", type=Path, default=Path("levers.md"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    scene_map = SceneMap.load(args.map)
    frames = load_dataset(args.dataset, args.poses).frames(args.split)
    guided = make_localizer(scene_map, "regressor")
    reg = make_localizer(scene_map, "regressor", guided=None)
    on_all = make_localizer(scene_map, "regressor", refine_on_all=True, guided=None)
    matcher = make_localizer(scene_map, "matching")
    rematchers = {r: DatabaseRematcher(scene_map, r) for r in (0.1, 0.2)}
    options = scene_map.info.feature_options
    query_extractors = {} if scene_map.info.feature_name != "sift" else {
        c: make_extractor("sift", **{**options, "contrast_threshold": c})
        for c in (0.006, 0.004) if c < options["contrast_threshold"]}
    scores: dict[str, tuple[list, list]] = {}

    def add(name, world_from_cam, truth, ms=0.0):
        err = pose_error(world_from_cam, truth) if world_from_cam is not None else (np.inf,) * 2
        scores.setdefault(name, ([], []))
        scores[name][0].append(err)
        scores[name][1].append(ms)

    for frame in frames:
        truth, camera = frame.world_from_cam, frame.camera.pinhole
        image = read_image(frame.image_path)
        t0 = time.perf_counter()
        feats = reg.extractor.extract(image, frame.camera)
        extract_ms = 1000 * (time.perf_counter() - t0)
        predicted, _ = reg.predict(feats.descriptors)
        kp, pts, _ = reg.confident_correspondences(feats)
        coarse = estimate_pose(kp, pts, camera, reg.pnp)
        result = guided.localize_features(feats, frame.camera)
        default = reg.localize_features(feats, frame.camera)
        add("regressor (default: guided refinement)", result.estimate.world_from_cam, truth,
            result.timings_ms["pnp"] - default.timings_ms["pnp"])
        add(f"unguided (refine loss {reg.pnp.refine_loss_px:g} px)",
            default.estimate.world_from_cam, truth)
        for contrast, extractor in query_extractors.items():
            t0 = time.perf_counter()
            more = extractor.extract(image, frame.camera)
            extra = 1000 * (time.perf_counter() - t0) - extract_ms
            result = reg.localize_features(more, frame.camera)
            add(f"query SIFT contrast {contrast:g}", result.estimate.world_from_cam, truth,
                extra + result.timings_ms["regressor"] + result.timings_ms["pnp"]
                - default.timings_ms["regressor"] - default.timings_ms["pnp"])
        refined = on_all.localize_features(feats, frame.camera)
        add("all predictions within 12 px (refine_on_all)", refined.estimate.world_from_cam,
            truth, refined.timings_ms["pnp"] - default.timings_ms["pnp"])
        for loss in (1.0, 2.0, 8.0):
            add(f"refine loss {loss:g} px", estimate_pose(
                kp, pts, camera, replace(reg.pnp, refine_loss_px=loss)).world_from_cam, truth)
        add("refine loss 1 px, gradient tolerance 1e-10", estimate_pose(
            kp, pts, camera, replace(reg.pnp, refine_loss_px=1.0,
                                     refine_gradient_tolerance=1e-10)).world_from_cam, truth)
        for keep in (1.0, 0.3):
            reg.keep_fraction = keep
            k2, p2, _ = reg.confident_correspondences(feats)
            add(f"keep {keep}", estimate_pose(k2, p2, camera, reg.pnp).world_from_cam, truth)
        reg.keep_fraction = 0.5
        if coarse.success:
            residual = reprojection_px(coarse.cam_from_world, kp, pts, camera.params())
            med = float(np.median(residual[coarse.inlier_mask]))
            for k in (1.0, 2.0):
                est = refine_from(coarse.cam_from_world, kp, pts, camera,
                                  replace(reg.pnp, refine_loss_px=k * med))
                add(f"scale {k:g} x median residual",
                    est.inverse() if est is not None else coarse.world_from_cam, truth)
            est = refine_from(coarse.cam_from_world, feats.keypoints, predicted, camera,
                              reg.pnp, max_error_px=6.0)
            add("all predictions within 6 px",
                est.inverse() if est is not None else coarse.world_from_cam, truth)
        else:
            for name in ("scale 1 x median residual", "scale 2 x median residual",
                         "all predictions within 6 px"):
                add(name, None, truth)
        for thr in (8.0, 16.0):
            add(f"PnP {thr:.0f} px", estimate_pose(
                kp, pts, camera, replace(reg.pnp, max_error_px=thr)).world_from_cam, truth)
        for radius, rematch in rematchers.items():
            t0 = time.perf_counter()
            k3, p3 = rematch(feats.keypoints, feats.descriptors, predicted)
            t1 = time.perf_counter()
            best = None if not coarse.success else refine_from(coarse.cam_from_world, k3, p3,
                                                               camera, PnPConfig())
            t2 = time.perf_counter()
            est = best.inverse() if best is not None else coarse.world_from_cam
            add(f"re-match {radius} m", est, truth, 1000 * (t2 - t0))
            ransac = estimate_pose(k3, p3, camera, PnPConfig(max_trials=2000))
            t3 = time.perf_counter()
            add(f"re-match {radius} m + RANSAC", ransac.world_from_cam
                if ransac.success else coarse.world_from_cam, truth, 1000 * (t3 - t2 + t1 - t0))
            if coarse.success:
                inl = coarse.inlier_mask
                both = refine_from(coarse.cam_from_world,
                                   np.concatenate([kp[inl].astype(np.float64), k3]),
                                   np.concatenate([pts[inl].astype(np.float64), p3]), camera)
                add(f"union {radius} m", both.inverse() if both is not None
                    else coarse.world_from_cam, truth)
            else:
                add(f"union {radius} m", None, truth)
        t0 = time.perf_counter()
        km, pm = matcher.correspondences(feats)
        est = estimate_pose(km, pm, camera, matcher.pnp)
        add("matching", est.world_from_cam, truth, 1000 * (time.perf_counter() - t0))
        add("matching, refine loss 4 px", estimate_pose(
            km, pm, camera, replace(matcher.pnp, refine_loss_px=4.0)).world_from_cam, truth)

    lines = [(f"map `{args.map}`, {len(frames)} queries of `{args.dataset}` ({args.split}), "
             f"scored against {args.poses or 'the dataset poses'}"), "",
             "| variant | " + " | ".join(THRESHOLDS) + " | median | extra ms |",
             "|---" * (len(THRESHOLDS) + 3) + "|"]
    for name, (errors, ms) in scores.items():
        e = np.array(errors)
        rec = [100 * v for v in recalls(e[:, 0], e[:, 1]).values()]
        lines.append(f"| {name} | " + " | ".join(f"{v:.1f} %" for v in rec) +
                     f" | {100 * np.median(e[:, 0]):.2f} cm / {np.median(e[:, 1]):.3f} deg | "
                     f"{np.median(ms):.1f} |")
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
