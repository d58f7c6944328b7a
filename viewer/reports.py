"""The REPORT.json files the viewer reads: `evaluate` (per-query errors) and `pseudo-label`
(the registered frames' poses). The `slam` report has its own reader (slam_report.py)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from slamreloc.errors import InputError
from slamreloc.geometry import Rigid3
from slamreloc.viewer.data import (EvalReport, FrameView, PseudoLabelReport, QueryView,
                                   Trajectory)
from slamreloc.viewer.images import frames_by_name


def read_json(path: str | Path) -> dict:
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: report not found")
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise InputError(f"{path}: not valid JSON ({err})") from None
    if not isinstance(data, dict):
        raise InputError(f"{path}: not a report (expected a JSON object)")
    return data


def report_kind(data: dict) -> str:
    if "per_query" in data or "n_queries" in data:
        return "evaluate"
    if "n_pseudo_labels" in data or "n_new_points" in data:
        return "pseudo-label"
    if any(k in data for k in ("ate_rmse_m", "n_kidnaps", "events", "graph_edges")):
        return "slam"
    return "other"


def read_evaluate(path: Path, data: dict, dataset, trajectories: list[Trajectory]) -> EvalReport:
    """Per query: its error, and its estimated pose from the trajectories given with the
    report (`evaluate --poses` writes them; the report holds errors only)."""
    per_query = data.get("per_query", [])
    if not isinstance(per_query, list):
        raise InputError(f"{path}: 'per_query' is not a list")
    by_name = frames_by_name(dataset)
    estimates = {}
    for traj in trajectories:
        for name, pose in zip(traj.names, traj.poses):
            if name:
                estimates.setdefault(name, pose)
    queries, missing = [], 0
    for i, q in enumerate(per_query):
        if not isinstance(q, dict) or "name" not in q:
            raise InputError(f"{path}: per_query[{i}] has no 'name'")
        name = str(q["name"])
        frame = by_name.get(name)
        t_err = q.get("translation_error_m")
        est = estimates.get(name) if t_err is not None else None
        missing += int(t_err is not None and est is None)
        queries.append(QueryView(name, est, frame.world_from_cam if frame else None,
                                 None if t_err is None else float(t_err),
                                 None if q.get("rotation_error_deg") is None
                                 else float(q["rotation_error_deg"]),
                                 q.get("num_inliers"), frame.image_path if frame else None))
    return EvalReport(path, data, queries, missing)


def read_pseudo_label(path: Path, data: dict) -> PseudoLabelReport:
    """The registered frames: the report's `poses`, {frame name: 4x4 world_from_cam}."""
    poses = data.get("poses", {})
    if not isinstance(poses, dict):
        raise InputError(f"{path}: 'poses' is not an object of frame name -> 4x4 world_from_cam")
    frames = []
    for name, matrix in poses.items():
        where = f"{path}: poses[{name!r}]"
        try:
            m = np.array(matrix, dtype=float)
        except (TypeError, ValueError):
            raise InputError(f"{where}: not a 4x4 matrix of numbers") from None
        frames.append(FrameView(name, Rigid3.from_matrix(m, tol=1e-2, source=where)))
    return PseudoLabelReport(path, data, frames)
