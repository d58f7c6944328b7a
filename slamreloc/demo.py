"""`slamreloc demo`: the whole job on the embedded synthetic scene, with a summary table."""

from __future__ import annotations

import time
from pathlib import Path

from slamreloc.datasets import load_dataset
from slamreloc.evaluate import print_summary, write_json
from slamreloc.mapping import MapConfig, build_map
from slamreloc.pipeline import run_evaluation
from slamreloc.progress import console, make_progress
from slamreloc.regressor.train import TrainConfig
from slamreloc.synthetic import SceneConfig, render_scene

# Settings sized for a 2-core CPU: the whole demo in a few minutes.
DEMO_MAP = MapConfig(arch="wide", train=TrainConfig(epochs=60))


def render_with_progress(out: Path, config: SceneConfig = SceneConfig()) -> Path:
    if (out / "scene.json").is_file():  # already rendered (render_scene checks the config)
        return render_scene(out, config)
    with make_progress() as bar:
        task = bar.add_task("rendering scene", total=sum(config.counts().values()), rate="")
        return render_scene(out, config, progress=lambda done, total: bar.update(
            task, completed=done, rate=f"{bar.tasks[0].speed or 0:6.1f} it/s"))


def run_demo(workdir: Path, viewer: bool = True, port: int = 8080,
             map_config: MapConfig = DEMO_MAP, scene_config: SceneConfig = SceneConfig()) -> dict:
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    console.rule("1/3 synthetic scene")
    scene_dir = render_with_progress(workdir / "scene", scene_config)
    dataset = load_dataset(scene_dir)
    console.rule("2/3 map: features, labels, regressor")
    scene_map = build_map(dataset, workdir / "map", "train", map_config)
    console.rule("3/3 relocalize the query sequence")
    summaries = [run_evaluation(scene_map.root, scene_dir, workdir / f"report_{m}.json", "test",
                                m, poses=workdir / f"poses_{m}.txt") for m in
                 ("regressor", "matching")]
    write_json(workdir / "report.json", summaries[0])  # the contract's name: the method itself
    print_summary(summaries)
    console.print(f"demo finished in {time.perf_counter() - t0:.0f} s; scene, map and reports "
                  f"are in {workdir}")
    if viewer:
        serve_demo_viewer(workdir, scene_map.root, scene_dir, port)
    return {"summaries": summaries, "map": str(scene_map.root), "scene": str(scene_dir)}


def serve_demo_viewer(workdir: Path, map_dir: Path, scene_dir: Path, port: int = 8080) -> None:
    """Serve the viewer on everything the demo wrote (reports, trajectories) until Ctrl-C."""
    from slamreloc.viewer import ViewerInputs, serve

    workdir = Path(workdir)
    reports, seen = [], set()
    for path in sorted(workdir.glob("report*.json")):  # report.json repeats report_regressor
        if path.read_bytes() not in seen:
            seen.add(path.read_bytes())
            reports.append(path)
    trajectories = sorted(p for p in [*workdir.glob("poses_*.txt"), *workdir.glob("traj*.txt")]
                          if not p.name.endswith(".names.txt"))
    console.rule("viewer")
    serve(ViewerInputs(map_dir, trajectories, reports, scene_dir, port=port),
          echo=console.print)
