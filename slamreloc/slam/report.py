"""The REPORT.json of `slamreloc slam` (DESIGN.md contract plus diagnostics)."""

from __future__ import annotations

import numpy as np

from slamreloc.geometry import Rigid3, align_poses, distinct_stamps, pose_error
from slamreloc.slam.events import EventKind
from slamreloc.slam.metrics import ate_rmse
from slamreloc.slam.poses import final_trajectory, odometry_only_trajectory

FALSE_ANCHOR = (0.25, 10.0)  # metres, degrees: an anchor further than this from the truth


def _ate(poses, truth, align=False):
    """ATE RMSE (metres) over the frames with both poses; None where there is none (aligned:
    fewer than 3, which fix no alignment)."""
    pairs = [(p, t) for p, t in zip(poses, truth) if p is not None and t is not None]
    if len(pairs) < (3 if align else 1):
        return None
    return ate_rmse([p for p, _ in pairs], [t for _, t in pairs], align)


CONFIRMING = (EventKind.TRACKING_RECOVERED, EventKind.MAP_UPDATED)


def kidnap_stats(confirmed: list[int], online: list, truth: list, jumps: list[int]) -> dict:
    """Per kidnap (first frame after the jump = p): the first frame c >= p, before the next
    kidnap, where a relocalization confirmed a map-frame pose (`confirmed`: the frames of the
    anchors and accepted loop closures, in order); frames to recover = c - p; error of the
    pose returned at c (`online`: each frame's world_from_cam as returned, or None)."""
    ends = [*jumps[1:], len(online)]
    frames, errors = [], []
    for p, end in zip(jumps, ends):
        c = next((f for f in confirmed if p <= f < end), None)
        if c is None:
            continue
        frames.append(c - p)
        if truth[c] is not None and online[c] is not None:
            errors.append(pose_error(online[c], truth[c]))
    med = (lambda v: float(np.median(v)) if len(v) else None)  # noqa: E731
    return {"n_kidnaps": len(jumps), "n_recovered": len(frames),
            "median_frames_to_recover": med(frames), "frames_to_recover": frames,
            "recovered_median_error_m": med([e[0] for e in errors]),
            "recovered_median_error_deg": med([e[1] for e in errors])}


def anchor_stats(backend, truth) -> dict:
    anchors = [e for e in backend.event_log if e.kind == EventKind.TRACKING_RECOVERED]
    errs = [pose_error(e.world_from_cam, truth[e.frame]) for e in anchors
            if truth[e.frame] is not None]
    false = [e for e in errs if e[0] > FALSE_ANCHOR[0] or e[1] > FALSE_ANCHOR[1]]
    return {"n_anchors": len(anchors),
            "n_reanchors": sum(bool(e.info.get("reanchor")) for e in anchors),
            "n_tracking_lost": sum(e.kind == EventKind.TRACKING_LOST for e in backend.event_log),
            "n_false_anchors": len(false) if errs else None}


def session_truth(backend, truth: list) -> tuple[list, Rigid3 | None]:
    """The ground truth in the map frame of a session that made its own (a live map started
    from nothing): truth moved by the rigid alignment of its keyframes onto their final poses
    (`align_poses` without scale: rotation from the cameras' orientations, which stays
    determined for a nearly straight path); (truth, map_from_truth), or (truth, None) with
    fewer than 3 such keyframes."""
    final = final_trajectory(backend)
    pairs = [(final[f.index], truth[f.index]) for f in backend.frames
             if f.key is not None and final[f.index] is not None and truth[f.index] is not None]
    if len(pairs) < 3:
        return truth, None
    map_from_truth = align_poses([t for _, t in pairs], [p for p, _ in pairs],
                                 with_scale=False).rigid
    return [None if t is None else map_from_truth @ t for t in truth], map_from_truth


def build_report(backend, frames, jumps, plugins, config, t_backend_s: float,
                 own_frame: bool = False, map_from_truth: Rigid3 | None = None) -> dict:
    """own_frame: the session made its map's frame (a live map started from nothing), so the
    truth is first aligned onto it on the keyframes (`session_truth`); map_from_truth: the
    truth's placement in a map's frame that is not the dataset's (a map a session learned),
    fitted on that map's own frames."""
    truth = [f.world_from_cam for f in frames]
    if own_frame:
        truth, map_from_truth = session_truth(backend, truth)
    elif map_from_truth is not None:
        truth = [None if t is None else map_from_truth @ t for t in truth]
    final, odo = final_trajectory(backend), odometry_only_trajectory(backend)
    online = [f.online_world_from_cam for f in backend.frames]
    timing = backend.timer.summary()
    stats = next((p.stats.to_dict() for p in plugins if hasattr(p, "stats")), {})
    n = len(frames)
    core_ms = sum(timing.get(k, {}).get("total_ms", 0.0) for k in ("odometry", "graph"))
    rnd = (lambda v: None if v is None else round(v, 4))  # noqa: E731
    report = {
        "n_frames": n,
        "odometry": getattr(backend.odometry, "name", config.odometry), "split": config.split,
        "ate_rmse_m": rnd(_ate(final, truth)),
        "ate_rmse_aligned_m": rnd(_ate(final, truth, align=True)),
        "ate_rmse_odometry_only_m": rnd(_ate(odo, truth)),
        "ate_rmse_odometry_only_aligned_m": rnd(_ate(odo, truth, align=True)),
        "truth_aligned_on_keyframes": map_from_truth is not None,
        "ate_rmse_online_m": rnd(_ate(online, truth)),
        "n_frames_without_pose_online": sum(p is None for p in online),
        **kidnap_stats([e.frame for e in backend.event_log if e.kind in CONFIRMING], online,
                       truth, jumps),
        "n_loop_closures": stats.get("n_loop_closures", 0),
        "n_loop_closures_rejected": stats.get("n_rejected", 0),
        **anchor_stats(backend, truth),
        "relocalization": stats,
        "kidnap_every": config.kidnap_every, "kidnap_skip": config.kidnap_skip,
        "timing_ms": {k: {kk: round(vv, 3) for kk, vv in v.items()} for k, v in timing.items()},
        "backend_fps": round(n / (core_ms / 1000), 2) if core_ms else None,
        "overall_fps": round(n / t_backend_s, 2) if t_backend_s else None,
        "relocalization_ms_per_call": timing.get("relocalization", {}).get("median_ms"),
        "events": event_list(backend, plugins, jumps, frames),
    }
    return report


def event_list(backend, plugins, jumps: list[int], frames) -> list[dict]:
    """Kidnaps, tracking lost / recovered, and every relocalization decision (accepted or
    rejected, with its map-frame position), by processed-frame index (and the frame's
    timestamp, as in the trajectory file), in order."""
    events = [{"frame": j, "type": "kidnap"} for j in jumps]
    events += [{"frame": e.frame, "type": e.kind.value, **(
        {"position": [round(float(v), 4) for v in e.world_from_cam.translation]}
        if e.world_from_cam is not None else {})} for e in backend.event_log
        if e.kind in (EventKind.TRACKING_LOST, EventKind.TRACKING_RECOVERED)]
    for p in plugins:
        events += getattr(getattr(p, "stats", None), "decisions", [])
    stamps = distinct_stamps([f.timestamp for f in frames])  # the trajectory file's column
    for e in events:
        e["timestamp"] = stamps[e["frame"]]
    return sorted(events, key=lambda e: e["frame"])
