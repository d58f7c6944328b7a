"""Depth ICP against a map's surface: how far it pulls wrong poses back, and at what cost.

    python benchmarks/experiments/icp_benchmark.py ../shared/data/7scenes_redkitchen --map M [--split test]
        [--points 600 2500]

Per query frame of the split: (1) the regressor's PnP pose and the same after ICP, against the
truth; (2) the truth perturbed by fixed errors (7 cm / 2.5 deg, 15 cm / 5 deg, 0.5 m, 20 deg),
then ICP, for each source point budget. Medians; one thread.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from slamreloc.datasets import load_dataset, read_image
from slamreloc.geometry import Rigid3, axis_angle_to_matrix, pose_error
from slamreloc.localize.localizer import RegressorLocalizer
from slamreloc.map.scene_map import SceneMap
from slamreloc.map.surface import IcpConfig, frame_cloud, refine_pose

PERTURBATIONS = ((0.07, 2.5), (0.15, 5.0), (0.5, 0.0), (0.0, 20.0))  # metres, degrees


def unit(rng) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def summary(name: str, errors: list, times: list, taken: list) -> str:
    e = np.array(errors)
    return (f"| {name} | {100 * np.median(e[:, 0]):.2f} cm / {np.median(e[:, 1]):.2f} deg | "
            f"{100 * np.mean((e[:, 0] <= 0.05) & (e[:, 1] <= 5)):.1f} % | "
            f"{100 * np.mean(taken):.0f} % | {np.median(times):.1f} ms |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("dataset")
    ap.add_argument("--map", required=True)
    ap.add_argument("--split", default="test")
    ap.add_argument("--points", type=int, nargs="+", default=[600, 2500])
    args = ap.parse_args()
    torch.set_num_threads(1)
    ds = load_dataset(args.dataset)
    scene_map = SceneMap.load(args.map)
    surface, loc = scene_map.surface, RegressorLocalizer(scene_map)
    frames = ds.frames(args.split)
    clouds = [frame_cloud(f, ds) for f in frames]
    print(f"{len(frames)} frames, surface {len(surface.points)} points")
    print("| start | after ICP (median) | within 5 cm / 5 deg | fit taken | ICP ms |")
    print("|---|---|---|---|---|")
    pnp, refined, times, taken = [], [], [], []
    for f, cloud in zip(frames, clouds):
        est = loc.localize(read_image(f.image_path), f.camera).estimate
        if not est.success:
            continue
        t0 = time.perf_counter()
        fit = refine_pose(surface, cloud, est.world_from_cam)
        times.append(1000 * (time.perf_counter() - t0))
        taken.append(fit.accepted)
        pnp.append(pose_error(est.world_from_cam, f.world_from_cam))
        refined.append(pose_error(fit.chosen(), f.world_from_cam))
    print(summary(f"PnP poses ({len(pnp)} localized): before", pnp, [0], [0]))
    print(summary("PnP poses: after ICP", refined, times, taken))
    for n in args.points:
        config = IcpConfig(max_source_points=n)
        for metres, degrees in PERTURBATIONS:
            rng, errors, times, taken = np.random.default_rng(0), [], [], []
            for f, cloud in zip(frames[::2], clouds[::2]):
                truth = f.world_from_cam
                guess = Rigid3(truth.rotation @ axis_angle_to_matrix(unit(rng) * np.radians(
                    degrees)), truth.translation + unit(rng) * metres)
                t0 = time.perf_counter()
                fit = refine_pose(surface, cloud, guess, config)
                times.append(1000 * (time.perf_counter() - t0))
                taken.append(fit.accepted)
                errors.append(pose_error(fit.world_from_cam, truth))
            print(summary(f"truth + {100 * metres:.0f} cm / {degrees:g} deg, {n} points",
                          errors, times, taken), flush=True)


if __name__ == "__main__":
    main()
