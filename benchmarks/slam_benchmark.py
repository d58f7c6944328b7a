"""SLAM backend benchmark: odometry front ends (drift, frames per second), the backend without
relocalization (odometry + keyframe graph updates), and the relocalization cost per call.

    OMP_NUM_THREADS=1 python benchmarks/slam_benchmark.py DATASET --map MAP [--split test]

Prints a markdown table (medians; drift = ATE RMSE of the odometry chained from the first
true pose, metres).
"""

from __future__ import annotations

import argparse
import platform
import time

import numpy as np
import torch

from slamreloc.datasets import load_dataset, read_image
from slamreloc.slam.backend import SlamBackend
from slamreloc.slam.events import EventKind
from slamreloc.slam.feed import depth_camera_of, feed_all, read_frames
from slamreloc.slam.metrics import ate_rmse
from slamreloc.slam.run import make_odometry


class AnchorAtStart:
    """Anchors the backend once at the true first pose: the graph runs, nothing relocalizes."""

    name = "anchor-at-start"

    def __init__(self, world_from_cam):
        self.world_from_cam = world_from_cam

    def attach(self, backend):
        self.backend = backend

    def on_event(self, event, frame):
        if event.kind == EventKind.FRAME and self.backend.state.value != "tracking":
            self.backend.anchor(frame.index, self.world_from_cam)


def run_odometry(name, frames, inputs, depth_camera):
    """inputs: the frames' FrameInputs (depth only), read beforehand: the backend is timed
    without the reading."""
    backend = SlamBackend(make_odometry(name, depth_camera),
                          [AnchorAtStart(frames[0].world_from_cam)])
    t0, c0 = time.perf_counter(), time.thread_time()
    feed_all(backend, inputs)
    wall, cpu = time.perf_counter() - t0, time.thread_time() - c0
    odo = [frames[0].world_from_cam @ r.odom_from_cam for r in backend.frames]
    timing = backend.timer.summary()
    truth = [f.world_from_cam for f in frames]
    return {"odometry": name, "drift_ate_m": ate_rmse(odo, truth),
            "odometry_ms": timing["odometry"]["median_ms"],
            "graph_ms": timing.get("graph", {}).get("median_ms", 0.0),
            "backend_fps": len(frames) / wall, "backend_cpu_fps": len(frames) / cpu,
            "lost": sum(e.kind == EventKind.TRACKING_LOST for e in backend.event_log)}


def relocalization_cost(map_dir, dataset, frames, n=30):
    """Median ms per call: (SIFT + regressor + PnP wall, its CPU time, depth ICP wall or None
    when the map has no surface)."""
    from slamreloc.localize.localizer import RegressorLocalizer
    from slamreloc.cli.jobs import depth_refiner
    from slamreloc.map.scene_map import SceneMap

    scene_map = SceneMap.load(map_dir)
    loc = RegressorLocalizer(scene_map)
    refine = depth_refiner(scene_map, dataset) if scene_map.surface is not None else None
    ms, cpu, icp = [], [], []
    for f in frames[:: max(1, len(frames) // n)]:
        image, c0 = read_image(f.image_path), time.thread_time()
        est = loc.localize(image, f.camera)
        ms.append(est.timings_ms["total"])
        cpu.append(1000 * (time.thread_time() - c0))
        if refine is not None and est.estimate.success:
            t0 = time.perf_counter()
            refine(f, est.estimate.world_from_cam)
            icp.append(1000 * (time.perf_counter() - t0))
    return (float(np.median(ms)), float(np.median(cpu)),
            float(np.median(icp)) if icp else None)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("dataset")
    ap.add_argument("--map", default=None)
    ap.add_argument("--split", default="test")
    ap.add_argument("--odometry", nargs="+", default=["kiss-icp", "open3d"])
    args = ap.parse_args()
    torch.set_num_threads(1)
    ds = load_dataset(args.dataset)
    frames = ds.frames(args.split)
    inputs = list(read_frames(ds, frames, image=False, depth=True))
    depth_camera = depth_camera_of(frames)
    print(f"{args.dataset} split {args.split}: {len(frames)} frames "
          f"{inputs[0].depth.shape[1]}x{inputs[0].depth.shape[0]}; {platform.machine()}, "
          f"{platform.processor() or ''} torch threads 1")
    print("| odometry | drift ATE | odometry ms | graph ms | backend fps (wall) | "
          "backend fps (CPU time of this thread) | false tracking losses |")
    print("|---|---|---|---|---|---|---|")
    for name in args.odometry:
        r = run_odometry(name, frames, inputs, depth_camera)
        print(f"| {name} | {100 * r['drift_ate_m']:.1f} cm | {r['odometry_ms']:.1f} | "
              f"{r['graph_ms']:.2f} | {r['backend_fps']:.1f} | {r['backend_cpu_fps']:.1f} | "
              f"{r['lost']} |")
    if args.map:
        wall, cpu, icp = relocalization_cost(args.map, ds, frames)
        print(f"relocalization (SIFT + regressor + PnP) per call: {wall:.1f} ms wall, "
              f"{cpu:.1f} ms CPU time (median)")
        if icp is not None:
            print(f"depth ICP against the map's surface (incl. reading the depth PNG) per "
                  f"call: {icp:.1f} ms wall (median)")


if __name__ == "__main__":
    main()
