"""`slamreloc demo`: the whole job on the embedded synthetic scene, with a summary table."""

from __future__ import annotations

import time
from pathlib import Path

from slamreloc.cli.slam_stage import print_slam_summary, run_slam_command
from slamreloc.datasets import load_dataset
from slamreloc.localize.evaluate import print_summary
from slamreloc.io.fileio import write_json
from slamreloc.geometry import NAMES_SUFFIX
from slamreloc.map.build import MapConfig, build_map
from slamreloc.cli.pipeline import run_evaluation
from slamreloc.runtime.progress import console, make_progress
from slamreloc.regressor.train import TrainConfig
from slamreloc.synthetic import SceneConfig, render_scene

# Settings sized for a 2-core CPU without native bf16: the whole demo within 10 minutes. The
# synthetic room's labels are dense (80 % of keypoints): 20 epochs localize every query within
# 2 cm (15 epochs: worst 2.0 cm, 30: 1.5 cm; BENCHMARKS.md).
DEMO_MAP = MapConfig(arch="wide", train=TrainConfig(epochs=20))
DEMO_KIDNAP = (30, 15)  # kidnap after every 30 frames, 15 dropped: twice in 120 frames


def render_with_progress(out: Path, config: SceneConfig = SceneConfig()) -> Path:
    if (out / "scene.json").is_file():  # already rendered (render_scene checks the config)
        return render_scene(out, config)
    with make_progress() as bar:
        task = bar.add_task("rendering scene", total=sum(config.counts().values()), rate="")
        return render_scene(out, config, progress=lambda done, total: bar.update(
            task, completed=done, rate=f"{bar.tasks[0].speed or 0:6.1f} it/s"))


def pseudo_label_stage(workdir: Path, map_dir: Path, dataset) -> list[dict]:
    """Update the map from the unlabelled sequence (its poses only score the report), then
    relocalize the query and kidnap sequences with the old and the updated map."""
    from slamreloc.pseudo_label import update_map

    new_map, rep = update_map(map_dir, dataset, workdir / "map_updated", "unlabelled")
    write_json(workdir / "report_pseudo_label.json", rep)
    prec = rep.get("pseudo_label_precision_10cm")
    console.print(f"update: {rep['n_frames_registered']}/{rep['n_frames']} unlabelled frames "
                  f"registered, {rep['n_pseudo_labels']} pseudo-labels, "
                  f"{rep['n_new_points']} new points"
                  + ("" if prec is None else f", {100 * prec:.1f} % within 10 cm") +
                  f"; regressor {rep['update']['mode']} in {rep['timings_s']['update_s']:.0f} s")
    rows = []
    for split in ("kidnap",):  # held-out views that reach beyond the labelled map
        for tag, root in (("before", map_dir), ("after", new_map.root)):
            s = run_evaluation(root, dataset.root, workdir / f"report_{split}_{tag}.json", split,
                               "regressor")
            s["method"] = f"regressor {tag} update, {split} seq."
            rows.append(s)
    after = run_evaluation(new_map.root, dataset.root, workdir / "report_updated.json", "test",
                           "regressor")
    after["method"] = "regressor after update"
    return [after, *rows]


def run_demo(workdir: Path, viewer: bool = True, port: int = 8080,
             map_config: MapConfig = DEMO_MAP, scene_config: SceneConfig = SceneConfig()) -> dict:
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    console.rule("1/5 synthetic scene")
    scene_dir = render_with_progress(workdir / "scene", scene_config)
    dataset = load_dataset(scene_dir)
    console.rule("2/5 map: features, labels, regressor")
    scene_map = build_map(dataset, workdir / "map", "train", map_config)
    console.rule("3/5 relocalize the query sequence")
    summaries = [run_evaluation(scene_map.root, scene_dir, workdir / f"report_{m}.json", "test",
                                m, trajectory=workdir / f"poses_{m}.txt") for m in
                 ("regressor", "matching")]
    write_json(workdir / "report.json", summaries[0])  # the contract's name: the method itself
    console.rule("4/5 SLAM backend on the kidnap sequence, camera kidnapped twice")
    slam = run_slam_command(scene_dir, scene_map.root, workdir / "report_slam.json", "kidnap",
                            kidnap_every=DEMO_KIDNAP[0], kidnap_skip=DEMO_KIDNAP[1],
                            trajectory=workdir / "trajectory_slam.txt")
    console.rule("5/5 map update from the unlabelled sequence (pseudo-labels)")
    updated = pseudo_label_stage(workdir, scene_map.root, dataset)
    summaries += updated
    print_summary(summaries)
    print_slam_summary(slam)
    console.print(f"demo finished in {time.perf_counter() - t0:.0f} s; scene, map and reports "
                  f"are in {workdir}")
    if viewer:
        serve_demo_viewer(workdir, scene_map.root, scene_dir, port)
    return {"summaries": summaries, "slam": slam, "map": str(scene_map.root),
            "scene": str(scene_dir)}


def demo_viewer_inputs(workdir: Path, map_dir: Path, scene_dir: Path, port: int = 8080):
    """ViewerInputs for everything the demo wrote in `workdir`: its reports (each once) and
    trajectories (the `evaluate --trajectory` files and the SLAM trajectory)."""
    from slamreloc.viewer import ViewerInputs

    workdir = Path(workdir)
    reports, seen = [], set()
    for path in sorted(workdir.glob("report*.json")):  # report.json repeats report_regressor
        if path.read_bytes() not in seen:
            seen.add(path.read_bytes())
            reports.append(path)
    trajectories = sorted(p for p in [*workdir.glob("poses_*.txt"), *workdir.glob("traj*.txt")]
                          if not p.name.endswith(NAMES_SUFFIX))
    return ViewerInputs(map_dir, trajectories, reports, scene_dir, port=port)


def serve_demo_viewer(workdir: Path, map_dir: Path, scene_dir: Path, port: int = 8080) -> None:
    """Serve the viewer on everything the demo wrote (reports, trajectories) until Ctrl-C."""
    from slamreloc.viewer import serve

    console.rule("viewer")
    serve(demo_viewer_inputs(workdir, map_dir, scene_dir, port), echo=console.print)
