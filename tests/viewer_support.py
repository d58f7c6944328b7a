"""Inputs for the viewer tests, built from the synthetic scene: a map folder in the real
format (points back-projected from registered depth at integer keypoints, so each point's
image colour is known exactly), an estimated trajectory with a names sidecar, an `evaluate`
report with failures, and a `slam` report with events and graph edges; and a map updated by
the real `slamreloc pseudo-label` with its report. No test lives here."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slamreloc.datasets import load_dataset, read_depth
from slamreloc.geometry import Rigid3, axis_angle_to_matrix, tum_line

POINTS_PER_FRAME = 150
FAILED = (3, 11)  # query indices reported as not localized
BIG_ERROR = 5  # query index given a 30 cm error


@dataclass
class ViewerCase:
    scene: Path
    map_dir: Path
    trajectory: Path
    report: Path
    slam_report: Path
    n_points: int
    n_train: int
    n_query: int
    truth_colors: np.ndarray  # (n_points, 3) uint8: image colour at each point's keypoint
    query_names: list[str]
    estimate_error_m: np.ndarray  # (n_query,) position error of each estimate (nan: failed)


def build_map_folder(scene: Path, out: Path, seed: int = 0):
    from slamreloc.map.meta import (CameraMeta, DatasetMeta, FeatureMeta, MapMeta,
                                    RegressorMeta)
    from slamreloc.map.write import save_map
    from slamreloc.regressor.model import RegressorConfig, SceneCoordinateRegressor
    from slamreloc.map.scene_map import MapDatabase

    ds = load_dataset(scene)
    frames = ds.frames("train")
    rng = np.random.default_rng(seed)
    pts, kps, idx, cols = [], [], [], []
    import cv2

    for i, f in enumerate(frames):
        depth = read_depth(f.depth_path, ds.depth_units_per_metre)
        img = cv2.cvtColor(cv2.imread(str(f.image_path)), cv2.COLOR_BGR2RGB)
        v, u = np.nonzero(depth > 0)
        pick = rng.choice(len(u), POINTS_PER_FRAME, replace=False)
        u, v = u[pick], v[pick]
        z = depth[v, u]
        cam = np.stack([(u - f.camera.cx) / f.camera.fx * z, (v - f.camera.cy) / f.camera.fy * z,
                        z], axis=1)
        pts.append(f.world_from_cam.transform(cam))
        kps.append(np.stack([u, v], axis=1).astype(np.float32))
        idx.append(np.full(len(u), i))
        cols.append(img[v, u])
    db = MapDatabase(np.zeros((len(frames) * POINTS_PER_FRAME, 128), np.float16),
                     np.concatenate(pts).astype(np.float32), np.concatenate(kps),
                     np.concatenate(idx).astype(np.int32), [f.name for f in frames],
                     np.stack([f.world_from_cam.matrix() for f in frames]))
    model = SceneCoordinateRegressor(RegressorConfig.preset("tiny", 128))
    meta = MapMeta(features=FeatureMeta("sift"),
                   regressor=RegressorMeta("tiny", model.config.to_dict(),
                                           model.num_parameters()),
                   labels={"n_labelled": len(db.points)},
                   camera=CameraMeta.from_camera(frames[0].camera),
                   dataset=DatasetMeta(root=str(Path(scene).resolve()), kind=ds.kind,
                                       split="train"))
    save_map(out, meta, model, db)
    return out, np.concatenate(cols), len(frames)


def pseudo_label_map(map_dir: Path, scene: Path, out: Path) -> tuple[Path, Path]:
    """What `slamreloc demo` leaves: MAP updated from the scene's `unlabelled` sequence by the
    real `slamreloc pseudo-label` (one fine-tuning epoch), and its report. Returns (new map,
    report)."""
    out.mkdir(parents=True, exist_ok=True)
    new_map, report = out / "map_updated", out / "report_pseudo_label.json"
    run = subprocess.run([sys.executable, "-m", "slamreloc.cli", "pseudo-label", str(map_dir),
                          str(scene), "--out", str(new_map), "--report", str(report),
                          "--split", "unlabelled", "--epochs", "1", "--device", "cpu"],
                         capture_output=True, text=True, timeout=600,
                         cwd=Path(__file__).resolve().parents[1])
    assert run.returncode == 0, run.stderr
    return new_map, report


def perturb(pose: Rigid3, offset_m: float, rng) -> Rigid3:
    d = rng.normal(size=3)
    return Rigid3(pose.rotation @ axis_angle_to_matrix(rng.normal(size=3) * 0.01),
                  pose.translation + d / np.linalg.norm(d) * offset_m)


def build_case(scene: Path, out: Path) -> ViewerCase:
    out.mkdir(parents=True, exist_ok=True)
    map_dir, truth_colors, n_train = build_map_folder(scene, out / "map")
    queries = load_dataset(scene).frames("test")
    rng = np.random.default_rng(1)
    errors = rng.uniform(0.005, 0.03, len(queries))
    errors[BIG_ERROR] = 0.30
    errors[list(FAILED)] = np.nan
    estimates = [perturb(q.world_from_cam, e, rng) if np.isfinite(e) else None
                 for q, e in zip(queries, errors)]
    # `evaluate --trajectory`: numeric first column (index), names in the sidecar
    lines = [tum_line(f"{i:.6f}", p) for i, p in enumerate(estimates) if p is not None]
    traj = out / "poses_regressor.txt"
    traj.write_text("\n".join(lines) + "\n")
    traj.with_suffix(".names.txt").write_text("".join(
        f"{i:.6f} {q.name}\n" for i, (q, p) in enumerate(zip(queries, estimates))
        if p is not None))
    report = out / "report.json"
    report.write_text(json.dumps({
        "method": "regressor", "n_queries": len(queries),
        "n_localized": int(np.isfinite(errors).sum()), "median_translation_m": 0.02,
        "median_rotation_deg": 0.5, "recall": {"5cm5deg": 0.85}, "device": "cpu",
        "dataset": {"root": str(Path(scene).resolve()), "split": "test"},
        "per_query": [{"name": q.name,
                       "translation_error_m": float(e) if np.isfinite(e) else None,
                       "rotation_error_deg": 0.5 if np.isfinite(e) else None,
                       "num_inliers": 100 if np.isfinite(e) else 3}
                      for q, e in zip(queries, errors)]}))
    slam = out / "slam_report.json"
    slam.write_text(json.dumps({
        "ate_rmse_m": 0.05, "n_kidnaps": 1, "n_recovered": 1, "n_loop_closures": 2,
        "n_loop_closures_rejected": 1,
        "events": [{"frame": 6, "type": "kidnap"},
                   {"frame": 7, "kind": "tracking_lost"},
                   {"frame": 9, "type": "recovery", "accepted": True},
                   {"frame": 12, "type": "loop_closure", "accepted": True},
                   {"frame": 14, "type": "loop_closure", "accepted": False},
                   {"frame": 15, "type": "relocalization", "rejected": True,
                    "position": [0.1, 0.2, 1.0]},
                   {"frame": 16, "type": "new_keyframe"}],
        "graph_edges": [{"type": "odometry", "from": i, "to": i + 1} for i in range(10)]
        + [{"type": "loop_closure", "from": 2, "to": 12, "accepted": True},
           {"type": "loop_closure", "from": 4, "to": 14, "accepted": False}]}))
    return ViewerCase(Path(scene), map_dir, traj, report, slam, n_train * POINTS_PER_FRAME,
                      n_train, len(queries), truth_colors, [q.name for q in queries], errors)
