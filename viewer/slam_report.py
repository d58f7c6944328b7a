"""The `slam` REPORT.json as the viewer reads it: events on the trajectory and pose-graph edges.

All format knowledge of the slam report lives here, tolerant of missing keys:

    "events": [{"frame" | "index": int, "timestamp": float,
                "type" | "kind": "relocalization" | "loop_closure" | "kidnap" | "recovery"
                                 | "tracking_lost" | "tracking_recovered" | "map_updated" | ...,
                "accepted": bool (or "rejected": bool, or "status": "accepted"|"rejected"),
                "world_from_cam": 4x4 | "position": [x, y, z] | "pose": [tx ty tz qx qy qz qw]}]
    "graph_edges" | "edges": [{"type": "odometry" | "loop_closure" | ..., "from" | "i": int,
                               "to" | "j": int, "accepted": bool,
                               "a" | "from_position": [x,y,z], "b" | "to_position": [x,y,z]}]
    "kidnap_frames" | "kidnaps": [int, ...]         (frames where the camera was teleported)
    "trajectory": "TRAJ.txt"                         (relative to the report, and read: a
                                                      missing or unreadable one is an error;
                                                      without the field, the first estimate
                                                      trajectory given to the viewer)

Frame indices resolve to positions through the trajectory (its i-th pose, or the pose whose
stamp equals the index / the event's timestamp)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from slamreloc.errors import InputError
from slamreloc.geometry import MAX_COORDINATE, Rigid3, unit_quaternion
from slamreloc.io.jsonio import Json
from slamreloc.viewer.data import GraphEdge, SlamEvent, SlamReport, Trajectory
from slamreloc.viewer.trajectories import read_trajectory

TYPE_ALIASES = {
    "relocalization": "relocalization", "reloc": "relocalization", "relocalisation":
        "relocalization", "anchor": "relocalization",
    "loop_closure": "loop_closure", "loop": "loop_closure", "map_updated": "loop_closure",
    "loop-closure": "loop_closure",
    "kidnap": "kidnap", "kidnapped": "kidnap", "teleport": "kidnap",
    "recovery": "recovery", "tracking_recovered": "recovery", "recovered": "recovery",
    "tracking_lost": "tracking_lost", "lost": "tracking_lost",
}
IGNORED = {"frame", "new_keyframe", "keyframe"}


def _first(e: Json, *keys: str) -> Json | None:
    """The first of `keys` (aliases of one field) that `e` holds."""
    return next((e.child(k) for k in keys if e.has(k)), None)


def _accepted(e: Json) -> bool:
    if e.has("accepted"):
        return e.child("accepted").bool()
    if e.has("rejected"):
        return not e.child("rejected").bool()
    info = e.get("info")
    status = e.opt("status", Json.str) or (
        info.opt("status", Json.str) if info is not None else None)
    if status:
        return status.lower() not in ("rejected", "failed", "refused")
    if info is not None and info.has("accepted"):
        return info.child("accepted").bool()
    return True


def _opt_index(field: Json | None) -> int | None:
    """A frame index (a whole number >= 0), or None where the field is absent."""
    if field is None:
        return None
    if field.int() < 0:
        raise InputError(f"{field.source}: {field.where} is a frame index, a whole number "
                         f">= 0; got {field.value}")
    return field.value


def _position(e: Json) -> np.ndarray | None:
    if e.has("world_from_cam"):
        field = e.child("world_from_cam")
        rows = 3 if isinstance(field.value, list) and len(field.value) == 3 else 4
        # a pose by every pose reader's rule (rigid, within the coordinate bound)
        return Rigid3.from_matrix(field.array((rows, 4)),
                                  source=f"{field.source}: {field.where}").translation.copy()
    for key in ("position", "pose", "tum"):
        if e.has(key):
            v = e.child(key)
            n = len(v.value) if isinstance(v.value, list) else 0
            values = v.array((7 if n == 7 else 3,))
            if n == 7:  # tx ty tz qx qy qz qw: the quaternion by every pose reader's rule
                unit_quaternion(values[3:], f"{v.source}: {v.where}")
            return _within_bound(v, values[:3])
    return None


def _within_bound(field: Json, xyz: np.ndarray) -> np.ndarray:
    """`xyz`, the position `field` gives, where it lies within MAX_COORDINATE metres (every
    pose reader's bound): the one rule of every position a slam report holds (an event's,
    a graph edge's ends)."""
    if np.abs(xyz).max() > MAX_COORDINATE:
        raise InputError(f"{field.source}: {field.where} lies beyond {MAX_COORDINATE:g} m")
    return xyz


def _end(e: Json, positions: tuple[str, ...], indices: tuple[str, ...], locate):
    field = _first(e, *positions)
    if field is not None:
        return _within_bound(field, field.array((3,)))
    return locate(_opt_index(_first(e, *indices)), None)


class _Locator:
    """Frame index or timestamp -> position on the slam trajectory."""

    def __init__(self, traj: Trajectory | None):
        self.traj = traj

    def __call__(self, frame: int | None, stamp: float | None) -> np.ndarray | None:
        t = self.traj
        if t is None or len(t) == 0:
            return None
        for key in (stamp, frame):
            if key is None:
                continue
            hit = np.flatnonzero(np.abs(t.stamps - key) < 1e-6)
            if len(hit):
                return t.poses[int(hit[0])].translation
        if frame is not None and 0 <= frame < len(t):
            return t.poses[frame].translation
        return None


def read_slam_report(path: Path, data: dict, trajectories: list[Trajectory]) -> SlamReport:
    report = Json(data, path)
    traj = None
    name = report.opt("trajectory", Json.str)
    if name == "":
        raise InputError(f"{path}: 'trajectory' is empty: name the trajectory file, or null")
    if name:  # named: it must be there and be one (`--trajectory`'s rule)
        try:
            traj = read_trajectory(Path(path).parent / name, kind="estimate",
                                   allow_empty=True)
        except InputError as err:
            raise InputError(f"{path}: its 'trajectory' {err}") from None
    if traj is None:
        traj = next((t for t in trajectories if t.kind == "estimate"), None)
    locate = _Locator(traj)

    events = []
    raw_events = report.get("events")
    for e in [] if raw_events is None else raw_events.list():
        e.obj()
        kind_field = _first(e, "type", "kind")
        raw_type = "other" if kind_field is None else kind_field.str().lower()
        if raw_type in IGNORED:
            continue
        kind = TYPE_ALIASES.get(raw_type, "other")
        frame = _opt_index(_first(e, "frame", "index"))
        stamp = e.opt("timestamp", Json.number)
        pos = _position(e)
        if pos is None:
            pos = locate(frame, stamp)
        events.append(SlamEvent(frame, stamp, kind, _accepted(e), pos, raw_type))
    known_kidnaps = {ev.frame for ev in events if ev.type == "kidnap"}
    kidnaps = _first(report, "kidnap_frames", "kidnaps")
    for f in [] if kidnaps is None else kidnaps.list():
        f = _opt_index(f)
        if f not in known_kidnaps:
            events.append(SlamEvent(f, None, "kidnap", True, locate(f, None), "kidnap"))

    edges = []
    raw_edges = _first(report, "graph_edges", "edges")
    for e in [] if raw_edges is None else raw_edges.list():
        e.obj()
        a = _end(e, ("a", "from_position"), ("from", "i"), locate)
        b = _end(e, ("b", "to_position"), ("to", "j"), locate)
        if a is None or b is None:
            continue
        kind_field = _first(e, "type", "kind")
        kind = "other" if kind_field is None else kind_field.str().lower()
        edges.append(GraphEdge(TYPE_ALIASES.get(kind, kind), a, b, _accepted(e)))
    return SlamReport(path, data, events, edges, traj)
