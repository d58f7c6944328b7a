"""Label levers and the spread of training, side by side: one map per variant, the regressor
and the matching baseline on the same queries.

    python -m benchmarks.label_levers DATASET [--poses FILE] --workdir W [--variants ...] \
        --out labels.md

Variants (each a map in WORKDIR/map-<name>, reused when it is there):
- `default`, `seed1`, `seed2`: today's labels, training seeds 0, 1 and 2 (the spread of one
  training);
- `ba`, `ba-seed1`: track points bundle-adjusted with the poses fixed
  (`LabelConfig.refine_points`);
- `angle4`: tracks triangulated at >= 4 deg only (`LabelConfig.min_tri_angle_deg`, default 2).

Scored against the poses the maps are trained on (the dataset's, or `--poses`). Features of
the queries are extracted once; one torch thread. The regressor is the default localizer;
matching is the classical baseline on the same map's labelled database.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from slamreloc.datasets import load_dataset
from slamreloc.evaluate import THRESHOLDS
from slamreloc.extract import extract_frames
from slamreloc.geometry import pose_error
from slamreloc.localizer import make_localizer
from slamreloc.mapping import MapConfig, build_map
from slamreloc.pnp import estimate_pose
from slamreloc.scene_map import SceneMap

VARIANTS = {  # name: (LabelConfig fields, TrainConfig fields)
    "default": ({}, {}),
    "seed1": ({}, {"seed": 1}),
    "seed2": ({}, {"seed": 2}),
    "ba": ({"refine_points": True}, {}),
    "ba-seed1": ({"refine_points": True}, {"seed": 1}),
    "angle4": ({"min_tri_angle_deg": 4.0}, {}),
}


def variant_map(dataset, name: str, workdir: Path) -> SceneMap:
    out = workdir / f"map-{name}"
    if SceneMap.is_map(out):
        return SceneMap.load(out)
    labels, train = VARIANTS[name]
    config = MapConfig()
    config.labels = replace(config.labels, **labels)
    config.train = replace(config.train, **train)
    return build_map(dataset, out, "train", config)


def scores(errors: list[tuple[float, float]]) -> str:
    e = np.array(errors)
    rec = [100 * np.mean((e[:, 0] <= t) & (e[:, 1] <= r)) for t, r in THRESHOLDS.values()]
    return (" / ".join(f"{v:.1f}" for v in rec) +
            f" | {100 * np.median(e[:, 0]):.3f} cm / {np.median(e[:, 1]):.3f} deg")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--poses", type=Path, default=None)
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/slamreloc-label-levers"))
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--out", type=Path, default=Path("labels.md"))
    args = ap.parse_args()
    dataset = load_dataset(args.dataset, args.poses)
    args.workdir.mkdir(parents=True, exist_ok=True)
    maps = {name: variant_map(dataset, name, args.workdir) for name in args.variants}
    torch.set_num_threads(1)
    frames = dataset.frames("test")
    first = next(iter(maps.values()))
    feats = extract_frames(frames, make_localizer(first, "regressor").extractor)
    head = " / ".join(THRESHOLDS)
    lines = [f"`{args.dataset}`, scored against {args.poses or 'the dataset poses'}, "
             f"{len(frames)} queries", "",
             f"| variant | labels | regressor {head} | regressor median | "
             f"matching {head} | matching median |", "|---" * 6 + "|"]
    for name, scene_map in maps.items():
        cells = []
        for method in ("regressor", "matching"):
            loc = make_localizer(scene_map, method)
            errors = []
            for frame, f in zip(frames, feats):
                est = estimate_pose(*loc.correspondences(f), frame.camera.pinhole, loc.pnp)
                errors.append(pose_error(est.world_from_cam, frame.world_from_cam)
                              if est.success else (np.inf, np.inf))
            cells.append(scores(errors))
        lab = scene_map.meta["labels"]
        lines.append(f"| {name} | {lab['n_labelled']}, {lab['median_reproj_error_px']:.2f} px | "
                     + " | ".join(cells) + " |")
        print(lines[-1], flush=True)
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
