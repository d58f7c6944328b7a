"""The map as the viewer shows it, read through the core's map reader (`SceneMap.load` without
the regressor: schema and checksums checked): its points (voxel-downsampled to a budget,
coloured by their image, else by height), its training cameras with thumbnails, and what map
updates added (provenance.npz: the points whose labels did not come from the map's training
frames, and the frames that carry them)."""

from __future__ import annotations

import numpy as np
from slamreloc.viewer import colors as palette
from slamreloc.viewer.data import FrameView, MapView, ViewerInputs
from slamreloc.viewer.images import fit_width, frames_by_name, read_rgb

from slamreloc.errors import InputError
from slamreloc.geometry import Rigid3
from slamreloc.io.images import pixel_colours
from slamreloc.map.format import DATABASE, LABELLED
from slamreloc.map.scene_map import SceneMap, rows_by_frame
from slamreloc.types import aspect_problem


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
    if max_points < 1:
        raise InputError(f"`max_points` must be at least 1, got {max_points}")
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


def updated_frames(scene_map: SceneMap) -> np.ndarray:
    """(F,) bool per database frame: added by a map update. Such a frame's database rows are
    all pseudo-labels; an update appends the frames it registered after the frames it started
    from (also those that kept no label)."""
    db, provenance = scene_map.database, scene_map.provenance
    added = np.zeros(len(db.world_from_cam), bool)
    if provenance is None:
        return added
    added[db.frame_index[provenance.source != LABELLED]] = True
    n_last = scene_map.info.n_frames_updated
    if n_last:
        added[-n_last:] = True
    return added


def load_map(inputs: ViewerInputs, scene_map: SceneMap, dataset=None) -> MapView:
    """The map's points, cameras and update layers; images from `dataset` when it is given."""
    db = scene_map.database
    provenance = scene_map.provenance
    poses = np.asarray(db.world_from_cam, dtype=np.float64).reshape(-1, 4, 4)
    names = list(db.frame_names) or [f"frame {i}" for i in range(len(poses))]
    keep, voxel = voxel_downsample(db.points, inputs.max_points)
    frame_index = db.frame_index[keep]
    keypoints = np.asarray(db.keypoints, dtype=np.float64)[keep]
    points = np.asarray(db.points, dtype=np.float32)[keep]

    by_name = frames_by_name(dataset)
    source = f"{scene_map.root / DATABASE}: pose"
    frames = [FrameView(n, Rigid3.from_matrix(m, tol=1e-2, source=source),
                        by_name[n].image_path if n in by_name else None)
              for n, m in zip(names, poses)]

    # Thumbnails for at most max_images frustums (evenly spread); colours from the same reads.
    with_image = set(np.linspace(0, len(frames) - 1, min(len(frames), inputs.max_images))
                     .round().astype(int).tolist()) if frames else set()
    colors = np.zeros((len(points), 3), np.uint8)
    coloured = np.zeros(len(points), bool)
    for i, (frame, idx) in enumerate(zip(frames, rows_by_frame(frame_index, len(frames)))):
        if frame.image_path is None or (len(idx) == 0 and i not in with_image):
            continue
        img = read_rgb(frame.image_path)
        if img is None:
            continue
        cam = scene_map.camera  # never stretched onto an image of another aspect ratio
        if len(idx) and not aspect_problem(cam.width, cam.height, img.shape[1], img.shape[0]):
            camera = cam.scaled_to(img.shape[1], img.shape[0])
            colors[idx] = pixel_colours(img, camera.distort(keypoints[idx]))  # image pixels
            coloured[idx] = True
        if i in with_image:
            frame.thumbnail = fit_width(img, inputs.thumbnail_width)
    up = estimate_up(poses)
    color_source = "image"
    if not coloured.all():
        colors[~coloured] = palette.height_colors(points[~coloured], up)
        color_source = "image" if coloured.mean() > 0.5 else "height"

    pseudo = None if provenance is None else provenance.source[keep] != LABELLED
    added = updated_frames(scene_map)
    return MapView(scene_map.root, points, colors, len(db.points), color_source,
                   [f for f, a in zip(frames, added) if not a], scene_map.camera, pseudo,
                   [f for f, a in zip(frames, added) if a], voxel)
