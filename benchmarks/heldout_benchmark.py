"""Held-out localization on RedKitchen: the shared 600 frames in folds along the trajectory,
each block of 200 frames localized in a map of the other 400, so no query was seen by any
setting chosen on the shared seq-02 queries (BENCHMARKS.md, "Held-out folds").

    python -m benchmarks.heldout_benchmark DATA --work DIR [--folds A B C] [--methods ...]
        [--map-poses sfm|dslam] [--augment-views N]

DATA: the 7-Scenes RedKitchen folder (seq-01 = 400 frames, seq-02 = 200, sfm_pgt/poses.txt).
Blocks: A = seq-01 frames 0-199, B = seq-01 200-399, C = seq-02 (the shared queries). Fold X:
a map of the two other blocks (`slamreloc map`, SfM poses, today's defaults), the X frames
localized by each method (`slamreloc evaluate --method`), scored against SfM and against the
dataset's own poses (dSLAM, `--reference`, fitted on the map's training cameras). Fold C is
the shared seq-02 figure; A and B are out of sample. `--map-poses dslam`: the maps are trained
on the dataset's own poses instead (so their labels come from depth), every query is refined
by depth ICP (`evaluate --depth`), and the scores are against dSLAM first, SfM second.
`--augment-views N`: the maps are made with `map --augment-views N` (DIR/map_X_augN).

Each fold is a folder of links (the data stays where it is): DIR/fold_X/seq-01 the map's
frames, DIR/fold_X/seq-02 the queries, renumbered, with `poses_sfm.txt` and `poses_dslam.txt`
naming them as renumbered. Prints a markdown table; writes DIR/heldout.json.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

from benchmarks.run_benchmark import cpu_kind

BLOCKS = {"A": ("seq-01", 0, 200), "B": ("seq-01", 200, 400), "C": ("seq-02", 0, 200)}
SFM = "sfm_pgt/poses.txt"


def read_named_poses(path: Path) -> dict[str, str]:
    """name -> the rest of its line ('tx ty tz qx qy qz qw') of a named pose file."""
    out = {}
    for line in path.read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            name, rest = line.split(maxsplit=1)
            out[name] = rest
    return out


def dslam_line(pose_txt: Path) -> str:
    """A 7-Scenes 4x4 world_from_cam as 'tx ty tz qx qy qz qw' (the named pose format)."""
    import numpy as np

    from slamreloc.geometry import matrix_to_quat

    m = np.loadtxt(pose_txt)
    q = matrix_to_quat(m[:3, :3])  # (x, y, z, w)
    return " ".join(f"{v:.7f}" for v in (*m[:3, 3], *q))


def make_fold(data: Path, held: str, out: Path) -> Path:
    """The fold's dataset folder (links, renumbered frames) and its two pose files."""
    sfm = read_named_poses(data / SFM)
    root = out / f"fold_{held}"
    if root.exists():
        return root
    lines = {"sfm": [], "dslam": []}
    for role, blocks in (("seq-01", [b for b in BLOCKS if b != held]), ("seq-02", [held])):
        folder = root / role
        folder.mkdir(parents=True)
        n = 0
        for b in blocks:
            seq, first, end = BLOCKS[b]
            for k in range(first, end):
                src = data / seq / f"frame-{k:06d}"
                dst = folder / f"frame-{n:06d}"
                for suffix in (".color.jpg", ".color.png", ".depth.png", ".pose.txt"):
                    if Path(f"{src}{suffix}").exists():
                        Path(f"{dst}{suffix}").symlink_to(Path(f"{src}{suffix}").resolve())
                name = f"{role}/frame-{n:06d}"
                lines["sfm"].append(f"{name} {sfm[f'{seq}/frame-{k:06d}']}")
                lines["dslam"].append(f"{name} {dslam_line(Path(f'{src}.pose.txt'))}")
                n += 1
    (root / "TrainSplit.txt").write_text("sequence1\n")
    (root / "TestSplit.txt").write_text("sequence2\n")
    for ref, rows in lines.items():
        (root / f"poses_{ref}.txt").write_text("# name tx ty tz qx qy qz qw\n"
                                               + "\n".join(rows) + "\n")
    return root


def cli(*args) -> float:
    """Run `slamreloc ARGS`; its wall seconds (exits with its error on failure)."""
    t0 = time.perf_counter()
    res = subprocess.run([sys.executable, "-m", "slamreloc.cli", *map(str, args)],
                         capture_output=True, text=True)
    if res.returncode:
        sys.exit(f"slamreloc {' '.join(map(str, args))}:\n{res.stderr}")
    return time.perf_counter() - t0


def scores(report: Path, own: str = "sfm", other: str = "dslam") -> dict:
    """The report's recalls against its own poses (`own`) and its one reference (`other`)."""
    r = json.loads(report.read_text())
    ref = next(iter(r["references"].values()))
    pick = (lambda d: {k: d["recall"][k] for k in ("1cm1deg", "2cm2deg", "5cm5deg")})  # noqa
    return {own: pick(r), other: pick(ref), f"{own}_median_cm": 100 * r["median_translation_m"],
            "ms_per_query": r["timing_ms"]["total"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("data", type=Path)
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--folds", nargs="+", default=["A", "B", "C"], choices=list(BLOCKS))
    ap.add_argument("--methods", nargs="+", default=["regressor", "matching"])
    ap.add_argument("--map-poses", choices=["sfm", "dslam"], default="sfm",
                    help="the poses the maps are trained on (dslam: with depth ICP)")
    ap.add_argument("--augment-views", type=int, default=0,
                    help="`map --augment-views`: simulated views per mapping image")
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    own, other = ("sfm", "dslam") if args.map_poses == "sfm" else ("dslam", "sfm")
    suffix = ("" if own == "sfm" else "_dslam") + (
        f"_aug{args.augment_views}" if args.augment_views else "")
    augment = ["--augment-views", str(args.augment_views)] if args.augment_views else []
    result = {"cpu": cpu_kind(), "map_poses": own, "augment_views": args.augment_views,
              "folds": {}}
    for held in args.folds:
        root = make_fold(args.data, held, args.work)
        m = args.work / f"map_{held}{suffix}"
        # dSLAM: the frames' own pose.txt (so `map` labels from depth); the named file scores
        poses = [] if own == "dslam" else ["--poses", root / "poses_sfm.txt"]
        fold = {}
        if not (m / "slamreloc_map.json").exists():
            fold["map_s"] = round(cli("map", root, *poses, *augment, "--out", m), 1)
        for method in args.methods:
            report = args.work / f"ev_{held}_{method}{suffix}.json"
            cli("evaluate", m, root, "--method", method, *poses, "--reference",
                root / f"poses_{other}.txt", "--report", report,
                *(["--depth"] if own == "dslam" else []))
            fold[method] = scores(report, own, other)
            print(held, method, json.dumps(fold[method]), flush=True)
        result["folds"][held] = fold
    (args.work / f"heldout{suffix}.json").write_text(json.dumps(result, indent=1))
    print(f"\n{result['cpu']}; maps on {own} poses\n")
    print(f"| fold (queries) | method | {own} 1cm1deg | 2cm2deg | 5cm5deg | {other} 5cm5deg | "
          f"{own} median | ms/query |")
    print("|---|---|---|---|---|---|---|---|")
    for held, fold in result["folds"].items():
        seq, first, end = BLOCKS[held]
        for method in args.methods:
            s = fold[method]
            print(f"| {held} ({seq} {first}-{end - 1}) | {method} | "
                  f"{100 * s[own]['1cm1deg']:.1f} % | {100 * s[own]['2cm2deg']:.1f} % | "
                  f"{100 * s[own]['5cm5deg']:.1f} % | {100 * s[other]['5cm5deg']:.1f} % | "
                  f"{s[f'{own}_median_cm']:.2f} cm | {s['ms_per_query']:.0f} |")


if __name__ == "__main__":
    main()
