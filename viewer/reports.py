"""The REPORT.json files the viewer reads: `evaluate` (per-query errors) and `pseudo-label`
(the registered frames' poses). The `slam` report has its own reader (slam_report.py)."""

from __future__ import annotations

from pathlib import Path

from slamreloc.errors import InputError
from slamreloc.geometry import Rigid3
from slamreloc.io.fileio import open_regular
from slamreloc.io.jsonio import Json
from slamreloc.io.jsonio import read_json as read_json_file
from slamreloc.io.values import check_values
from slamreloc.map.meta import check_recorded_path
from slamreloc.types import frame_name_problem
from slamreloc.viewer.data import (EvalReport, FrameView, PseudoLabelReport, QueryView,
                                   Trajectory)
from slamreloc.viewer.images import frames_by_name


def read_json(path: str | Path) -> dict:
    """A report: a JSON object (bounded size and depth; `slamreloc.io.jsonio`) whose numbers
    are all finite floats or integers within int64 (`check_values`: an integer literal of 400
    digits or a `1e400`, infinite once read, is refused here, naming the file and the field,
    not left to fail in whatever converts it later), and whose counts and measures have the
    meaning their names give them."""
    path = Path(path)
    # missing, or there and not a regular file (a named pipe, a device, a folder): one line
    # naming its kind, read without blocking (`open_regular`), before the JSON reader's own
    open_regular(path, "report").close()
    data = read_json_file(path, "JSON")
    check_values(data, path, names=("poses",), name_problem=frame_name_problem)
    return data


def recorded_dataset(path: Path, data: dict) -> str | None:
    """The dataset folder an evaluate report records (`dataset.root`), if any: an absolute
    path, as `evaluate` writes it and as a map records one (`check_recorded_path`: a relative
    one would name another dataset from each folder the viewer starts in)."""
    field = Json(data, path).get("dataset")
    root = None if field is None else field.opt("root", Json.str)
    if root is not None:
        check_recorded_path(root, "dataset.root", path)
    return root


def read_evaluate(path: Path, data: dict, dataset, trajectories: list[Trajectory]) -> EvalReport:
    """Per query: its error, and its estimated pose from the trajectories given with the
    report (`evaluate --trajectory` writes them; the report holds errors only)."""
    report = Json(data, path)
    per_query = report.get("per_query")
    by_name = frames_by_name(dataset)
    estimates = {}
    for traj in trajectories:
        for name, pose in zip(traj.names, traj.poses):
            if name:
                estimates.setdefault(name, pose)
    n_queries, n_localized = report.opt("n_queries", Json.int), report.opt("n_localized",
                                                                            Json.int)
    if n_queries is not None and n_localized is not None and n_localized > n_queries:
        raise InputError(f"{path}: n_localized {n_localized} is more than n_queries {n_queries}")
    queries, missing, seen = [], 0, set()
    for q in [] if per_query is None else per_query.list():
        name = q.child("name").str()
        problem = frame_name_problem(name)
        if problem:
            raise InputError(f"{path}: {q.where}.name {name[:80]!r} {problem}")
        if name in seen:
            raise InputError(f"{path}: {q.where}.name: frame {name[:80]!r} is listed twice")
        seen.add(name)
        frame = by_name.get(name)
        t_err = q.opt("translation_error_m", Json.number)
        r_err = q.opt("rotation_error_deg", Json.number)
        inliers = q.opt("num_inliers", Json.int)
        est = estimates.get(name) if t_err is not None else None
        missing += int(t_err is not None and est is None)
        queries.append(QueryView(name, est, frame.world_from_cam if frame else None, t_err,
                                 r_err, inliers, frame.image_path if frame else None))
    return EvalReport(path, data, queries, missing)


def read_pseudo_label(path: Path, data: dict) -> PseudoLabelReport:
    """The registered frames: the report's `poses`, {frame name: 4x4 world_from_cam}."""
    poses = Json(data, path).get("poses")
    frames = []
    for name, matrix in [] if poses is None else poses.items():
        m = matrix.array((4, 4))
        frames.append(FrameView(name, Rigid3.from_matrix(  # the pose files' rule (RIGID_TOL)
            m, source=f"{path}: {matrix.where}")))
    return PseudoLabelReport(path, data, frames)
