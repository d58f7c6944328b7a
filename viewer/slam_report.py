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
    "trajectory": "TRAJ.txt"                         (relative to the report; else the first
                                                      estimate trajectory given to the viewer)

Frame indices resolve to positions through the trajectory (its i-th pose, or the pose whose
stamp equals the index / the event's timestamp)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from slamreloc.errors import InputError
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


def _accepted(e: dict) -> bool:
    if "accepted" in e:
        return bool(e["accepted"])
    if "rejected" in e:
        return not bool(e["rejected"])
    status = str(e.get("status", e.get("info", {}).get("status", "") if isinstance(
        e.get("info"), dict) else "")).lower()
    if status:
        return status not in ("rejected", "failed", "refused")
    if isinstance(e.get("info"), dict) and "accepted" in e["info"]:
        return bool(e["info"]["accepted"])
    return True


def _int(v) -> int | None:
    try:
        return None if v is None else int(v)
    except (TypeError, ValueError):
        return None


def _float(v) -> float | None:
    try:
        return None if v is None else float(v)
    except (TypeError, ValueError):
        return None


def _position(e: dict, source: str) -> np.ndarray | None:
    if e.get("world_from_cam") is not None:
        m = np.asarray(e["world_from_cam"], dtype=float)
        if m.shape not in ((4, 4), (3, 4)):
            raise InputError(f"{source}: world_from_cam is not a 4x4 matrix")
        return m[:3, 3].copy()
    for key in ("position", "pose", "tum"):
        v = e.get(key)
        if isinstance(v, (list, tuple)) and len(v) in (3, 7):
            return np.asarray(v[:3], dtype=float)
    return None


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
    traj = None
    if isinstance(data.get("trajectory"), str):
        candidate = (Path(path).parent / data["trajectory"])
        if candidate.is_file():
            traj = read_trajectory(candidate, kind="estimate")
    if traj is None:
        traj = next((t for t in trajectories if t.kind == "estimate"), None)
    locate = _Locator(traj)

    raw_events = data.get("events", [])
    if not isinstance(raw_events, list):
        raise InputError(f"{path}: 'events' is not a list")
    events = []
    for i, e in enumerate(raw_events):
        if not isinstance(e, dict):
            raise InputError(f"{path}: events[{i}] is not an object")
        raw_type = str(e.get("type", e.get("kind", "other"))).lower()
        if raw_type in IGNORED:
            continue
        kind = TYPE_ALIASES.get(raw_type, "other")
        frame, stamp = _int(e.get("frame", e.get("index"))), _float(e.get("timestamp"))
        pos = _position(e, f"{path}: events[{i}]")
        if pos is None:
            pos = locate(frame, stamp)
        events.append(SlamEvent(frame, stamp, kind, _accepted(e), pos, raw_type))
    known_kidnaps = {ev.frame for ev in events if ev.type == "kidnap"}
    for f in data.get("kidnap_frames", data.get("kidnaps", [])) or []:
        f = _int(f)
        if f is not None and f not in known_kidnaps:
            events.append(SlamEvent(f, None, "kidnap", True, locate(f, None), "kidnap"))

    raw_edges = data.get("graph_edges", data.get("edges", []))
    if not isinstance(raw_edges, list):
        raise InputError(f"{path}: 'graph_edges' is not a list")
    edges = []
    for i, e in enumerate(raw_edges):
        if not isinstance(e, dict):
            raise InputError(f"{path}: graph_edges[{i}] is not an object")
        a = e.get("a", e.get("from_position"))
        b = e.get("b", e.get("to_position"))
        a = np.asarray(a, float)[:3] if isinstance(a, (list, tuple)) else locate(
            _int(e.get("from", e.get("i"))), None)
        b = np.asarray(b, float)[:3] if isinstance(b, (list, tuple)) else locate(
            _int(e.get("to", e.get("j"))), None)
        if a is None or b is None:
            continue
        kind = str(e.get("type", e.get("kind", "other"))).lower()
        edges.append(GraphEdge(TYPE_ALIASES.get(kind, kind), a, b, _accepted(e)))
    return SlamReport(path, data, events, edges, traj)

