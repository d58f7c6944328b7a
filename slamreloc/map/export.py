"""A map's labelled points and training cameras in the formats other tools read: a COLMAP text
model (pycolmap, the COLMAP GUI), a coloured PLY point cloud (open3d, MeshLab, CloudCompare)
and a TUM trajectory of the training poses (evo).

Map frame, metres. The database holds one row per labelled keypoint; rows of one triangulated
track share their world point exactly, so they become one COLMAP 3D point with a track of all
their observations (depth labels: one observation each). Colours come from the training images
when the map's dataset is at hand (the one it records, or `dataset`), else grey; a `dataset`
that is not the map's is refused (`check_dataset_of_map`).
"""

from __future__ import annotations

import json
import os
import shutil
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slamreloc.errors import InputError
from slamreloc.io.fileio import resolved, sha256_of
from slamreloc.io.outputs import (Undo, atomic_file, commit_output, exchange_paths,
                                  make_temp_dir, marked_file, naming_output, outputs_together,
                                  record_written, still_as_checked, temp_dir_path,
                                  temp_in_the_way, what_is_there)
from slamreloc.geometry import Rigid3, matrix_to_quat, write_tum_trajectory
from slamreloc.io.images import pixel_colours, read_image
from slamreloc.io.jsonio import read_json
from slamreloc.runtime.progress import track
from slamreloc.types import aspect_problem
from slamreloc.io.folder_lock import Debris, folder_write_lock
from slamreloc.map.scene_map import SceneMap, rows_by_frame

# the PLY header's comment that marks a file `export` wrote (and may replace)
PLY_COMMENT = "slamreloc map points"
PLY_FILE = marked_file(b"ply\n", PLY_COMMENT.encode(), "a PLY file of slamreloc map points")

GREY = 128


@dataclass
class ExportPoints:
    """The map's distinct world points with their colours and observations."""

    xyz: np.ndarray  # (P, 3) float64, map frame, metres
    rgb: np.ndarray  # (P, 3) uint8
    coloured: np.ndarray  # (P,) bool: coloured from an image (else grey)
    row_point: np.ndarray  # (M,) database row -> point index
    error_px: np.ndarray  # (P,) mean reprojection error over the point's observations


def frame_images(scene_map: SceneMap, dataset=None) -> tuple[Path | None, dict[str, Path]]:
    """(dataset root, frame name -> image file), from `dataset` (a Dataset) or the one the map
    records, and the frames it holds from its other datasets (`MapMeta.dataset_roots`: its
    updates', a SLAM session's earlier sessions'; a name already found is kept); (None, {})
    when none is at hand (moved or deleted). A recorded dataset that is there but cannot be
    read (an image gone, a named pipe) is an InputError naming it: the colours are not
    silently dropped."""
    from slamreloc.datasets import load_dataset

    def frames_of(root) -> dict[str, Path]:
        if root is None or not Path(root).is_dir():
            return {}
        try:
            return {f.name: f.image_path for f in load_dataset(root).frames("all")}
        except InputError as err:
            raise InputError(f"{err} (in {root}, a dataset the map records, read for the "
                             "points' colours: repair it, or give the map's images with "
                             "`--dataset`)") from None

    if dataset is None:
        root = scene_map.info.dataset_root
        images = frames_of(root)
        root = root if images else None
    else:
        root, images = Path(dataset.root), {f.name: f.image_path for f in dataset.frames("all")}
    for other in reversed(scene_map.info.dataset_roots()):  # the newest first
        if root is None or Path(other) != Path(root):
            for name, path in frames_of(other).items():
                images.setdefault(name, path)
    return root, images


def check_dataset_of_map(scene_map: SceneMap, dataset_dir: Path, dataset) -> None:
    """InputError unless `dataset` (given as `dataset_dir`) holds the images `scene_map` was
    built from: another dataset whose frames have the same names would colour the points
    with its own pictures, silently. Some of the map's frames must be in it, and:

    - a dataset the map records (its own, or its update's): taken as it is;
    - another path while a recorded one is at hand (a copy, say): each of the map's frames
      found in both has the same image file, byte for byte;
    - the map records none, or its recorded one has moved: the frames are of the map
      camera's size and (a map built on its dataset's own poses, never updated) have the
      poses the map holds for them."""
    import filecmp

    from slamreloc.datasets import load_dataset

    meta = scene_map.info
    recorded = [Path(p) for key, p in meta.recorded_inputs().items()
                if p is not None and "pose file" not in key]
    if any(resolved(r) == resolved(dataset_dir) for r in recorded):  # loops too
        return
    db = scene_map.database
    index = {name: i for i, name in enumerate(db.frame_names)}
    frames = [f for f in dataset.frames("all") if f.name in index]
    if not frames:
        first = db.frame_names[0] if len(db.frame_names) else "-"
        raise InputError(f"`dataset` {dataset_dir}: holds none of the map's "
                         f"{len(db.frame_names)} frames (such as '{first}'): not the dataset "
                         "it was built from")
    at_hand = {}  # frame name -> its image in a recorded dataset
    for root in recorded:
        try:
            for f in load_dataset(root).frames("all") if root.exists() else []:
                at_hand.setdefault(f.name, f.image_path)
        except InputError:
            continue  # not readable now: as if moved
    if at_hand:
        for f in frames:
            theirs = at_hand.get(f.name)
            if theirs is not None and not filecmp.cmp(f.image_path, theirs, shallow=False):
                raise InputError(f"`dataset` {dataset_dir}: {f.image_path} is not the image of "
                                 f"frame '{f.name}' in the dataset the map records ({theirs}): "
                                 "other images would stand for the map's (leave `dataset` "
                                 "out to use the map's)")
        return
    cam = scene_map.camera
    for f in frames:
        if (f.camera.width, f.camera.height) != (cam.width, cam.height):
            raise InputError(f"`dataset` {dataset_dir}: frame '{f.name}' is "
                             f"{f.camera.width}x{f.camera.height}, the map's camera "
                             f"{cam.width}x{cam.height}: not the images the map was built from")
    if meta.poses_source != "dataset" or meta.pseudo_label or dataset.poses_source != "dataset":
        return  # the map's poses are not the dataset's own (SLAM, --poses, an update)
    for f in frames:
        pose = np.asarray(db.world_from_cam[index[f.name]], np.float64)
        if f.world_from_cam is not None and np.abs(f.world_from_cam.matrix() - pose).max() > 1e-3:
            raise InputError(f"`dataset` {dataset_dir}: frame '{f.name}' has another pose than "
                             "the map holds for it (the map was built on its dataset's own "
                             "poses): not the dataset it was built from")


def export_points(scene_map: SceneMap, images: dict[str, Path],
                  progress: bool = True) -> ExportPoints:
    db = scene_map.database
    xyz, row_point = np.unique(np.asarray(db.points, np.float64), axis=0, return_inverse=True)
    row_point = row_point.reshape(-1)
    rgb = np.full((len(xyz), 3), GREY, np.uint8)
    coloured = np.zeros(len(xyz), bool)
    frame_rows = rows_by_frame(db.frame_index, len(db.frame_names))
    for i, name in enumerate(track(db.frame_names, "colouring points", enabled=progress)):
        rows = frame_rows[i][~coloured[row_point[frame_rows[i]]]]
        if len(rows) == 0 or name not in images:
            continue
        # keypoints are in the pinhole camera's pixels: back to the (distorted) image's
        image = read_image(images[name])
        cam = scene_map.camera
        if aspect_problem(cam.width, cam.height, image.shape[1], image.shape[0]):
            continue  # not this camera's image (another aspect ratio): never stretched, grey
        camera = cam.scaled_to(image.shape[1], image.shape[0])
        rgb[row_point[rows]] = pixel_colours(image, camera.distort(db.keypoints[rows]))
        coloured[row_point[rows]] = True
    # reprojection error of each observation with the map's camera
    cam = scene_map.camera
    cam_from_world = np.linalg.inv(np.asarray(db.world_from_cam, np.float64))[db.frame_index]
    pc = np.einsum("nij,nj->ni", cam_from_world[:, :3, :3], xyz[row_point]) \
        + cam_from_world[:, :3, 3]
    z = np.maximum(pc[:, 2], 1e-9)
    proj = np.stack([cam.fx * pc[:, 0] / z + cam.cx, cam.fy * pc[:, 1] / z + cam.cy], axis=1)
    err = np.linalg.norm(proj - db.keypoints, axis=1)
    error_px = np.bincount(row_point, err, len(xyz)) / np.maximum(
        np.bincount(row_point, minlength=len(xyz)), 1)
    return ExportPoints(xyz, rgb, coloured, row_point, error_px)


def write_colmap(scene_map: SceneMap, out: Path, points: ExportPoints,
                 images: dict[str, Path], root: Path | None = None) -> None:
    """cameras.txt, images.txt, points3D.txt in `out`, written beside it and renamed into
    place. Image names are the files' paths relative to the dataset root where known (a
    COLMAP project's image folder), else the frame names."""
    out = Path(out)
    db = scene_map.database
    cam = scene_map.camera
    names = []
    for name in db.frame_names:
        path = images.get(name)  # relative to the root where inside it (not an earlier
        inside = path is not None and root is not None and Path(path).resolve().is_relative_to(
            Path(root).resolve())  # session's dataset, whose images are elsewhere)
        names.append(os.path.relpath(path, root) if inside else name)
    out.parent.mkdir(parents=True, exist_ok=True)
    held = ExitStack()  # the model's write lock, until its swap is done
    held.enter_context(folder_write_lock(out, "this COLMAP model", COLMAP_DEBRIS))
    try:
        tmp = make_temp_dir(temp_dir_path(out), str(out))
    except BaseException:
        held.close()
        raise
    try:
        # COLMAP's pixel centres are at +0.5 (slamreloc: OpenCV, at integers)
        (tmp / "cameras.txt").write_text(
            "# slamreloc map camera\n"
            f"1 PINHOLE {cam.width} {cam.height} {float(cam.fx)!r} {float(cam.fy)!r} "
            f"{float(cam.cx) + 0.5!r} {float(cam.cy) + 0.5!r}\n")
        frame_rows = rows_by_frame(db.frame_index, len(db.frame_names))
        point2d_index = np.zeros(len(db.points), np.int64)
        lines = ["# IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME / POINTS2D[] as (X, Y, "
                 "POINT3D_ID)"]
        for i, name in enumerate(names):
            cam_from_world = Rigid3.from_matrix(db.world_from_cam[i], tol=1e-2).inverse()
            qx, qy, qz, qw = matrix_to_quat(cam_from_world.rotation).tolist()
            tx, ty, tz = cam_from_world.translation.tolist()
            lines.append(f"{i + 1} {qw!r} {qx!r} {qy!r} {qz!r} {tx!r} {ty!r} {tz!r} 1 {name}")
            rows = frame_rows[i]
            point2d_index[rows] = np.arange(len(rows))
            kp = db.keypoints[rows].astype(np.float64) + 0.5
            lines.append(" ".join(f"{x!r} {y!r} {p + 1}" for (x, y), p in
                                  zip(kp.tolist(), points.row_point[rows].tolist())))
        (tmp / "images.txt").write_text("\n".join(lines) + "\n")
        point_rows = rows_by_frame(points.row_point, len(points.xyz))  # rows of each point
        image_id = db.frame_index.astype(np.int64) + 1
        with open(tmp / "points3D.txt", "w") as f:
            f.write("# POINT3D_ID X Y Z R G B ERROR TRACK[] as (IMAGE_ID, POINT2D_IDX)\n")
            for p in range(len(points.xyz)):
                rows = point_rows[p]
                x, y, z = points.xyz[p].tolist()
                r, g, b = points.rgb[p].tolist()
                track_text = " ".join(f"{im} {k}" for im, k in
                                      zip(image_id[rows].tolist(), point2d_index[rows].tolist()))
                f.write(f"{p + 1} {x!r} {y!r} {z!r} {r} {g} {b} {points.error_px[p]:.6f} "
                        f"{track_text}\n")
        _write_export_mark(tmp, scene_map)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        held.close()
        raise

    old = temp_dir_path(out, "old")
    moved: list[Path] = []  # the old model, once moved aside (where there is no exchange)

    def swap() -> Undo:
        with naming_output(out):
            still_as_checked(out)  # a link, a file, another folder put there: not written
            if os.path.islink(out):
                raise InputError(f"{out}: is {what_is_there(out)}; not written (what is there "
                                 "is kept)")
            undo = put_in()
        record_written(out)
        return undo

    def put_in() -> Undo:  # the new model in; the old one back on undo
        if not os.path.lexists(out):
            os.replace(tmp, out)
            return lambda: os.replace(out, tmp)  # removed with the unused temporary
        if any(out.iterdir()) and not is_colmap_model(out):  # changed since the check
            raise InputError(f"{out}: is no longer the COLMAP model export wrote; "
                             "refusing to replace it")
        if exchange_paths(tmp, out):  # no instant without a model; the old one at tmp
            return lambda: exchange_paths(tmp, out)
        if os.path.lexists(old):  # not a killed export's (cleaned under the lock)
            raise InputError(temp_in_the_way(old, str(out)))
        os.replace(out, old)  # a kill -9 now: the next export puts it back
        moved.append(old)
        os.replace(tmp, out)

        def undo() -> None:
            os.replace(out, tmp)
            os.replace(old, out)
            moved.clear()
        return undo

    def discard() -> None:
        try:
            shutil.rmtree(tmp, ignore_errors=True)  # the unused new model, or the old one
            for made in moved:  # only the folder this writer moved aside
                shutil.rmtree(made, ignore_errors=True)
        finally:
            held.close()

    commit_output(swap, discard, folder=True)


def _unfinished_model(folder: Path) -> bool:
    """Whether `folder` holds only what `write_colmap` writes into its temporary (the text
    model files and export's mark, regular files, the mark written last): a killed export's,
    removed under the model's lock (`COLMAP_DEBRIS`). A binary model is never export's."""
    try:
        return all(e.name in COLMAP_TEXT_FILES | {EXPORT_MARK}
                   and e.is_file(follow_symlinks=False) for e in os.scandir(folder))
    except OSError:
        return False


COLMAP_MODEL_FILES = frozenset(f"{name}.{ext}" for name in ("cameras", "images", "points3D")
                               for ext in ("txt", "bin"))
EXPORT_MARK = "slamreloc_export.json"  # beside the model files: who wrote them, their digests
COLMAP_TEXT_FILES = frozenset(f"{name}.txt" for name in ("cameras", "images", "points3D"))


def _write_export_mark(folder: Path, scene_map: SceneMap) -> None:
    """The mark that makes `folder` export's own model: the map it came from and the SHA-256 of
    each model file as written (COLMAP and pycolmap read only the model files)."""
    digests = {}
    for name in sorted(COLMAP_MODEL_FILES):
        if (folder / name).is_file():
            with open(folder / name, "rb") as f:
                digests[name] = sha256_of(f)
    (folder / EXPORT_MARK).write_text(json.dumps(
        {"written_by": "slamreloc export", "map": str(Path(scene_map.root).resolve()),
         "sha256": digests}, indent=2))


def is_colmap_model(folder: Path) -> bool:
    """Whether `folder` is a COLMAP model `export` wrote, unchanged: its mark
    (`EXPORT_MARK`) and exactly the model files the mark lists, regular files with the
    SHA-256 recorded there. The only folder `write_colmap` replaces: a model another tool
    wrote (a COLMAP dataset's `sparse/0`), one edited since, or one with anything beside it
    (notes, an image folder) is the user's, never replaced."""
    folder = Path(folder)
    try:  # bounded, never blocking on a pipe, depth-checked: any file may sit at the mark's name
        digests = read_json(folder / EXPORT_MARK, "export mark")["sha256"]
        entries = {e.name: e for e in folder.iterdir()}
        if not isinstance(digests, dict) or set(entries) != {*digests, EXPORT_MARK} \
                or not set(digests) <= COLMAP_MODEL_FILES:
            return False
        for name, digest in digests.items():
            entry = entries[name]
            if entry.is_symlink() or not entry.is_file():
                return False
            with open(entry, "rb") as f:
                if sha256_of(f) != digest:
                    return False
    except (InputError, OSError, ValueError, KeyError, TypeError, AttributeError):
        return False
    return True


# a killed export's unfinished model, or the model it had moved aside: export's own, unchanged
# (`is_colmap_model`), put back where none is there
COLMAP_DEBRIS = Debris(new=_unfinished_model, old=is_colmap_model, put_back=is_colmap_model)


def write_ply(path: Path, points: ExportPoints) -> None:
    """Binary little-endian PLY: x y z (float32, metres) and red green blue (uchar)."""
    vertex = np.zeros(len(points.xyz), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                              ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for i, axis in enumerate("xyz"):
        vertex[axis] = points.xyz[:, i]
    for i, channel in enumerate(("red", "green", "blue")):
        vertex[channel] = points.rgb[:, i]
    header = (f"ply\nformat binary_little_endian 1.0\ncomment {PLY_COMMENT}, map frame, "
              f"metres\nelement vertex {len(vertex)}\nproperty float x\nproperty float y\n"
              "property float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n"
              "end_header\n")
    with atomic_file(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(header.encode("ascii"))
            f.write(vertex.tobytes())


def write_training_poses(scene_map: SceneMap, path: Path) -> None:
    """The training cameras as a TUM trajectory (camera-to-world; stamps = frame index), with
    the frame names in the `.names.txt` sidecar."""
    db = scene_map.database
    poses = [Rigid3.from_matrix(m, tol=1e-2) for m in db.world_from_cam]
    write_tum_trajectory(path, range(len(poses)), poses,
                         [f"slamreloc map {scene_map.root}: training cameras, map frame, "
                          "camera-to-world", "stamp = frame index; names in the .names.txt file"],
                         names=list(db.frame_names))


def _check_colmap_names(scene_map: SceneMap) -> None:
    """InputError unless every training frame's name can be an image name of a COLMAP text
    model that COLMAP (and slamreloc) reads back: one word (images.txt is split at blanks),
    each name once (a model's image names are unique)."""
    seen: set[str] = set()
    for name in scene_map.database.frame_names:
        if any(c.isspace() for c in name):
            raise InputError(f"{scene_map.root}: frame {name!r} holds a blank, which a COLMAP "
                             "text model cannot carry in an image name (`colmap` needs "
                             "one-word names; `ply` and `tum` take it)")
        if name in seen:
            raise InputError(f"{scene_map.root}: frame {name!r} is a training frame twice (a "
                             "map updated with frames it held), and a COLMAP model names each "
                             "image once (`ply` and `tum` take it)")
        seen.add(name)


def export_map(map_dir: Path, colmap: Path | None = None, ply: Path | None = None,
               tum: Path | None = None, dataset_dir: Path | None = None,
               progress: bool = True) -> dict:
    """Write the requested exports of the map at `map_dir`; returns a summary."""
    from slamreloc.io.outputs import check_outputs
    from slamreloc.map.format import check_is_map

    if colmap is None and ply is None and tum is None:
        raise InputError("export: nothing to write (give `colmap` DIR, `ply` FILE or `tum` FILE)")
    check_is_map(map_dir)
    from slamreloc.datasets.poses import NAMES_FILE, TUM_FILE, check_names_sidecar_free
    from slamreloc.geometry import names_sidecar
    from slamreloc.map.meta import MapMeta

    check_outputs({"`colmap`": colmap, "`ply`": ply, "`tum`": tum,
                   "`tum`'s names file": None if tum is None else names_sidecar(tum)},
                  {"the map": map_dir, "`dataset`": dataset_dir,
                   **MapMeta.read(map_dir).recorded_inputs()},
                  folders={"`colmap`": (is_colmap_model, "a COLMAP model")},
                  files={"`tum`": TUM_FILE, "`tum`'s names file": NAMES_FILE,
                         "`ply`": PLY_FILE})
    if tum is not None:
        check_names_sidecar_free(Path(tum), "`tum`")
    scene_map = SceneMap.load(map_dir, regressor=False)
    if colmap is not None:
        _check_colmap_names(scene_map)
    dataset = None
    if dataset_dir is not None:
        from slamreloc.datasets import load_dataset

        dataset = load_dataset(dataset_dir)
        check_dataset_of_map(scene_map, dataset_dir, dataset)
    root, images = (frame_images(scene_map, dataset) if colmap is not None or ply is not None
                    else (None, {}))  # the images colour the points only
    summary = {"frames": len(scene_map.database.frame_names)}
    points = None
    if colmap is not None or ply is not None:
        points = export_points(scene_map, images, progress)
        summary.update(points=len(points.xyz), observations=len(points.row_point),
                       coloured=int(points.coloured.sum()))
    with outputs_together():  # interrupted: all new, or all as they were
        if colmap is not None:
            with naming_output(colmap):
                write_colmap(scene_map, Path(colmap), points, images, root)
        if ply is not None:
            write_ply(Path(ply), points)
        if tum is not None:
            write_training_poses(scene_map, Path(tum))
    return summary
