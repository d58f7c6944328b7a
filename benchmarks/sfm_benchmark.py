"""A map from images without poses against a map from the same images with known poses.

    python -m benchmarks.sfm_benchmark ../shared/data/7scenes_redkitchen \
        --workdir /tmp/sfm-bench [--train seq-01] [--test seq-02] [--epochs N]

1. `slamreloc sfm` on the training sequence's images (their poses unread), metric scale from
   their depth; 2. `slamreloc map` of that SfM dataset; 3. the map of the same images with the
   dataset's known (depth-SLAM) poses; 4. both localize the test sequence. Each map's
   estimates live in its own world frame; for each reference (the dataset's depth-SLAM poses,
   and the SfM pseudo ground truth in DATASET/sfm_pgt/poses.txt where present) a similarity
   transform is fitted on that map's *training* cameras only and moves the estimates into the
   reference's frame before scoring. Prints a table and writes WORKDIR/sfm_benchmark.json.

    python -m benchmarks.sfm_benchmark DATASET --timing-only --train all

times `sfm` + `map` alone (the 600-image target), without evaluation.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path, PurePosixPath

from benchmarks.run_benchmark import cpu_name
from slamreloc.datasets import load_dataset
from slamreloc.localize.evaluate import align_to_reference, rescore, summarize
from slamreloc.io.outputs import write_json
from slamreloc.geometry import read_tum_trajectory
from slamreloc.map.build import MapConfig, build_map
from slamreloc.datasets import load_dataset
from slamreloc.localize.evaluate import evaluate_map
from slamreloc.map.scene_map import SceneMap
from slamreloc.sfm import IMAGE_SUFFIXES, SfmConfig, run_sfm


def frame_key(name: str) -> str:
    """A frame name without an image suffix: `seq-01/frame-000000.png` -> `seq-01/frame-000000`
    (an SfM dataset names frames by their image files)."""
    path = PurePosixPath(name)
    return str(path.with_suffix("")) if path.suffix.lower() in IMAGE_SUFFIXES else name


def training_poses(scene_map: SceneMap) -> dict:
    """The map's training cameras (map frame) by frame key."""
    recorded = scene_map.meta["dataset"]
    frames = load_dataset(recorded["root"]).frames(recorded["split"])
    return {frame_key(f.name): f.world_from_cam for f in frames}


def timed_map(dataset_dir: Path, out: Path, split: str, config: MapConfig
              ) -> tuple[SceneMap, float]:
    """The map (built unless WORKDIR already holds it) and the seconds building it took."""
    if SceneMap.is_map(out):
        m = SceneMap.load(out)
        return m, float(sum(m.meta.get("timings_s", {}).values()))
    t0 = time.perf_counter()
    m = build_map(load_dataset(dataset_dir), out, split, config)
    return m, time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/slamreloc-sfm-bench"))
    ap.add_argument("--train", default="seq-01")
    ap.add_argument("--test", default="seq-02")
    ap.add_argument("--epochs", type=int, default=None)
    ap.add_argument("--timing-only", action="store_true")
    args = ap.parse_args()
    work = args.workdir
    work.mkdir(parents=True, exist_ok=True)
    config = MapConfig()
    if args.epochs:
        config.train = replace(config.train, epochs=args.epochs)
    out = {"cpu": cpu_name(), "dataset": str(args.dataset), "train": args.train,
           "test": args.test, "epochs": config.train.epochs}

    sfm_dir = work / f"sfm-{args.train}"
    if not (sfm_dir / "sfm.json").is_file():
        t0 = time.perf_counter()
        run_sfm(args.dataset, sfm_dir, SfmConfig(split=args.train, scale_from_depth=True))
        out["sfm_s"] = time.perf_counter() - t0
    sfm = json.loads((sfm_dir / "sfm.json").read_text())
    out["sfm"] = {k: sfm[k] for k in ("n_images", "n_registered", "n_points",
                                      "mean_track_length", "mean_reprojection_error_px",
                                      "scale", "units", "camera", "timings_s")}
    sfm_map, out["map_sfm_s"] = timed_map(sfm_dir, work / f"map-sfm-{args.train}", "all",
                                          config)
    out["sfm_plus_map_s"] = sfm["timings_s"]["total_s"] + out["map_sfm_s"]
    print(f"sfm + map of {sfm['n_images']} images: {out['sfm_plus_map_s'] / 60:.1f} min "
          f"(sfm {sfm['timings_s']['total_s'] / 60:.1f}, map {out['map_sfm_s'] / 60:.1f})")
    if args.timing_only:
        write_json(work / "sfm_timing.json", out)
        return
    known_map, out["map_known_s"] = timed_map(args.dataset, work / f"map-known-{args.train}",
                                              args.train, config)

    dataset = load_dataset(args.dataset)
    references = {"dSLAM": {f.name: f.world_from_cam for f in dataset.frames("all")}}
    pgt = args.dataset / "sfm_pgt" / "poses.txt"
    if pgt.is_file():
        references["SfM"] = dict(read_tum_trajectory(pgt))
    rows = []
    for label, scene_map in (("known poses", known_map), ("sfm (no poses)", sfm_map)):
        results = evaluate_map(scene_map, load_dataset(args.dataset), args.test).results
        train = training_poses(scene_map)
        for ref_name, reference in references.items():
            ref_from_map, record = align_to_reference(train, reference)
            s = summarize(rescore(results, reference, ref_from_map), "regressor")
            rows.append({"map": label, "reference": ref_name, "alignment": record, **s})
    out["rows"] = rows
    for ref_name in references:
        by = {r["map"]: r for r in rows if r["reference"] == ref_name}
        known, ours = by["known poses"]["recall"]["5cm5deg"], by["sfm (no poses)"]["recall"][
            "5cm5deg"]
        out[f"ratio_5cm5deg_{ref_name}"] = ours / known if known else None
    write_json(work / "sfm_benchmark.json", out)
    print("| map | reference | aligned on (frames, scale, residual) | median | 1cm1deg | "
          "2cm2deg | 5cm5deg | 10cm5deg |\n|---|---|---|---|---|---|---|---|")
    for r in rows:
        a = r["alignment"]
        print(f"| {r['map']} | {r['reference']} | {a['n_frames']}, x{a['scale']:.4f}, "
              f"{100 * a['median_residual_m']:.1f} cm / {a['median_residual_deg']:.2f} deg | "
              f"{100 * (r['median_translation_m'] or float('inf')):.1f} cm / "
              f"{r['median_rotation_deg'] or float('inf'):.2f} deg | "
              + " | ".join(f"{100 * r['recall'][k]:.1f} %" for k in
                           ("1cm1deg", "2cm2deg", "5cm5deg", "10cm5deg")) + " |")
    for ref_name in references:
        print(f"5cm5deg ratio sfm / known, {ref_name} reference: "
              f"{100 * out[f'ratio_5cm5deg_{ref_name}']:.1f} %")


if __name__ == "__main__":
    main()
