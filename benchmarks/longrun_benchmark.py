"""Long runs (issue 11): memory and throughput of one process that localizes 10 000 queries and
runs the SLAM backend over 5 000 frames.

    OMP_NUM_THREADS=1 python benchmarks/longrun_benchmark.py --workdir DIR [--queries 10000]
        [--slam-frames 5000] [--block 500] [--threads 1] [--out longrun.json]
        [--release-memory-every 100]  (0: never hand freed heap back, the A/B of that fix)

Renders the small synthetic scene (320x240 as the tests use, with the full 120-frame kidnap
sequence: 3 cm per frame, trackable) into DIR/scene and maps it into DIR/map (both reused when
present), then, in this one process:

1. localizes the query sequence's images (read from disk for every query) repeated to
   --queries queries with one RegressorLocalizer;
2. runs SlamBackend with the relocalization plugin over the kidnap sequence, thinned by the
   demo's kidnap schedule (30 frames kept, 15 dropped: 90 frames, 2 jumps) and repeated to
   --slam-frames frames, each repetition starting with another jump. Odometry is external (the Python API's
   `odometry_world_from_cam`): the true pose in a fixed odometry frame, so every jump is a
   tracking loss that relocalization must recover.

After every block of --block queries / frames it records the resident memory (RSS, after a
garbage collection), the block's throughput (wall clock: depends on what else the machine
runs) and its CPU time per item (this process, all threads: the steadier measure on a shared
machine); at the end, what the backend holds per frame.
Target (issue 11): RSS at the end within 10 % of RSS after the first block; steady throughput.
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import platform
import sys
import time
from dataclasses import fields, is_dataclass, replace
from pathlib import Path

import numpy as np

from slamreloc.datasets import load_dataset, read_image
from slamreloc.cli.demo import DEMO_KIDNAP
from slamreloc.geometry import Rigid3, axis_angle_to_matrix, pose_error
from slamreloc.localize.localizer import RegressorLocalizer
from slamreloc.map.build import MapConfig, build_map
from slamreloc.regressor.train import TrainConfig
from slamreloc.map.scene_map import SceneMap
from slamreloc.slam.backend import BackendConfig, SlamBackend
from slamreloc.slam.events import load_plugin
from slamreloc.slam.feed import feed, read_frames
from slamreloc.slam.run import kidnap_schedule
from slamreloc.synthetic import SceneConfig, render_scene

SCENE = SceneConfig(width=320, height=240, fx=262.5, fy=262.5, cx=159.5, cy=119.5,
                    n_map=60, n_query=20, n_kidnap=120, n_unlabelled=20)
ODOM_FROM_WORLD = Rigid3(axis_angle_to_matrix(np.array([0.1, -0.2, 0.3])),
                         np.array([1.0, -2.0, 0.5]))  # the odometry's own frame


def rss_mb() -> float:
    """Resident memory of this process now (after a garbage collection), MiB."""
    gc.collect()
    with open("/proc/self/statm") as f:
        pages = int(f.read().split()[1])
    return pages * os.sysconf("SC_PAGE_SIZE") / 2 ** 20


def deep_bytes(obj, seen: set | None = None) -> int:
    """Approximate memory held by a Python object graph (numpy arrays by their buffers)."""
    seen = set() if seen is None else seen
    if id(obj) in seen:
        return 0
    seen.add(id(obj))
    size = sys.getsizeof(obj)
    if isinstance(obj, np.ndarray):
        return size + (obj.nbytes if obj.base is None else 0)
    if isinstance(obj, dict):
        return size + sum(deep_bytes(k, seen) + deep_bytes(v, seen) for k, v in obj.items())
    if isinstance(obj, (list, tuple, set, frozenset)):
        return size + sum(deep_bytes(v, seen) for v in obj)
    if isinstance(obj, type):
        return 0
    if hasattr(obj, "__dict__"):
        return size + deep_bytes(vars(obj), seen)
    if is_dataclass(obj):  # slots
        return size + sum(deep_bytes(getattr(obj, f.name), seen) for f in fields(obj))
    return size


def prepare(workdir: Path, epochs: int) -> tuple[Path, Path]:
    scene = workdir / "scene"
    if not (scene / "scene.json").is_file():
        render_scene(scene, SCENE)
    map_dir = workdir / "map"
    if not SceneMap.is_map(map_dir):
        config = MapConfig(feature_options={"upsample": True}, train=TrainConfig(epochs=epochs))
        build_map(load_dataset(scene), map_dir, "train", config, progress=False)
    return scene, map_dir


def blocks_summary(rows: list[dict], key: str, cpu_key: str) -> dict:
    first, last = rows[0], rows[-1]
    out = {"rss_after_first_block_mb": round(first["rss_mb"], 1),
           "rss_end_mb": round(last["rss_mb"], 1),
           "rss_growth_pct": round(100 * (last["rss_mb"] / first["rss_mb"] - 1), 2)}
    for k in (key, cpu_key):
        values = [r[k] for r in rows]
        out.update({f"{k}_first_block": round(values[0], 2),
                    f"{k}_last_block": round(values[-1], 2),
                    f"{k}_min_block": round(min(values), 2),
                    f"{k}_max_block": round(max(values), 2),
                    f"{k}_median_block": round(float(np.median(values)), 2)})
    return out


def localize_run(scene: Path, map_dir: Path, n: int, block: int) -> dict:
    frames = load_dataset(scene).frames("query")
    localizer = RegressorLocalizer(SceneMap.load(map_dir))
    rows, t0, c0, ok, errs = [], time.perf_counter(), time.process_time(), 0, []
    for q in range(n):
        f = frames[q % len(frames)]
        est = localizer.localize(read_image(f.image_path), f.camera).estimate
        if est.success:
            ok += 1
            errs.append(pose_error(est.world_from_cam, f.world_from_cam)[0])
        if (q + 1) % block == 0:
            dt = time.perf_counter() - t0
            cpu_ms = 1000 * (time.process_time() - c0) / block
            rows.append({"done": q + 1, "queries_per_s": block / dt, "cpu_ms_per_query": cpu_ms,
                         "rss_mb": rss_mb(), "localized": ok / block,
                         "median_error_cm": 100 * float(np.median(errs)) if errs else None})
            t0, c0, ok, errs = time.perf_counter(), time.process_time(), 0, []
    return {"blocks": rows, **blocks_summary(rows, "queries_per_s", "cpu_ms_per_query")}


def slam_run(scene: Path, map_dir: Path, n: int, block: int, release_every: int) -> dict:
    dataset = load_dataset(scene)
    seq = dataset.frames("kidnap")
    kept, _ = kidnap_schedule(len(seq), *DEMO_KIDNAP)
    plugin = load_plugin("relocalization", map_dir=map_dir)
    backend = SlamBackend(plugins=[plugin],
                          config=BackendConfig(release_memory_every=release_every))
    frames = [seq[kept[i % len(kept)]] for i in range(n)]
    # the true pose as external odometry, timestamps running on across the repetitions
    inputs = (replace(inp, timestamp=i / 30.0,
                      odometry_world_from_cam=ODOM_FROM_WORLD @ f.world_from_cam)
              for i, (f, inp) in enumerate(zip(frames, read_frames(dataset, frames,
                                                                   depth=False))))
    rows, t0, c0 = [], time.perf_counter(), time.process_time()
    timer_before = {}
    for i, _ in enumerate(feed(backend, inputs)):
        if (i + 1) % block == 0:
            dt = time.perf_counter() - t0
            totals = {k: float(np.sum(v)) for k, v in backend.timer.samples.items()}
            ms = {f"{k}_ms_per_frame": round((totals[k] - timer_before.get(k, 0.0)) / block, 3)
                  for k in totals}
            timer_before = totals
            cpu_ms = 1000 * (time.process_time() - c0) / block
            rows.append({"done": i + 1, "frames_per_s": block / dt, "cpu_ms_per_frame": cpu_ms,
                         "rss_mb": rss_mb(), **ms, "state": backend.state.value,
                         "relocalizations": plugin.stats.n_attempts,
                         "anchors": plugin.stats.n_anchors,
                         "loop_closures": plugin.stats.n_loop_closures})
            t0, c0 = time.perf_counter(), time.process_time()
    backend.finish()
    held = {"frames": backend.frames, "event_log": backend.event_log,
            "timer": dict(backend.timer.samples), "plugin_decisions": plugin.stats.decisions,
            "plugin_accepted_frames": plugin.stats.accepted_frames}
    held_bytes = {k: deep_bytes(v) for k, v in held.items()}
    return {"blocks": rows, **blocks_summary(rows, "frames_per_s", "cpu_ms_per_frame"),
            "n_keyframes": len(backend.graph.poses()),
            "held_bytes": held_bytes,
            "held_bytes_per_frame": {k: round(v / n, 1) for k, v in held_bytes.items()},
            "held_lengths": {k: (sum(len(x) for x in v.values()) if isinstance(v, dict)
                                 else len(v)) for k, v in held.items()}}


def cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def markdown(result: dict) -> str:
    """The BENCHMARKS.md table of the runs in `result`."""
    head = ("| run | n | RSS after block 1 | RSS at end | growth | throughput per block: first, "
            "median, min-max, last | CPU ms per item per block: first, median, min-max, last |"
            "\n|---|---|---|---|---|---|---|")
    out = [head]
    for name, key, cpu, unit in (("localize", "queries_per_s", "cpu_ms_per_query", "queries/s"),
                                 ("slam", "frames_per_s", "cpu_ms_per_frame", "frames/s")):
        if name not in result:
            continue
        r = result[name]

        def span(k, r=r):
            return (f"{r[k + '_first_block']}, {r[k + '_median_block']}, "
                    f"{r[k + '_min_block']}-{r[k + '_max_block']}, {r[k + '_last_block']}")

        out.append(f"| {name} | {r['blocks'][-1]['done']} | {r['rss_after_first_block_mb']} MiB "
                   f"| {r['rss_end_mb']} MiB | {r['rss_growth_pct']:+.1f} % | {span(key)} "
                   f"{unit} | {span(cpu)} |")
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--workdir", type=Path, required=True)
    ap.add_argument("--queries", type=int, default=10_000)
    ap.add_argument("--slam-frames", type=int, default=5_000)
    ap.add_argument("--block", type=int, default=500)
    ap.add_argument("--epochs", type=int, default=60, help="training epochs of the map")
    ap.add_argument("--threads", type=int, default=1,
                    help="torch threads (1: a 2-core machine shared with other work)")
    ap.add_argument("--release-memory-every", type=int,
                    default=BackendConfig.release_memory_every,
                    help="SLAM frames between malloc_trim calls (0: never)")
    ap.add_argument("--skip-localize", action="store_true", help="only the SLAM run")
    ap.add_argument("--out", type=Path, help="write the full result (JSON)")
    args = ap.parse_args()
    import torch

    torch.set_num_threads(args.threads)

    t0 = time.perf_counter()
    scene, map_dir = prepare(args.workdir, args.epochs)
    setup_s = time.perf_counter() - t0
    result = {"cpu": cpu_name(), "cores": os.cpu_count(), "torch_threads":
              torch.get_num_threads(), "setup_s": round(setup_s, 1), "rss_start_mb":
              round(rss_mb(), 1)}
    runs = ("slam",) if args.skip_localize else ("localize", "slam")
    if "localize" in runs:
        t0 = time.perf_counter()
        result["localize"] = localize_run(scene, map_dir, args.queries, args.block)
        result["localize"]["wall_s"] = round(time.perf_counter() - t0, 1)
    t0 = time.perf_counter()
    result["slam"] = slam_run(scene, map_dir, args.slam_frames, args.block,
                              args.release_memory_every)
    result["slam"]["wall_s"] = round(time.perf_counter() - t0, 1)
    if args.out:
        args.out.write_text(json.dumps(result, indent=1))
    print(json.dumps({k: v for k, v in result.items() if k not in ("localize", "slam")}))
    for name in runs:
        print(name, json.dumps({k: v for k, v in result[name].items() if k != "blocks"}))
        for row in result[name]["blocks"]:
            print("  ", json.dumps({k: round(v, 3) if isinstance(v, float) else v
                                    for k, v in row.items()}))
    print(markdown(result))


if __name__ == "__main__":
    main()
