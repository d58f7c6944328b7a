"""Map a dataset, evaluate the regressor and the matching baseline side by side, write a table.

    python benchmarks/run_benchmark.py ../shared/data/7scenes_redkitchen --out bench.md \
        [--arch wide] [--epochs 20] [--workdir /tmp/bench]

Writes WORKDIR/map, one contract report per method (regressor.json, matching.json) and
WORKDIR/curves.png (both methods' error curves and positions).

Both methods run in the same process on the same map, one after the other, so their timings
are comparable. Numbers are medians per query.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from dataclasses import replace
from pathlib import Path

import torch

from slamreloc.datasets import load_dataset
from slamreloc.fileio import write_json
from slamreloc.mapping import MapConfig, build_map
from slamreloc.pipeline import evaluate_method
from slamreloc.plots import plot_evaluation
from slamreloc.precision import bf16_support


def cpu_name() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            return next(ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name"))
    except (OSError, StopIteration):
        return platform.processor() or platform.machine()


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--out", type=Path, default=Path("bench.md"))
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/slamreloc-bench"))
    ap.add_argument("--arch", default=None)
    ap.add_argument("--epochs", type=int, default=None)
    ap.add_argument("--device", default="auto")
    ap.add_argument("--precision", default="auto", help="auto | fp32 | bf16")
    args = ap.parse_args()
    config = MapConfig(device=args.device)
    config.train = replace(config.train, precision=args.precision)
    if args.arch:
        config.arch = args.arch
    if args.epochs:
        config.train = replace(config.train, epochs=args.epochs)
    t0, c0 = time.perf_counter(), time.process_time()
    scene_map = build_map(load_dataset(args.dataset), args.workdir / "map", "train", config)
    map_s, map_cpu_s = time.perf_counter() - t0, time.process_time() - c0
    rows, results = [], {}
    for method in ("regressor", "matching"):
        rep, results[method], frames = evaluate_method(scene_map, args.dataset, "test", method)
        write_json(args.workdir / f"{method}.json", rep)
        rows.append(rep)
    plot_evaluation(args.workdir / "curves.png", results, frames)  # both methods, one figure
    t = scene_map.meta["timings_s"]
    lines = [
        f"dataset `{args.dataset}`, map = train split, queries = test split; "
        f"machine: {cpu_name()} ({bf16_support('cpu')[1]}), {torch.get_num_threads()} "
        f"torch threads, torch {torch.__version__}, precision "
        f"{scene_map.meta['train']['precision']}",
        f"mapping {map_s:.0f} s wall, {map_cpu_s:.0f} s CPU (features {t['features_s']:.0f} s, labels {t['labels_s']:.0f} s, "
        f"training {t['train_s']:.0f} s), arch {scene_map.meta['regressor']['arch']}, "
        f"{scene_map.meta['train']['epochs']} epochs, device {scene_map.meta['train']['device']}",
        "",
        "| method | 5cm5deg | 10cm5deg | 2cm2deg | median | localized | features ms | "
        "regressor/matching ms | PnP ms | total ms | map size |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        size = (r["map"]["size_bytes"] if r["method"] == "regressor"
                else r["map"]["database_bytes"]) / 1e6
        med = (f"{100 * r['median_translation_m']:.1f} cm / {r['median_rotation_deg']:.2f} deg"
               if r["median_translation_m"] is not None else "inf")
        tm = r["timing_ms"]
        lines.append(
            f"| {r['method']} | {100 * r['recall']['5cm5deg']:.1f} % | "
            f"{100 * r['recall']['10cm5deg']:.1f} % | {100 * r['recall']['2cm2deg']:.1f} % | "
            f"{med} | {r['n_localized']}/{r['n_queries']} | {tm['features']:.0f} | "
            f"{tm['regressor']:.1f} | {tm['pnp']:.1f} | {tm['total']:.0f} | {size:.1f} MB |")
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    (args.workdir / "summary.json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
