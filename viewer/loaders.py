"""Read what the viewer shows: the map folder, TUM trajectories, REPORT.json files, images.

Bad input ends as an InputError naming the file (the CLI prints it as one line)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from slamreloc.errors import InputError
from slamreloc.geometry import Rigid3, nearest_stamps, read_named_trajectory
from slamreloc.viewer import colors as palette
from slamreloc.viewer.data import (EvalReport, FrameView, MapView, PseudoLabelReport, QueryView,
                                   SceneData, Trajectory, ViewerInputs)

META, DATABASE, MAP_FORMAT = "slamreloc_map.json", "database.npz", "slamreloc-map"
GT_NAME = re.compile(r"(^|[^a-z])(gt|groundtruth|ground_truth|ground-truth)([^a-z]|$)", re.I)


# ---------------------------------------------------------------- datasets and images
def open_dataset(root: str | Path | None):
    """The dataset at `root`, or None when there is none (images are optional)."""
    if not root or not Path(root).is_dir():
        return None
    from slamreloc.datasets import load_dataset

    try:
        return load_dataset(root)
    except InputError:
        return None


def frames_by_name(dataset) -> dict:
    return {} if dataset is None else {f.name: f for f in dataset.frames("all")}


def read_rgb(path: Path | None, width: int | None = None) -> np.ndarray | None:
    """RGB uint8 image (resized to `width` when given), or None if it cannot be read."""
    import cv2

    if path is None:
        return None
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        return None
    img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    if width and img.shape[1] > width:
        h = max(1, round(img.shape[0] * width / img.shape[1]))
        img = cv2.resize(img, (width, h), interpolation=cv2.INTER_AREA)
    return img


# ---------------------------------------------------------------- map
def estimate_up(world_from_cam: np.ndarray) -> np.ndarray:
    """World up direction from camera poses (OpenCV cameras: image y points down), snapped to
    the nearest axis when within 25 degrees of it."""
    if len(world_from_cam) == 0:
        return np.array([0.0, 0.0, 1.0])
    up = -world_from_cam[:, :3, 1].mean(axis=0)
    if np.linalg.norm(up) < 1e-6:
        return np.array([0.0, 0.0, 1.0])
    up /= np.linalg.norm(up)
    axis = np.zeros(3)
    k = int(np.argmax(np.abs(up)))
    axis[k] = np.sign(up[k])
    return axis if up @ axis > np.cos(np.radians(25)) else up


def voxel_downsample(points: np.ndarray, max_points: int) -> tuple[np.ndarray, float]:
    """Indices of at most `max_points` points, one per voxel (the voxel grows until they fit),
    and the voxel size used (0 when nothing was dropped)."""
    n = len(points)
    if n <= max_points:
        return np.arange(n), 0.0
    lo, hi = points.min(axis=0), points.max(axis=0)
    voxel = float(np.prod(np.maximum(hi - lo, 1e-6)) / max_points) ** (1 / 3) / 4
    while True:
        keys = np.floor((points - lo) / voxel).astype(np.int64)
        _, first = np.unique(keys[:, 0] * 2_000_003 ** 2 + keys[:, 1] * 2_000_003 + keys[:, 2],
                             return_index=True)
        if len(first) <= max_points:
            return np.sort(first), voxel
        voxel *= 1.25


def load_map(inputs: ViewerInputs, dataset=None) -> MapView:
    root = Path(inputs.map_dir)
    if not root.is_dir():
        raise InputError(f"{root}: map folder not found")
    if not (root / META).is_file():
        raise InputError(f"{root}: not a slamreloc map (no {META})")
    try:
        meta = json.loads((root / META).read_text())
    except json.JSONDecodeError as err:
        raise InputError(f"{root / META}: not valid JSON ({err})") from None
    if not isinstance(meta, dict) or meta.get("format") != MAP_FORMAT:
        raise InputError(f"{root / META}: not a slamreloc map")
    if not (root / DATABASE).is_file():
        raise InputError(f"{root / DATABASE}: map has no database (the viewer draws its points)")
    try:
        with np.load(root / DATABASE) as z:
            arrays = {k: z[k] for k in z.files if k != "descriptors"}
    except (OSError, ValueError) as err:
        raise InputError(f"{root / DATABASE}: cannot read ({err})") from None
    for key in ("points", "keypoints", "frame_index", "world_from_cam"):
        if key not in arrays:
            raise InputError(f"{root / DATABASE}: no '{key}' array")
    points = np.asarray(arrays["points"], dtype=np.float32).reshape(-1, 3)
    names = list(meta.get("frame_names", []))
    poses = np.asarray(arrays["world_from_cam"], dtype=np.float64).reshape(-1, 4, 4)
    names += [f"frame {i}" for i in range(len(names), len(poses))]
    keep, voxel = voxel_downsample(points, inputs.max_points)
    frame_index = np.asarray(arrays["frame_index"])[keep]
    keypoints = np.asarray(arrays["keypoints"], dtype=np.float64)[keep]
    points = points[keep]

    if dataset is None:
        dataset = open_dataset(inputs.dataset or meta.get("dataset", {}).get("root"))
    by_name = frames_by_name(dataset)
    frames = [FrameView(n, Rigid3.from_matrix(m, tol=1e-2, source=f"{root / DATABASE}: pose"),
                        by_name[n].image_path if n in by_name else None)
              for n, m in zip(names, poses)]

    # Thumbnails for at most max_images frustums (evenly spread); colours from the same reads.
    with_image = set(np.linspace(0, len(frames) - 1, min(len(frames), inputs.max_images))
                     .round().astype(int).tolist()) if frames else set()
    colors = np.zeros((len(points), 3), np.uint8)
    coloured = np.zeros(len(points), bool)
    order = np.argsort(frame_index, kind="stable")
    bounds = np.searchsorted(frame_index[order], np.arange(len(frames) + 1))
    for i, frame in enumerate(frames):
        idx = order[bounds[i]:bounds[i + 1]]
        if frame.image_path is None or (len(idx) == 0 and i not in with_image):
            continue
        img = read_rgb(frame.image_path)
        if img is None:
            continue
        if len(idx):
            h, w = img.shape[:2]
            uv = np.round(keypoints[idx]).astype(int)
            u, v = np.clip(uv[:, 0], 0, w - 1), np.clip(uv[:, 1], 0, h - 1)
            colors[idx] = img[v, u]
            coloured[idx] = True
        if i in with_image:
            frame.thumbnail = _thumbnail(img, inputs.thumbnail_width)
    up = estimate_up(poses)
    source = "image"
    if not coloured.all():
        colors[~coloured] = palette.height_colors(points[~coloured], up)
        source = "image" if coloured.mean() > 0.5 else "height"

    pseudo = None
    for key in ("pseudo", "is_pseudo", "pseudo_label"):
        if key in arrays and len(arrays[key]) == len(keep):
            pseudo = np.asarray(arrays[key]).astype(bool)[keep]
    if pseudo is None and "source" in arrays and len(arrays["source"]) == len(keep):
        src = np.asarray(arrays["source"])[keep]
        pseudo = (src != 0) if src.dtype.kind in "iub" else ~np.isin(src.astype(str),
                                                                      ["train", "map", "gt"])
    pseudo_frames = []
    provenance = meta.get("pseudo_label") or meta.get("update") or {}
    flags = arrays.get("frame_pseudo", arrays.get("frame_source"))
    if flags is not None and len(flags) == len(frames):
        flags = np.asarray(flags)
        flags = flags != 0 if flags.dtype.kind in "iub" else ~np.isin(flags.astype(str),
                                                                       ["train", "map", "gt"])
        pseudo_frames = [f for f, p in zip(frames, flags) if p]
    elif isinstance(provenance, dict) and isinstance(provenance.get("frames"), list):
        wanted = set(map(str, provenance["frames"]))
        pseudo_frames = [f for f in frames if f.name in wanted]
    if pseudo_frames:
        ids = {id(f) for f in pseudo_frames}
        frames = [f for f in frames if id(f) not in ids]

    from slamreloc.types import Camera

    try:
        camera = Camera(**meta["camera"])
    except (KeyError, TypeError, InputError):
        camera = None
    return MapView(root, points, colors, int(len(arrays["points"])), source, frames, camera,
                   pseudo, pseudo_frames, voxel, meta)


def _thumbnail(img: np.ndarray, width: int) -> np.ndarray:
    import cv2

    if img.shape[1] <= width:
        return img
    h = max(1, round(img.shape[0] * width / img.shape[1]))
    return cv2.resize(img, (width, h), interpolation=cv2.INTER_AREA)


# ---------------------------------------------------------------- trajectories
def read_trajectory(path: str | Path, kind: str | None = None) -> Trajectory:
    """A TUM file `stamp tx ty tz qx qy qz qw` (camera-to-world), read by the core's
    `read_named_trajectory`: the first column may also be a frame name (older `evaluate
    --poses`), and the sidecar `<stem>.names.txt` that `evaluate --poses` writes names
    numeric stamps."""
    path = Path(path)
    tum = read_named_trajectory(path)
    if not tum.poses:
        raise InputError(f"{path}: no poses in the trajectory file")
    if kind is None:
        kind = "groundtruth" if GT_NAME.search(path.stem) else "estimate"
    return Trajectory(path.stem, path, tum.stamps, tum.names, tum.poses, kind)


def attach_truth(traj: Trajectory, dataset) -> None:
    """Ground truth and images for each pose: by frame name, else by timestamp within the
    dataset sequence that matches most of the trajectory's stamps. Sequences often share
    their timestamps (frame index / rate); among equally good ones the sequence whose poses
    lie nearest the trajectory's (median distance) is taken."""
    if dataset is None:
        return
    by_name = frames_by_name(dataset)
    matched = [by_name.get(n) if n else None for n in traj.names]
    if sum(m is not None for m in matched) < len(traj) / 2:
        best, best_key = None, (0, 0.0)
        for frames in dataset.sequences.values():
            j = nearest_stamps([f.timestamp for f in frames], traj.stamps, 1e-3)
            cand = [frames[k] if k >= 0 else None for k in j]
            key = (int((j >= 0).sum()), -_median_distance(traj, cand))
            if key > best_key:
                best, best_key = cand, key
        if best is not None and best_key[0] >= len(traj) / 2:
            matched = best
    traj.truth = [m.world_from_cam if m is not None else None for m in matched]
    traj.image_paths = [m.image_path if m is not None else None for m in matched]
    if not any(n for n in traj.names):
        traj.names = [m.name if m is not None else None for m in matched]


def _median_distance(traj: Trajectory, frames: list) -> float:
    """Median distance (m) between the trajectory's camera centres and those frames' (where
    known); inf when none is."""
    d = [np.linalg.norm(p.translation - f.world_from_cam.translation)
         for p, f in zip(traj.poses, frames) if f is not None and f.world_from_cam is not None]
    return float(np.median(d)) if d else float("inf")


def truth_by_stamp(traj: Trajectory, truth: Trajectory, max_dt: float = 0.02) -> None:
    """Ground truth from a ground-truth trajectory file: the nearest stamp within max_dt."""
    if len(truth) == 0:
        return
    j = nearest_stamps(truth.stamps, traj.stamps, max_dt)
    traj.truth = [truth.poses[k] if k >= 0 else None for k in j]
    if truth.image_paths:
        traj.image_paths = [truth.image_paths[k] if k >= 0 else None for k in j]


def truth_trajectory(est: Trajectory) -> Trajectory | None:
    """The ground truth of an estimate's frames, as its own (green) trajectory."""
    keep = [i for i, t in enumerate(est.truth) if t is not None]
    if not keep:
        return None
    return Trajectory(f"{est.name} (ground truth)", None, est.stamps[keep],
                      [est.names[i] for i in keep], [est.truth[i] for i in keep], "groundtruth",
                      [est.truth[i] for i in keep], [est.image_paths[i] for i in keep])


# ---------------------------------------------------------------- reports
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


def _pose_from(entry: dict, source: str) -> Rigid3 | None:
    """A pose stored in a report entry: a 4x4 `world_from_cam`, or `pose` [tx ty tz qx qy qz qw]."""
    if entry.get("world_from_cam") is not None:
        return Rigid3.from_matrix(np.array(entry["world_from_cam"], dtype=float), tol=1e-2,
                                  source=source)
    pose = entry.get("pose") or entry.get("tum")
    if isinstance(pose, (list, tuple)) and len(pose) == 7:
        v = np.array(pose, dtype=float)
        return Rigid3.from_qt(v[3:], v[:3])
    return None


def read_evaluate(path: Path, data: dict, dataset, trajectories: list[Trajectory]) -> EvalReport:
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
        est = _pose_from(q, f"{path}: per_query[{i}]") or (estimates.get(name)
                                                            if t_err is not None else None)
        missing += int(t_err is not None and est is None)
        queries.append(QueryView(name, est, frame.world_from_cam if frame else None,
                                 None if t_err is None else float(t_err),
                                 None if q.get("rotation_error_deg") is None
                                 else float(q["rotation_error_deg"]),
                                 q.get("num_inliers"), frame.image_path if frame else None))
    return EvalReport(path, data, queries, missing)


def read_pseudo_label(path: Path, data: dict) -> PseudoLabelReport:
    frames = []
    for i, f in enumerate(data.get("frames", []) if isinstance(data.get("frames"), list) else []):
        if isinstance(f, dict):
            pose = _pose_from(f, f"{path}: frames[{i}]")
            if pose is not None:
                frames.append(FrameView(str(f.get("name", i)), pose))
    pts = data.get("new_points")
    points = None
    if isinstance(pts, list) and pts:
        points = np.asarray(pts, dtype=np.float32).reshape(-1, 3)
    return PseudoLabelReport(path, data, frames, points)


def load_scene_data(inputs: ViewerInputs) -> SceneData:
    """Read every input; InputError on the first bad one (before any server starts)."""
    from slamreloc.viewer.slam_report import read_slam_report

    reports = [(Path(p), read_json(p)) for p in inputs.reports]
    trajectories = [read_trajectory(p) for p in inputs.trajectories]
    meta_root = None
    if (Path(inputs.map_dir) / META).is_file():
        try:
            meta_root = json.loads((Path(inputs.map_dir) / META).read_text()).get(
                "dataset", {}).get("root")
        except (json.JSONDecodeError, AttributeError):
            meta_root = None
    if inputs.dataset is not None and not Path(inputs.dataset).is_dir():
        raise InputError(f"{inputs.dataset}: dataset folder not found")
    dataset = open_dataset(inputs.dataset or meta_root)
    scene_map = load_map(inputs, dataset)
    for traj in trajectories:
        attach_truth(traj, dataset)
    truths = [t for t in trajectories if t.kind == "groundtruth"]
    for traj in trajectories:
        if traj.kind == "estimate" and truths and traj.errors_m is None:
            truth_by_stamp(traj, truths[0])
    scene = SceneData(scene_map, max_images=inputs.max_images,
                      thumbnail_width=inputs.thumbnail_width)
    for traj in trajectories:
        scene.trajectories.append(traj)
        has_gt = any(t.kind == "groundtruth" for t in trajectories)
        if traj.kind == "estimate" and not has_gt:
            gt = truth_trajectory(traj)
            if gt is not None:
                scene.trajectories.append(gt)
    for path, data in reports:
        kind = report_kind(data)
        if kind == "evaluate":
            recorded = data.get("dataset", {}).get("root") if isinstance(
                data.get("dataset"), dict) else None
            ds = dataset if inputs.dataset or not recorded else (open_dataset(recorded) or dataset)
            scene.evaluations.append(read_evaluate(path, data, ds, trajectories))
        elif kind == "slam":
            scene.slams.append(read_slam_report(path, data, trajectories))
        elif kind == "pseudo-label":
            scene.pseudo_labels.append(read_pseudo_label(path, data))
        else:
            scene.other_reports.append((path, data))
    return scene
