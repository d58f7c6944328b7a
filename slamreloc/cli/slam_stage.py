"""The `slamreloc slam` command's stage: run, write the report and trajectory, print a table."""

from __future__ import annotations

import os
from pathlib import Path

from rich.table import Table

from slamreloc.errors import InputError
from slamreloc.io.fileio import check_outputs, write_json
from slamreloc.geometry import write_tum_trajectory
from slamreloc.map.format import check_is_map
from slamreloc.runtime.progress import console
from slamreloc.slam.poses import final_trajectory
from slamreloc.slam.run import TOPIC_PREFIX, SlamRunConfig, run_slam


def run_slam_command(dataset: Path, map_dir: Path, report: Path, split: str = "test",
                     kidnap_every: int = 0, kidnap_skip: int = 20, odometry: str = "auto",
                     trajectory: Path | None = None, progress: bool = True,
                     plugin_options: dict | None = None, plugins: list | None = None,
                     poses: Path | None = None) -> dict:
    """plugin_options: keyword arguments of the relocalization plugin (benchmarks, tests);
    plugins: the backend's plugins instead of that one (benchmarks: a test-harness plugin);
    poses: the ground truth from this pose file instead of the dataset's (`--poses`)."""
    if kidnap_every < 0 or kidnap_skip < 0:
        raise InputError("--kidnap-every and --kidnap-skip must be >= 0")
    check_is_map(map_dir)  # what the inputs are, then where the outputs may go
    odometry_file = (odometry if odometry not in ("auto", "kiss-icp", "open3d")
                     and not odometry.startswith(TOPIC_PREFIX) else None)
    check_outputs({"--report": report, "--trajectory": trajectory},
                  {"the dataset": dataset, "the map": map_dir, "--odometry": odometry_file,
                   "--poses": poses})
    config = SlamRunConfig(split=split, odometry=odometry, kidnap_every=kidnap_every,
                           kidnap_skip=kidnap_skip, progress=progress,
                           plugin_options=plugin_options or {}, poses=poses)
    result, backend, frames = run_slam(dataset, map_dir, config, plugins)
    if trajectory is not None:
        poses = final_trajectory(backend)
        keep = [i for i, p in enumerate(poses) if p is not None]
        write_tum_trajectory(
            trajectory, [frames[i].timestamp for i in keep], [poses[i] for i in keep],
            [f"slamreloc slam {dataset} (split {split}), map frame, camera-to-world",
             "timestamp tx ty tz qx qy qz qw"], names=[frames[i].name for i in keep])
        result["trajectory"] = os.path.relpath(trajectory, Path(report).parent)
    write_json(report, result)
    print_slam_summary(result)
    return result


def print_slam_summary(r: dict) -> None:
    table = Table(title="SLAM backend")
    for col in ("frames", "ATE", "ATE odometry only", "kidnaps recovered", "frames to recover",
                "loop closures (rejected)", "backend fps"):
        table.add_column(col)
    cm = (lambda v: "-" if v is None else f"{100 * v:.1f} cm")  # noqa: E731
    table.add_row(str(r["n_frames"]), cm(r["ate_rmse_m"]), cm(r["ate_rmse_odometry_only_m"]),
                  f"{r['n_recovered']}/{r['n_kidnaps']}",
                  "-" if r["median_frames_to_recover"] is None
                  else f"{r['median_frames_to_recover']:.0f}",
                  f"{r['n_loop_closures']} ({r['n_loop_closures_rejected']})",
                  "-" if r["backend_fps"] is None else f"{r['backend_fps']:.1f}")
    console.print(table)
