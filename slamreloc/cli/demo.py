"""`slamreloc demo`: the whole job on the embedded synthetic scene, with a summary table."""

from __future__ import annotations

import shlex
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

from rich import box
from rich.console import Console
from rich.table import Table

from slamreloc.errors import Interrupted
from slamreloc.datasets import load_dataset
from slamreloc.io.outputs import check_outputs, write_json
from slamreloc.map.build import MapConfig, build_map
from slamreloc.cli import jobs
from slamreloc.runtime.progress import console, make_progress, shown
from slamreloc.regressor.train import TrainConfig
from slamreloc.synthetic import SceneConfig, render_scene

# Settings sized for a 2-core CPU without native bf16: the whole demo within 10 minutes. The
# synthetic room's labels are dense (80 % of keypoints): 20 epochs localize every query within
# 2 cm (15 epochs: worst 2.0 cm, 30: 1.5 cm; BENCHMARKS.md).
DEMO_MAP = MapConfig(arch="wide", train=TrainConfig(epochs=20))
DEMO_KIDNAP = (30, 15)  # kidnap after every 30 frames, 15 dropped: twice in 120 frames
N_STAGES = 5


@contextmanager
def stage(number: int, title: str, steps: int | None = None) -> Iterator[Callable[[], None]]:
    """A stage of the demo: a header saying what it does, then a bar of the stage's steps
    and elapsed time that stays live while the stage's own bars come and go, so that no
    stretch of its work is silent (some steps, e.g. matching the unlabelled frames against
    the map before smoothing, have no bar of their own). Yields `done()`: one step over."""
    console.rule(f"{number}/{N_STAGES} {title}")
    with make_progress() as bar:
        task = bar.add_task(f"stage {number}/{N_STAGES}", total=steps, rate="")
        yield lambda: bar.advance(task)
        bar.update(task, total=steps or 1, completed=steps or 1)


def render_with_progress(out: Path, config: SceneConfig = SceneConfig()) -> Path:
    if (out / "scene.json").is_file():  # already rendered (render_scene checks the config)
        return render_scene(out, config)
    with make_progress() as bar:
        task = bar.add_task("rendering scene", total=sum(config.counts().values()), rate="")
        return render_scene(out, config, progress=lambda done, total: bar.update(
            task, completed=done, rate=f"{bar.tasks[0].speed or 0:6.1f} it/s"))


def pseudo_label_stage(workdir: Path, map_dir: Path, dataset,
                       done: Callable[[], None] = lambda: None) -> list[dict]:
    """Update the map from the unlabelled sequence (its poses only score the report), then
    relocalize the query and kidnap sequences with the old and the updated map; `done()`
    after each of these four steps."""
    from slamreloc.map.scene_map import SceneMap
    from slamreloc.pseudo_label import update_map

    console.print("registering the unlabelled frames in the map, smoothing them with "
                  "odometry, pseudo-labelling, then fine-tuning the regressor")
    new_map, rep = update_map(SceneMap.load(map_dir), dataset, workdir / "map_updated",
                              "unlabelled")
    done()
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
            s = jobs.evaluate(root, dataset.root, workdir / f"report_{split}_{tag}.json", split,
                              "regressor")
            s["method"] = f"regressor {tag} update, {split} seq."
            rows.append(s)
            done()
    after = jobs.evaluate(new_map.root, dataset.root, workdir / "report_updated.json", "test",
                          "regressor")
    done()
    after["method"] = "regressor after update"
    return [after, *rows]


# what the demo writes in its workdir, besides the rendered scene (`render_scene` checks that)
DEMO_REPORTS = ("report.json", "report_regressor.json", "report_matching.json",
                "report_slam.json", "report_pseudo_label.json", "report_kidnap_before.json",
                "report_kidnap_after.json", "report_updated.json")
DEMO_TRAJECTORIES = ("poses_regressor.txt", "poses_matching.txt", "trajectory_slam.txt")
DEMO_MAPS = ("map", "map_updated")


def check_demo_outputs(workdir: Path) -> None:
    """Every output the demo writes in `workdir` checked before any work, by the rules of the
    commands that write them (a user's file of one of those names is refused, not replaced
    at the end of its stage)."""
    from slamreloc.datasets.poses import NAMES_FILE, TUM_FILE
    from slamreloc.map.format import is_map

    outputs, files = {}, {}
    for name in DEMO_REPORTS:
        outputs[f"the demo's {name}"] = workdir / name
        files[f"the demo's {name}"] = jobs.REPORT_FILE
    for name in DEMO_TRAJECTORIES:
        outputs[f"the demo's {name}"] = workdir / name
        files[f"the demo's {name}"] = TUM_FILE
        outputs[f"the demo's {name} names file"] = jobs.sidecar(workdir / name)
        files[f"the demo's {name} names file"] = NAMES_FILE
    maps = {f"the demo's {name}": (is_map, "a slamreloc map") for name in DEMO_MAPS}
    outputs.update({f"the demo's {name}": workdir / name for name in DEMO_MAPS})
    check_outputs(outputs, {}, folders=maps, files=files)


def run_demo(workdir: Path, viewer: bool = True, port: int = 8080,
             map_config: MapConfig = DEMO_MAP, scene_config: SceneConfig = SceneConfig()) -> dict:
    """The stages `slamreloc demo --help` lists, each under a header saying what it does;
    ends with the result tables (readable at 80 columns) and the next commands to try."""
    workdir = Path(workdir)
    # a folder (a previous demo's is reused), never under a file: one line before any work
    check_outputs({"--workdir": workdir}, {}, folders=("--workdir",))
    check_demo_outputs(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    counts = scene_config.counts()
    n_query, n_kidnap, n_unlabelled = counts["seq-02"], counts["seq-03"], counts["seq-04"]
    with stage(1, f"render the synthetic room: {sum(counts.values())} RGB-D frames, "
                  "4 sequences"):
        scene_dir = render_with_progress(workdir / "scene", scene_config)
        dataset = load_dataset(scene_dir)
    with stage(2, "map: features, labels, surface, regressor training "
                  f"({map_config.train.epochs} epochs)"):
        try:
            scene_map = build_map(dataset, workdir / "map", "train", map_config)
        except Interrupted:  # the map command's advice (`--resume`) is not the demo's
            raise Interrupted(f"{workdir / 'map'}: the demo was interrupted while training "
                              "its map; run the same demo command again to start it "
                              "over") from None
    with stage(3, f"relocalize the {n_query} query frames: regressor, then matching",
               steps=2) as done:
        summaries = []
        for m in ("regressor", "matching"):
            summaries.append(jobs.evaluate(scene_map.root, scene_dir,
                                           workdir / f"report_{m}.json", "test", m,
                                           trajectory=workdir / f"poses_{m}.txt"))
            done()
        write_json(workdir / "report.json", summaries[0])  # the contract's name: the method
    with stage(4, f"SLAM backend on the {n_kidnap} kidnap frames, camera kidnapped twice"):
        slam = jobs.slam(scene_dir, scene_map.root, workdir / "report_slam.json", "kidnap",
                         kidnap_every=DEMO_KIDNAP[0], kidnap_skip=DEMO_KIDNAP[1],
                         trajectory=workdir / "trajectory_slam.txt")
    with stage(5, f"map update from the {n_unlabelled} unlabelled frames, relocalize again",
               steps=4) as done:
        summaries += pseudo_label_stage(workdir, scene_map.root, dataset, done)
    console.rule("results")
    print_demo_summary(summaries, slam, console)
    console.print(f"demo finished in {time.perf_counter() - t0:.0f} s; scene, map and reports "
                  f"are in {shown(workdir)}")
    for line in next_steps(workdir, dataset.frames("test")[0].image_path, viewer):
        console.print(line, soft_wrap=True, highlight=False, markup=False)
    if viewer:
        serve_demo_viewer(workdir, scene_map.root, scene_dir, port)
    return {"summaries": summaries, "slam": slam, "map": str(scene_map.root),
            "scene": str(scene_dir)}


def _cm_deg(t_m: float | None, r_deg: float | None) -> str:
    return "-" if t_m is None else f"{100 * t_m:.1f} cm {r_deg:.2f}\N{DEGREE SIGN}"


def demo_tables(summaries: list[dict], slam: dict) -> tuple[Table, Table]:
    """The demo's results, narrow enough for 80 columns: relocalization (one row per run,
    the recalls within 5 cm / 5 deg and 10 cm / 5 deg) and the SLAM run (one row per
    measure). The full numbers are in the reports."""
    runs = Table(title="relocalization", box=box.SIMPLE_HEAD, show_edge=False,
                 collapse_padding=True,
                 caption="the query sequence unless marked kidnap; all numbers in the reports")
    runs.add_column("run", overflow="fold")
    for col in ("localized", "median error", "5cm 5\N{DEGREE SIGN}",
                "10cm 5\N{DEGREE SIGN}", "ms/query"):
        runs.add_column(col, justify="right", no_wrap=True)
    for s in summaries:
        runs.add_row(_run_label(s["method"]), f"{s['n_localized']}/{s['n_queries']}",
                     _cm_deg(s["median_translation_m"], s["median_rotation_deg"]),
                     *(f"{100 * s['recall'][k]:.0f} %" for k in ("5cm5deg", "10cm5deg")),
                     f"{s['timing_ms'].get('total', float('nan')):.0f}")
    cm = (lambda v: "-" if v is None else f"{100 * v:.1f} cm")  # noqa: E731
    frames = slam["median_frames_to_recover"]
    fps = slam["backend_fps"]
    rows = [
        ("frames tracked", str(slam["n_frames"])),
        ("trajectory error (ATE)", f"{cm(slam['ate_rmse_m'])} (odometry alone: "
                                   f"{cm(slam['ate_rmse_odometry_only_m'])})"),
        ("kidnaps recovered", f"{slam['n_recovered']}/{slam['n_kidnaps']}"
         + ("" if frames is None else f", after {frames:.0f} frames (median)")),
        ("loop closures", f"{slam['n_loop_closures']} "
                          f"({slam['n_loop_closures_rejected']} rejected)"),
        ("backend speed", "-" if fps is None else f"{fps:.1f} frames/s"),
    ]
    slam_table = Table(title="SLAM backend, kidnap sequence", box=box.SIMPLE_HEAD,
                       show_edge=False, show_header=False)
    slam_table.add_column(no_wrap=True)
    slam_table.add_column(overflow="fold")
    for row in rows:
        slam_table.add_row(*row)
    return runs, slam_table


def _run_label(method: str) -> str:
    """The demo's run names, short enough for the table at 80 columns."""
    labels = {"regressor": "regressor", "matching": "matching baseline",
              "regressor after update": "regressor, updated map",
              "regressor before update, kidnap seq.": "kidnap seq., regressor",
              "regressor after update, kidnap seq.": "kidnap seq., updated map"}
    return labels.get(method, method)


def print_demo_summary(summaries: list[dict], slam: dict, out: Console = console) -> None:
    for table in demo_tables(summaries, slam):
        out.print(table)


def next_steps(workdir: Path, query_image: Path, viewer: bool = True) -> list[str]:
    """What to try next, with the paths the demo wrote (as given: relative stays relative)."""
    q = shlex.quote
    w = Path(workdir)
    view = (f"slamreloc view {q(str(w / 'map'))} --report {q(str(w / 'report_slam.json'))} "
            f"--trajectory {q(str(w / 'trajectory_slam.txt'))}")
    return [
        "next:",
        f"  {view}" + ("   # the viewer again" if viewer else "   # the viewer"),
        f"  slamreloc localize {q(str(w / 'map'))} {q(str(query_image))}   # one image's pose",
        "  slamreloc map ../shared/data/7scenes_redkitchen --out maps/redkitchen   # real data: "
        "README, 'A first run on real data'",
        "  slamreloc --help   # every command; slamreloc COMMAND --help for its options",
    ]


def demo_viewer_inputs(workdir: Path, map_dir: Path, scene_dir: Path, port: int = 8080):
    """ViewerInputs for everything the demo wrote in `workdir`: its reports and trajectories
    (the `evaluate --trajectory` files and the SLAM trajectory), by their names (a user's file
    beside them is never read). report.json repeats report_regressor.json: left out."""
    from slamreloc.viewer import ViewerInputs

    workdir = Path(workdir)
    reports = [workdir / name for name in DEMO_REPORTS if name != "report.json"]
    trajectories = [workdir / name for name in DEMO_TRAJECTORIES]
    return ViewerInputs(map_dir, trajectories, reports, scene_dir, port=port)


def serve_demo_viewer(workdir: Path, map_dir: Path, scene_dir: Path, port: int = 8080) -> None:
    """Serve the viewer on everything the demo wrote (reports, trajectories) until Ctrl-C."""
    from slamreloc.viewer import serve

    console.rule("viewer")
    serve(demo_viewer_inputs(workdir, map_dir, scene_dir, port), echo=console.print)
