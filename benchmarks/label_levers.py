"""Label levers and the spread of training, side by side: one map per variant, the regressor
and the matching baseline on the same queries.

    python -m benchmarks.label_levers DATASET [--poses FILE] --workdir W [--variants ...] \
        --out labels.md

Variants (each a map in WORKDIR/map-<name>, reused when it is there):
- `default`, `seed1`, `seed2`: today's labels, training seeds 0, 1 and 2 (the spread of one
  training);
- `ba`, `ba-seed1`: track points bundle-adjusted with the poses fixed
  (`LabelConfig.refine_points`);
- `angle4`: tracks triangulated at >= 4 deg only (`LabelConfig.min_tri_angle_deg`, default 2);
- `sift-full`: SIFT on OpenCV's doubled first octave (`upsample`), for map and queries: finer
  keypoint localisation at ~3x the extraction time.

Scored against the poses the maps are trained on (the dataset's, or `--poses`). Features of
the queries are extracted once per feature setting (its time per query is a column); one
torch thread. The regressor is the default localizer;
matching is the classical baseline on the same map's labelled database.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from slamreloc.localize import evaluate
from slamreloc.datasets import load_dataset, read_image
from slamreloc.localize.evaluate import THRESHOLDS
from slamreloc.geometry import pose_error
from slamreloc.localize.localizer import METHODS, make_localizer
from slamreloc.map.build import MapConfig, build_map
from slamreloc.map.scene_map import SceneMap

VARIANTS = {  # name: (LabelConfig fields, TrainConfig fields, feature options)
    "default": ({}, {}, {}),
    "seed1": ({}, {"seed": 1}, {}),
    "seed2": ({}, {"seed": 2}, {}),
    "ba": ({"refine_points": True}, {}, {}),
    "ba-seed1": ({"refine_points": True}, {"seed": 1}, {}),
    "angle4": ({"min_tri_angle_deg": 4.0}, {}, {}),
    "sift-full": ({}, {}, {"upsample": True}),
}


def variant_map(dataset, name: str, workdir: Path) -> SceneMap:
    out = workdir / f"map-{name}"
    if SceneMap.is_map(out):
        return SceneMap.load(out)
    labels, train, features = VARIANTS[name]
    config = MapConfig(feature_options=features)
    config.labels = replace(config.labels, **labels)
    config.train = replace(config.train, **train)
    return build_map(dataset, out, "train", config)


def query_features(frames, scene_map: SceneMap) -> tuple[list, float]:
    """The queries' features with the map's extractor, one image at a time, and the median
    extraction time per image (ms, image decoding excluded)."""
    extractor = make_localizer(scene_map, "regressor").extractor
    feats, ms = [], []
    for frame in frames:
        image = read_image(frame.image_path)
        t0 = time.perf_counter()
        feats.append(extractor.extract(image, frame.camera))
        ms.append(1000 * (time.perf_counter() - t0))
    return feats, float(np.median(ms))


def method_errors(scene_map: SceneMap, method: str, frames, feats, **options) -> np.ndarray:
    """(N, 2) translation (m) and rotation (deg) errors of one localization method
    (`make_localizer` options) over the queries; inf where it failed."""
    loc = make_localizer(scene_map, method, **options)
    errors = []
    for frame, f in zip(frames, feats):
        est = loc.localize_features(f, frame.camera).estimate
        errors.append(pose_error(est.world_from_cam, frame.world_from_cam)
                      if est.success else (np.inf, np.inf))
    return np.array(errors, dtype=float)


def score_method(scene_map: SceneMap, method: str, frames, feats, **options) -> str:
    """Recalls and median of one localization method over the queries (a table's cells)."""
    return scores(method_errors(scene_map, method, frames, feats, **options))


def recalls(errors: np.ndarray) -> list[float]:
    """Per cent of queries within each of evaluate.THRESHOLDS, for (N, 2) errors."""
    e = np.asarray(errors, dtype=float)
    return [100 * v for v in evaluate.recalls(e[:, 0], e[:, 1]).values()]


def summary(errors: np.ndarray) -> list[float]:
    """`recalls` and the median translation error (cm), for (N, 2) errors."""
    return recalls(errors) + [100 * float(np.median(np.asarray(errors, dtype=float)[:, 0]))]


def median_rows(rows: dict[str, list[list[float]]]) -> list[str]:
    """Table rows `| median of n | name | | recalls | median cm |`: the median over runs of
    each name's `summary` values."""
    lines = []
    for name, values in rows.items():
        med = np.median(np.array(values), axis=0)
        lines.append(f"| median of {len(values)} | {name} | | "
                     + " / ".join(f"{v:.2f}" for v in med[:-1]) + f" | {med[-1]:.3f} cm |")
    return lines


def scores(errors: np.ndarray) -> str:
    e = np.asarray(errors)
    return (" / ".join(f"{v:.1f}" for v in recalls(e)) +
            f" | {100 * np.median(e[:, 0]):.3f} cm / {np.median(e[:, 1]):.3f} deg")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--poses", type=Path, default=None)
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/slamreloc-label-levers"))
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--methods", nargs="+", default=list(METHODS), choices=list(METHODS),
                    help="matching is deterministic on a map's labels: leave it out to save time")
    ap.add_argument("--refine-on-all", action="store_true",
                    help="the regressor's last refinement on all its predictions near the pose")
    ap.add_argument("--out", type=Path, default=Path("labels.md"))
    args = ap.parse_args()
    dataset = load_dataset(args.dataset, args.poses)
    args.workdir.mkdir(parents=True, exist_ok=True)
    maps = {name: variant_map(dataset, name, args.workdir) for name in args.variants}
    torch.set_num_threads(1)
    frames = dataset.frames("test")
    by_features: dict[str, tuple[list, float]] = {}  # feature settings -> (features, ms)
    head = " / ".join(THRESHOLDS)
    lines = [(f"`{args.dataset}`, scored against {args.poses or 'the dataset poses'}, "
              f"{len(frames)} queries; features: median ms per query, one at a time"
              + ("; regressor with refine_on_all" if args.refine_on_all else "")), "",
             (f"| variant | labels | features | regressor {head} | regressor median | "
              f"matching {head} | matching median |"), "|---" * 7 + "|"]
    for name, scene_map in maps.items():
        key = json.dumps(scene_map.meta["features"], sort_keys=True)
        if key not in by_features:
            by_features[key] = query_features(frames, scene_map)
        feats, feature_ms = by_features[key]
        options = {"regressor": {"refine_on_all": args.refine_on_all}, "matching": {}}
        cells = [score_method(scene_map, method, frames, feats, **options[method])
                 if method in args.methods else "- | -" for method in METHODS]
        lab = scene_map.meta["labels"]
        lines.append(f"| {name} | {lab['n_labelled']}, {lab['median_reproj_error_px']:.2f} px | "
                     f"{feature_ms:.1f} ms | " + " | ".join(cells) + " |")
        print(lines[-1], flush=True)
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
