"""Map update from an unlabelled sequence on 7-Scenes RedKitchen (issue 9's scenario).

    labelled map   = frames 0-199 of seq-01 (true poses)       [--n-labelled]
    unlabelled     = frames 200-399 of seq-01, pose files left out (scored with the originals)
                                                               [--n-unlabelled]
    queries        = seq-02
    reference      = a map trained with the true poses of the labelled + unlabelled frames

Usage:
    python benchmarks/pseudo_label_benchmark.py ../shared/data/7scenes_redkitchen \
        --workdir /tmp/rk_bench --out pseudo_bench.md [--epochs 100] [--reuse] \
        [--poses ../shared/data/7scenes_redkitchen/sfm_pgt/poses.txt]

`--poses FILE`: the same scenario on another reference (e.g. the SfM one): the maps are
trained on FILE's poses, and registration, pseudo-labels and queries are scored against them.

Everything runs in this one process, in a row, so timings share the machine's load. `--reuse`
keeps maps already in WORKDIR (labelled and reference), to repeat the update alone.
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from slamreloc.datasets import load_dataset
from slamreloc.localize.guided import GuidedConfig
from slamreloc.map.build import MapConfig, build_map
from slamreloc.datasets import load_dataset
from slamreloc.localize.evaluate import EvaluationConfig, evaluate_map
from slamreloc.pseudo_label import PseudoLabelConfig
from slamreloc.pseudo_label.update import pseudo_label
from slamreloc.pseudo_label.write import write_updated_map
from slamreloc.map.scene_map import SceneMap

ROOT = Path(__file__).resolve().parents[1]


def build(dataset: Path, out: Path, epochs: int, reuse: bool,
          poses: Path | None = None) -> tuple[SceneMap, float]:
    marker = out.parent / f".{out.name}.building"  # another process builds it: wait
    while reuse and marker.exists() and not SceneMap.is_map(out):
        time.sleep(10)
    if reuse and SceneMap.is_map(out):
        m = SceneMap.load(out)
        return m, float(m.meta["timings_s"]["train_s"])
    cfg = MapConfig()
    cfg = replace(cfg, train=replace(cfg.train, epochs=epochs))
    m = build_map(load_dataset(dataset, poses), out, "train", cfg)
    return m, float(m.meta["timings_s"]["train_s"])


RECALLS = ("1cm1deg", "2cm2deg", "5cm5deg", "10cm5deg")


def pct(value: float | None, spec: str = ".1f", scale: float = 100) -> str:
    """`scale * value` formatted, or "n/a" where the report has none (e.g. no frame registered)."""
    return "n/a" if value is None else format(scale * value, spec)


def row(name: str, s: dict) -> str:
    r = s["recall"]
    med = ("inf" if s["median_translation_m"] is None else
           f"{100 * s['median_translation_m']:.2f} cm / {s['median_rotation_deg']:.2f} deg")
    guided = "yes" if s["guided_refinement"] else "no"
    return (f"| {name} | {guided} | " + " | ".join(f"{100 * r[k]:.1f} %" for k in RECALLS)
            + f" | {med} | {s['n_localized']}/{s['n_queries']} |")


def within(q: dict, max_m: float, max_deg: float) -> bool:
    t, r = q["translation_error_m"], q["rotation_error_deg"]
    return t is not None and t <= max_m and r <= max_deg


def area_recalls(per_query: dict[str, list[dict]]) -> dict:
    """5cm5deg recall of every map on the queries the labelled map already places within
    10 cm / 5 deg (the old area) and on the rest (the area the update has to add)."""
    lab = [per_query[k] for k in per_query if k.startswith("labelled map")]
    old = np.array([any(within(q[i], 0.10, 5.0) for q in lab) for i in range(len(lab[0]))])
    rec = {}
    for name, qs in per_query.items():
        ok = np.array([within(q, 0.05, 5.0) for q in qs])
        rec[name] = {"old": float(ok[old].mean()) if old.any() else 0.0,
                     "new": float(ok[~old].mean()) if (~old).any() else 0.0}
    return {"n_old": int(old.sum()), "n_new": int((~old).sum()), "recall_5cm5deg": rec}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("source", type=Path)
    ap.add_argument("--workdir", type=Path, default=Path("rk_pseudo_bench"))
    ap.add_argument("--out", type=Path, default=None, help="markdown summary")
    ap.add_argument("--epochs", type=int, default=100, help="training epochs of both maps")
    ap.add_argument("--rounds", type=int, default=PseudoLabelConfig().rounds)
    ap.add_argument("--reuse", action="store_true")
    ap.add_argument("--n-labelled", type=int, default=200, help="first frames of seq-01")
    ap.add_argument("--n-unlabelled", type=int, default=None,
                    help="the frames after them (default: the rest of seq-01)")
    ap.add_argument("--poses", type=Path, default=None,
                    help="another reference's poses for every frame (e.g. sfm_pgt/poses.txt): "
                         "the labelled and true-pose maps are trained on them and registration, "
                         "pseudo-labels and queries are scored against them")
    ap.add_argument("--only-reference", action="store_true",
                    help="build only the true-pose map (run beside a --reuse run)")
    args = ap.parse_args()
    work = args.workdir
    work.mkdir(parents=True, exist_ok=True)
    split = work / "split"
    if not (split / "queries").is_dir():
        sizes = ["--n-labelled", str(args.n_labelled)]
        if args.n_unlabelled is not None:
            sizes += ["--n-unlabelled", str(args.n_unlabelled)]
        subprocess.run([sys.executable, str(ROOT / "scripts" / "make_redkitchen_update_split.py"),
                        str(args.source), "--out", str(split), *sizes], check=True)
    t_start = time.perf_counter()
    if args.only_reference:  # to build the reference map in a parallel process
        marker = work / ".map_true_poses.building"
        marker.touch()
        try:
            build(split / "full", work / "map_true_poses", args.epochs, False, args.poses)
        finally:
            marker.unlink()
        return
    labelled, t_lab = build(split / "labelled", work / "map_labelled", args.epochs, args.reuse,
                            args.poses)

    config = PseudoLabelConfig(rounds=args.rounds)
    labels = pseudo_label(labelled, load_dataset(split / "unlabelled"), "all", config,
                          truth=load_dataset(args.source, args.poses))
    maps = {}
    reports = {}
    for update in ("finetune", "retrain"):
        cfg = replace(config, update=update)
        maps[update], reports[update] = write_updated_map(labels, work / f"map_{update}", cfg)
        rep = {k: v for k, v in reports[update].items() if k != "poses"}
        (work / f"report_{update}.json").write_text(json.dumps(rep, indent=2))

    reference, t_ref = build(split / "full", work / "map_true_poses", args.epochs, args.reuse,
                             args.poses)
    evals, per_query = {}, {}
    n_lab, n_full = (len(load_dataset(split / p).frames("all")) for p in ("labelled", "full"))
    lab, full = f"labelled map ({n_lab} frames)", f"true poses of all {n_full} frames"
    # every regressor map with its default localizer and with --no-guided (the guided
    # refinement runs only where the map's labels agree with its images: the "guided" column)
    runs = [(f"{lab}, matching", labelled, "matching", True)]
    for name, m in ((lab, labelled), ("updated, fine-tuned", maps["finetune"]),
                    ("updated, retrained", maps["retrain"]), (full, reference)):
        runs += [(name, m, "regressor", True), (f"{name}, --no-guided", m, "regressor", False)]
    for name, m, method, guided in runs:
        s = evaluate_map(m, load_dataset(split / "queries", args.poses), "test",
                         EvaluationConfig(method=method, guided=guided)).report
        per_query[name] = s.pop("per_query")
        evals[name] = s
    areas = area_recalls(per_query)
    rep = reports["finetune"]
    before = evals[lab]["recall"]["5cm5deg"]
    after = evals["updated, fine-tuned"]["recall"]["5cm5deg"]
    after_rt = evals["updated, retrained"]["recall"]["5cm5deg"]
    ref = evals[full]["recall"]["5cm5deg"]
    t_ft = reports["finetune"]["timings_s"]["update_s"]
    t_rt = reports["retrain"]["timings_s"]["update_s"]
    lines = [
        f"dataset `{args.source}`, poses {args.poses or 'of the dataset'}; machine: {platform.machine()}, {torch.get_num_threads()} "
        f"torch threads, torch {torch.__version__}; maps: {args.epochs} epochs; "
        f"whole benchmark {time.perf_counter() - t_start:.0f} s",
        "",
        f"- registration: {rep['n_frames_registered']}/{rep['n_frames']} unlabelled frames "
        f"({100 * rep['registered_fraction']:.1f} %), median pose error "
        f"{pct(rep['median_pose_error_m'], '.2f')} cm / "
        f"{pct(rep['median_pose_error_deg'], '.2f', 1)} deg, "
        f"{pct(rep['registered_within_5cm2deg'])} % of them within 5 cm / 2 deg, "
        f"worst {pct(rep['max_pose_error_m'])} cm",
        f"- pseudo-labels: {rep['n_pseudo_labels']} ({rep['n_inherited_labels']} inherited, "
        f"{rep['n_triangulated_labels']} triangulated; {rep['n_new_points']} new points); "
        f"precision within 10 cm {pct(rep['pseudo_label_precision_10cm'])} % "
        f"(inherited {100 * (rep['precision_inherited_10cm'] or 0):.1f} %, triangulated "
        f"{100 * (rep['precision_new_10cm'] or 0):.1f} %; within 5 cm "
        f"{pct(rep['pseudo_label_precision_5cm'])} %), scored on "
        f"{100 * rep['scored_fraction']:.0f} % of them",
        f"- time: pseudo-labelling {rep['timings_s']['pseudo_label_s']:.0f} s; regressor "
        f"fine-tune {t_ft:.0f} s vs full retraining {t_rt:.0f} s (ratio {t_ft / t_rt:.2f}); "
        f"training the labelled map {t_lab:.0f} s, the true-pose map {t_ref:.0f} s",
        "- the label error each map records (the guided refinement runs at most at "
        f"{GuidedConfig().max_label_error_px:g} px): " + ", ".join(
            f"{name} {px:.2f} px" if px is not None else f"{name} none"
            for name, px in (("labelled", labelled.info.label_reproj_error_px),
                             ("updated", maps["finetune"].info.label_reproj_error_px),
                             ("true-pose", reference.info.label_reproj_error_px))),
        "",
        "| map (queries: seq-02) | guided | " + " | ".join(RECALLS) + " | median | localized |",
        "|---" * (len(RECALLS) + 4) + "|",
        *[row(k, v) for k, v in evals.items()],
        "",
        f"- regressor recall gain (fine-tuned): {100 * (after - before):+.1f} points "
        f"(retrained: {100 * (after_rt - before):+.1f}); share of the true-pose map's recall: "
        f"{100 * after / max(ref, 1e-9):.0f} % (retrained {100 * after_rt / max(ref, 1e-9):.0f} %)",
        "",
        f"By area (old: the {areas['n_old']} queries the labelled map places within 10 cm / "
        f"5 deg by matching or regressor; new: the other {areas['n_new']}), 5cm5deg:",
        "",
        "| map | old area | new area |",
        "|---|---|---|",
        *[f"| {k} | {100 * v['old']:.1f} % | {100 * v['new']:.1f} % |"
          for k, v in areas["recall_5cm5deg"].items()],
    ]
    text = "\n".join(lines)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")
    (work / "benchmark.json").write_text(json.dumps(
        {"evaluations": evals, "areas": areas, "per_query": per_query, "reports": {k: {kk: vv for kk, vv in v.items() if kk != "poses"}
                                           for k, v in reports.items()}}, indent=2))


if __name__ == "__main__":
    main()
