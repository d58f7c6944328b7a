"""Query time and accuracy with and without the guided refinement, side by side in one process.

    python -m benchmarks.guided_timing MAP DATASET [--poses FILE] [--threads 2] [--passes 2] \
        [--precisions auto,fp32] [--matching] --out guided.md

For every query the localizers (the default, guided; `guided=None`, the pose RANSAC's on the
regressed points; each at every precision of `--precisions`; with `--matching` the matching
baseline too) run on the same decoded image one after the other, in an order that rotates
from query to query, so that a change in the machine's load reaches all alike. Each pass
goes over all queries; times are medians per query over every pass (ms, `Localizer.localize`:
features, regressor, PnP with the guided refinement, total). Errors are against the poses the
map was trained on (the dataset's, or `--poses`).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from slamreloc.datasets import load_dataset, read_image
from slamreloc.localize.evaluate import THRESHOLDS, recalls
from slamreloc.geometry import pose_error
from slamreloc.localize.localizer import make_localizer
from slamreloc.runtime.precision import bf16_support
from slamreloc.map.scene_map import SceneMap

STAGES = ("features", "regressor", "pnp", "total")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("map", type=Path)
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--poses", type=Path, default=None)
    ap.add_argument("--split", default="test")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--passes", type=int, default=2)
    ap.add_argument("--precisions", default="auto",
                    help="comma-separated regressor precisions (auto | fp32 | bf16)")
    ap.add_argument("--matching", action="store_true", help="time the matching baseline too")
    ap.add_argument("--out", type=Path, default=Path("guided.md"))
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    scene_map = SceneMap.load(args.map)
    frames = load_dataset(args.dataset, args.poses).frames(args.split)
    localizers = {}
    for precision in args.precisions.split(","):
        guided = make_localizer(scene_map, "regressor", precision=precision)
        tag = f"{precision} = {guided.precision}" if precision == "auto" else precision
        localizers[f"guided (default), {tag}"] = guided
        localizers[f"unguided, {tag}"] = make_localizer(scene_map, "regressor", precision=precision,
                                                        guided=None)
    if args.matching:
        localizers["matching"] = make_localizer(scene_map, "matching")
    times = {name: {s: [] for s in STAGES} for name in localizers}
    errors = {name: [] for name in localizers}
    for p in range(args.passes):
        for i, frame in enumerate(frames):
            image = read_image(frame.image_path)
            k = (i + p) % len(localizers)
            order = list(localizers)[k:] + list(localizers)[:k]
            for name in order:
                result = localizers[name].localize(image, frame.camera)
                for s in STAGES:
                    times[name][s].append(result.timings_ms[s])
                if p == 0:
                    est = result.estimate
                    errors[name].append(pose_error(est.world_from_cam, frame.world_from_cam)
                                        if est.success else (np.inf, np.inf))
        print(f"pass {p + 1} of {args.passes} done", flush=True)
    lines = [f"map `{args.map}`, {len(frames)} queries of `{args.dataset}` ({args.split}), "
             f"scored against {args.poses or 'the dataset poses'}; {args.threads} torch "
             f"threads, {args.passes} passes; {bf16_support('cpu')[1]}", "",
             "| localizer | " + " | ".join(THRESHOLDS) + " | median | "
             + " | ".join(f"{s} ms" for s in STAGES) + " |",
             "|---" * (len(THRESHOLDS) + len(STAGES) + 2) + "|"]
    for name in localizers:
        e = np.array(errors[name])
        rec = [100 * v for v in recalls(e[:, 0], e[:, 1]).values()]
        lines.append(f"| {name} | " + " | ".join(f"{v:.1f} %" for v in rec) +
                     f" | {100 * np.median(e[:, 0]):.3f} cm / {np.median(e[:, 1]):.3f} deg | "
                     + " | ".join(f"{np.median(times[name][s]):.1f}" for s in STAGES) + " |")
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
