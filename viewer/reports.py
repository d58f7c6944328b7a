"""The REPORT.json files the viewer reads: `evaluate` (per-query errors) and `pseudo-label`
(the registered frames' poses). The `slam` report has its own reader (slam_report.py)."""

from __future__ import annotations

import math
import re
from pathlib import Path

from slamreloc.errors import InputError
from slamreloc.geometry import Rigid3
from slamreloc.io.fileio import open_regular
from slamreloc.io.jsonio import Json
from slamreloc.io.jsonio import read_json as read_json_file
from slamreloc.viewer.data import (EvalReport, FrameView, PseudoLabelReport, QueryView,
                                   Trajectory)
from slamreloc.types import frame_name_problem
from slamreloc.viewer.images import frames_by_name


MAX_INT = 2 ** 63 - 1  # a report's counts and indices: int64 (numpy reads them as such)


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
    check_values(data, path)
    return data


# Report fields by their names, as every slamreloc report writes them: `n_*` / `num_*` are
# counts, `*_m` / `*_cm` / `*_deg` / `*_px` / `*_s` / `*_ms` distances, errors, angles and
# durations, never negative, angles (`*_deg`) at most 180; `recall`, `*_fraction` and
# `*precision_*` shares in [0, 1] (null: not measured; an object of such, as `timings_s`,
# holds them per stage or threshold). A report's own `poses` maps frame names, not fields.
COUNT = re.compile(r"(n|num)_\w+")
MEASURE = re.compile(r"\w+_(m|cm|deg|px|s|ms)")
FRACTION = re.compile(r"recall|\w+_fraction|\w*precision_\w+")  # shares: [0, 1]
NAMES = ("poses",)


def check_values(value, source) -> None:
    """InputError naming `source` and the field of the first value that breaks the report
    rules: a number that is not a finite float or an integer within +-MAX_INT, a count
    (`COUNT`) that is not a whole number >= 0, a measure (`MEASURE`) that is not a number >= 0,
    or a key of `poses` that cannot name a frame (`frame_name_problem`). Iterative: any
    nesting."""
    stack = [(value, "", "top")]
    while stack:
        v, where, rule = stack.pop()
        if isinstance(v, dict):
            for k, c in v.items():
                field = f"{where}.{k}" if where else str(k)
                if rule == "names":
                    problem = frame_name_problem(k)
                    if problem:
                        raise InputError(f"{source}: {where}: the frame name {k[:80]!r} "
                                         f"{problem}")
                    stack.append((c, field, None))
                else:
                    stack.append((c, field, _rule(k, rule)))
            continue
        if isinstance(v, list):
            # a list under a count or measure holds counts or measures
            inner = rule if rule in ("count", "measure", "angle", "fraction") else None
            stack.extend((c, f"{where}[{i}]", inner) for i, c in enumerate(v))
            continue
        _check_scalar(v, where, rule, source)


def _rule(key: str, parent: str | None) -> str | None:
    """The rule for the value under `key` (inside an object checked by `parent`'s rule;
    "top": the report itself)."""
    if parent in ("measure", "angle", "fraction"):  # an object of such: each value is one
        return parent
    if key in NAMES and parent == "top":  # a report's own `poses` (not `dataset.poses`)
        return "names"
    if COUNT.fullmatch(key):
        return "count"
    if FRACTION.fullmatch(key):
        return "fraction"
    if MEASURE.fullmatch(key):
        return "angle" if key.endswith("_deg") else "measure"
    return None


def _check_scalar(v, where: str, rule: str | None, source) -> None:
    field = where or "the value"
    if isinstance(v, int) and not isinstance(v, bool) and abs(v) > MAX_INT:
        raise InputError(f"{source}: {field}: an integer of {len(str(abs(v)))} digits, out of "
                         f"range (at most {MAX_INT})")
    if isinstance(v, float) and not math.isfinite(v):
        raise InputError(f"{source}: {field}: a number beyond the range of a float (read as "
                         "infinite)")
    if rule is None or v is None:
        return
    number = isinstance(v, (int, float)) and not isinstance(v, bool)
    if rule == "count" and not (number and isinstance(v, int) and v >= 0):
        raise InputError(f"{source}: {field} is a count, a whole number >= 0; got {_short(v)}")
    if rule == "measure" and not (number and v >= 0):
        raise InputError(f"{source}: {field} is a measure (distance, angle or time), a number "
                         f">= 0; got {_short(v)}")
    if rule == "angle" and not (number and 0 <= v <= 180):
        raise InputError(f"{source}: {field} is an angle between two directions, in [0, 180] "
                         f"degrees; got {_short(v)}")
    if rule == "fraction" and not (number and 0 <= v <= 1):
        raise InputError(f"{source}: {field} is a share, a number in [0, 1]; got {_short(v)}")
    if rule == "names":
        raise InputError(f"{source}: {field} must be an object of frame names, got {_short(v)}")


def _short(v) -> str:
    text = repr(v)
    return text if len(text) <= 40 else text[:37] + "..."


def recorded_dataset(path: Path, data: dict) -> str | None:
    """The dataset folder an evaluate report records (`dataset.root`), if any."""
    field = Json(data, path).get("dataset")
    return None if field is None else field.opt("root", Json.str)


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
    queries, missing = [], 0
    for q in [] if per_query is None else per_query.list():
        name = q.child("name").str()
        problem = frame_name_problem(name)
        if problem:
            raise InputError(f"{path}: {q.where}.name {name[:80]!r} {problem}")
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
        frames.append(FrameView(name, Rigid3.from_matrix(
            m, tol=1e-2, source=f"{path}: {matrix.where}")))
    return PseudoLabelReport(path, data, frames)
