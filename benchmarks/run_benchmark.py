"""Map a dataset, evaluate the regressor, the matching baseline and RGB-D refinement side by
side, scored against the dataset's poses and, given `--reference`, a second reference.

    python benchmarks/run_benchmark.py ../shared/data/7scenes_redkitchen --out bench.md \
        [--reference ../shared/data/7scenes_redkitchen/sfm_pgt/poses.txt] \
        [--arch wide] [--epochs 20] [--workdir /tmp/bench] [--reuse]

With `--reference FILE` two maps are built: one on the dataset's poses (`map-dataset`) and one
on FILE's poses (`map-reference`, `slamreloc map --poses FILE`). Every method on every map is
scored against both references: the map's own (the poses it was trained on) and the other,
moved into its frame by a similarity fitted on the map's training cameras only
(`evaluate --reference`; the dataset's own poses are that reference given as the dataset
folder).

Writes WORKDIR/map-*, one contract report per map and method (`<map>-<method>.json`) and
WORKDIR/curves-<map>.png (both methods' error curves and positions).

All methods run in the same process on the same map, one after the other, so their timings
are comparable. Numbers are medians per query.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from dataclasses import replace
from pathlib import Path

import torch

from slamreloc.datasets import load_dataset
from slamreloc.io.outputs import write_json
from slamreloc.map.build import MapConfig, build_map
from slamreloc.cli.jobs import depth_refiner, reference_labels
from slamreloc.datasets import load_dataset
from slamreloc.localize.evaluate import (
    EvaluationConfig,
    evaluate_map,
    prepare_reference,
    query_frames,
)
from slamreloc.localize.plots import plot_evaluation
from slamreloc.runtime.precision import bf16_support
from slamreloc.map.scene_map import SceneMap

METHODS = (("regressor", False), ("matching", False), ("regressor", True))  # (method, depth)
# Published 5cm5deg on the official RedKitchen split, depth-SLAM vs SfM reference (Brachmann
# et al., "On the Limits of Pseudo Ground Truth in Visual Camera Re-Localization", ICCV 2021)
LITERATURE = "DSAC* 65.5 % -> 97.0 %, hloc 61.9 % -> 98.6 % (dSLAM -> SfM reference)"


def cpu_name() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            return next(ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name"))
    except (OSError, StopIteration):
        return platform.processor() or platform.machine()


def cpu_kind() -> str:
    """The CPU's model, cores and bf16 kind as torch will use it (AMX, AVX512-BF16, or why not:
    `runtime.precision.bf16_kind`, which also names an AVX2 restriction)."""
    from slamreloc.runtime.precision import bf16_kind

    return f"{cpu_name()}, {os.cpu_count()} cores, {bf16_kind('cpu')[1]}"


def get_map(dataset_dir: Path, poses: Path | None, out: Path, config: MapConfig,
            reuse: bool) -> tuple[SceneMap, str]:
    """The map trained on `poses` (None: the dataset's), built unless `reuse` finds it."""
    if reuse and SceneMap.is_map(out):
        return SceneMap.load(out), "reused"
    t0, c0 = time.perf_counter(), time.process_time()
    scene_map = build_map(load_dataset(dataset_dir, poses), out, "train", config)
    t = scene_map.meta["timings_s"]
    return scene_map, (
        f"{time.perf_counter() - t0:.0f} s wall, {time.process_time() - c0:.0f} s CPU "
        f"(features {t['features_s']:.0f} s, labels {t['labels_s']:.0f} s, training "
        f"{t['train_s']:.0f} s)")


def table_rows(map_label: str, rep: dict, own_label: str) -> list[str]:
    """One markdown row per reference the report scores against."""
    scored = [(own_label, rep)] + [(label, r) for label, r in rep.get("references", {}).items()]
    method = rep["method"] + (" + depth ICP" if rep.get("refine") == "depth" else "")
    rows = []
    for label, r in scored:
        med = (f"{100 * r['median_translation_m']:.2f} cm / {r['median_rotation_deg']:.3f} deg"
               if r["median_translation_m"] is not None else "inf")
        rec = " | ".join(f"{100 * r['recall'][k]:.1f} %"
                         for k in ("1cm1deg", "2cm2deg", "5cm5deg", "10cm5deg"))
        rows.append(f"| {map_label} | {method} | {label} | {rec} | {med} | "
                    f"{r['n_localized']}/{r['n_queries']} | {rep['timing_ms']['total']:.0f} |")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--out", type=Path, default=Path("bench.md"))
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/slamreloc-bench"))
    ap.add_argument("--reference", type=Path, default=None,
                    help="a second reference's poses (e.g. sfm_pgt/poses.txt)")
    ap.add_argument("--reference-name", default="SfM")
    ap.add_argument("--dataset-name", default="dSLAM", help="what the dataset's poses are")
    ap.add_argument("--reuse", action="store_true", help="reuse maps already in WORKDIR")
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
    args.workdir.mkdir(parents=True, exist_ok=True)
    maps = [("dataset", None, args.dataset_name)]
    if args.reference is not None:
        maps.append(("reference", args.reference, args.reference_name))
    head = [(f"dataset `{args.dataset}`, map = train split, queries = test split; machine: "
            f"{cpu_name()} ({bf16_support('cpu')[1]}), {torch.get_num_threads()} torch "
            f"threads, torch {torch.__version__}"), ""]
    rows = [("| map trained on | method | scored against | 1cm1deg | 2cm2deg | 5cm5deg | "
            "10cm5deg | median | localized | ms/query |"), "|---" * 10 + "|"]
    reports = {}
    for key, poses, label in maps:
        scene_map, how = get_map(args.dataset, poses, args.workdir / f"map-{key}", config,
                                 args.reuse)
        head.append(f"- map `{key}` ({label} poses): {how}; arch "
                    f"{scene_map.meta['regressor']['arch']}, training precision "
                    f"{scene_map.meta['train']['precision']}, labels: "
                    f"{scene_map.meta['labels']['n_labelled']} "
                    f"({scene_map.meta['labels'].get('n_depth_labels', 0)} from depth), "
                    f"{scene_map.size_bytes() / 1e6:.1f} MB")
        # the other reference: a pose file, or the dataset folder for the dataset's own poses
        other = [(args.dataset if p is None else p, n) for k, p, n in maps if k != key]
        results = {}
        for method, depth in METHODS:
            if depth and scene_map.surface is None:
                continue
            paths = [p for p, _ in other]
            dataset = load_dataset(args.dataset, poses)
            queries = query_frames(dataset, "test")
            refs = [prepare_reference(Path(p), label, scene_map, dataset, queries)
                    for p, label in zip(paths, reference_labels(paths))]
            ev = evaluate_map(scene_map, dataset, "test", EvaluationConfig(method=method),
                              depth_refiner(scene_map, dataset) if depth else None, refs)
            rep, res, frames = ev.report, ev.results, ev.frames
            name = method + ("-depth" if depth else "")
            # the report's reference labels are file names: name them by what they are
            rep["references"] = {n: r for n, r in zip([n for _, n in other],
                                                      rep.get("references", {}).values())}
            write_json(args.workdir / f"{key}-{name}.json", rep)
            reports[f"{key}-{name}"] = rep
            results[name] = res
            rows += table_rows(label, rep, label)
        plot_evaluation(args.workdir / f"curves-{key}.png", results, frames)
    lines = head + ["", *rows, "", f"Literature, official split, 5cm5deg: {LITERATURE}."]
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    (args.workdir / "summary.json").write_text(json.dumps(reports, indent=1))


if __name__ == "__main__":
    main()
