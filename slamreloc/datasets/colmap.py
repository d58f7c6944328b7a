"""COLMAP project: a sparse model (posed, calibrated images) and the images it names.

    ROOT/images/NAME                     the images, NAME as the model lists it
    ROOT/sparse/0/ (or ROOT/sparse/)     cameras.{bin,txt}, images.{bin,txt}; points3D, and from
                                         COLMAP 3.12 rigs and frames, may lie beside them
    ROOT/TrainSplit.txt, TestSplit.txt   optional: sequence names, one a line

The model is read with pycolmap (which also composes rig and frame poses of COLMAP >= 3.12
models); points3D is not needed (slamreloc triangulates its own labels) and is not read, nor
are the images' 2D points (checked, then left out of what pycolmap is given).
A folder holding the model both as .bin and as .txt is read when the two describe the same
model (the same image names, each with the same camera and pose, within `geometry.AGREE_REL`:
`geometry.same_pose`), and refused when they disagree; a folder holding cameras or images of
one format without the other (`images.bin` beside `cameras.txt`, a stray `cameras.txt` beside a
.bin model) is refused, naming the missing file.
Each model file is first walked record by record (colmap_check.py), so that a damaged file is
an InputError naming the file (and the line), not garbage, an unbounded allocation or a hang in
pycolmap's reader.

A sequence is the folder of the image names (`seq1/0001.png` -> `seq1`; names without a
folder belong to one sequence named after ROOT). Every sequence is in the train split unless
split files exist. Cameras: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV
and OPENCV_FISHEYE (keypoints are undistorted, `slamreloc.camera_models`); COLMAP's principal
point (pixel centres at +0.5) is converted to OpenCV's (pixel centres at integers).
"""

from __future__ import annotations

import struct
import tempfile
from pathlib import Path, PurePosixPath

import numpy as np

from slamreloc.camera_models import MODELS
from slamreloc.datasets.base import Dataset
from slamreloc.datasets.colmap_check import ModelIndex, check_model
from slamreloc.datasets.io import check_frame_files
from slamreloc.errors import InputError
from slamreloc.geometry import Rigid3, pose_gap, same_pose, unit_quaternion, values_agree
from slamreloc.io.fileio import open_regular, optional_file, read_text
from slamreloc.io.jsonio import read_json
from slamreloc.types import Camera, Frame

MODEL_DIRS = ("sparse/0", "sparse")
FILES = ("cameras", "images")
OPTIONAL_FILES = ("rigs", "frames")
EXTS = ("bin", "txt")


def is_colmap(root: Path) -> bool:
    return (Path(root) / "sparse").is_dir()


def find_model(root: Path, dirs: tuple[str, ...] = MODEL_DIRS) -> tuple[Path, str]:
    """(model folder, "bin" or "txt") of the project at `root`: the first of `dirs` (relative
    to `root`; "." is `root` itself) that holds cameras and images. A folder with both formats
    complete gives "bin" (`read_checked` then reads the .txt too and compares); a folder with
    cameras or images of a format without the other is an InputError naming the missing file."""
    for rel in dirs:
        folder = root / rel
        present = {ext: [n for n in FILES if (folder / f"{n}.{ext}").is_file()] for ext in EXTS}
        if not any(present.values()):
            continue
        for ext in EXTS:  # a model file there, but a folder, a pipe or a device: said so
            for n in FILES:
                path = folder / f"{n}.{ext}"
                if n not in present[ext] and (path.exists() or path.is_symlink()):
                    with open_regular(path, "COLMAP model"):
                        pass
        partial = [(ext, names) for ext, names in present.items()
                   if names and len(names) < len(FILES)]
        if partial:
            complete = [ext for ext, names in present.items() if len(names) == len(FILES)]
            missing = "; ".join(
                f"{names[0]}.{ext} without {next(n for n in FILES if n not in names)}.{ext}"
                for ext, names in partial)
            beside = f" beside the .{complete[0]} model" if complete else ""
            raise InputError(f"{folder}: incomplete COLMAP model: {missing}{beside} (a model "
                             "is cameras and images, both .bin or both .txt)")
        return folder, "bin" if present["bin"] else "txt"
    if dirs == MODEL_DIRS:
        raise InputError(f"{root / 'sparse'}: no COLMAP model (cameras and images .bin or .txt) "
                         "in sparse/0 or sparse")
    where = " or ".join("the folder itself" if d == "." else d for d in dirs)
    raise InputError(f"{root}: no COLMAP model (cameras and images .bin or .txt) in {where}")


def other_format(folder: Path, ext: str) -> str | None:
    """The model's other format ("txt" beside "bin") where the folder holds it complete too."""
    other = "txt" if ext == "bin" else "bin"
    return other if all((folder / f"{n}.{other}").is_file() for n in FILES) else None


def read_reconstruction(folder: Path, ext: str, index: ModelIndex):
    """pycolmap's reading of the model files that `check_model` checked (`index`): points3D
    left out (an empty one stands in), and a text model's images.txt as the check read it,
    without its POINTS2D (`ModelIndex.images_text`), so that pycolmap's copy of the model
    does not grow with its 2D points (its reader would hold a POINTS2D line twice, and ~50
    bytes a point: ~7 times the line's size)."""
    import pycolmap

    with tempfile.TemporaryDirectory(prefix="slamreloc-colmap-") as tmp:
        for name in (*FILES, *OPTIONAL_FILES):
            src = folder / f"{name}.{ext}"
            if name == "images" and index.images_text is not None:
                (Path(tmp) / src.name).write_bytes(index.images_text)
            elif src.is_file():
                (Path(tmp) / src.name).symlink_to(src.resolve())
        empty = Path(tmp) / f"points3D.{ext}"
        empty.write_bytes(struct.pack("<Q", 0) if ext == "bin" else b"")
        try:
            return pycolmap.Reconstruction(tmp)
        except Exception as err:  # noqa: BLE001 - pycolmap's checks raise ValueError,
            # IndexError, MemoryError, RuntimeError: all mean "this model is not readable"
            message = " ".join(str(err).split())[:200] or type(err).__name__
            raise InputError(f"{folder}: not a readable COLMAP model ({message})") from None


def _attr(obj, name: str):
    """A pycolmap attribute that is a property in some versions and a method in others."""
    value = getattr(obj, name)
    return value() if callable(value) else value


def model_camera(cam, source: str) -> Camera:
    """Our Camera from a pycolmap camera: a pinhole, or one of the lens-distortion models
    slamreloc undistorts keypoints for (`slamreloc.camera_models`); InputError for others."""
    model = cam.model.name
    if model not in MODELS:
        raise InputError(f"{source}: camera {cam.camera_id} is {model}, which slamreloc does "
                         f"not model (known: {', '.join(MODELS)}); undistort the images with "
                         "`colmap image_undistorter` or re-run COLMAP with one of those")
    return Camera.from_colmap(model, int(cam.width), int(cam.height),
                              [float(p) for p in cam.params],
                              f"{source}: camera {cam.camera_id}")


def _image_path(images_dir: Path, name: str, source: Path) -> Path:
    rel = PurePosixPath(name)
    if rel.is_absolute() or ".." in rel.parts or not rel.parts:
        raise InputError(f"{source}: image name {name!r} points outside {images_dir}")
    return images_dir.joinpath(*rel.parts)


def image_world_from_cam(image, source: str) -> Rigid3 | None:
    """A pycolmap image's camera-to-world pose (the inverse of COLMAP's cam_from_world, in the
    model's units); None for an image the model holds without a pose."""
    posed = _attr(image, "has_pose") if hasattr(image, "has_pose") else _attr(image,
                                                                               "registered")
    if not posed:
        return None
    # from its quaternion, normalised (its norm was checked within unit_quaternion's 1e-3 as
    # the model was read: `colmap_check`), as every pose file's; the matrix pycolmap makes of
    # a quaternion a little off unit norm is no rotation
    pose = _attr(image, "cam_from_world")
    quat = unit_quaternion(np.asarray(pose.rotation.quat, np.float64), source)  # x y z w
    return Rigid3.from_qt(quat, np.asarray(pose.translation, np.float64)).inverse()


def read_checked(folder: Path, ext: str):
    """(ModelIndex, pycolmap Reconstruction) of the model in `folder`, its files checked
    (`check_model`) before pycolmap reads them. Where the folder holds the model in the other
    format too, that one is checked and read as well: InputError naming the folder unless both
    describe the same model (`models_disagree`)."""
    index = check_model(folder, ext)
    rec = read_reconstruction(folder, ext, index)
    other = other_format(folder, ext)
    if other is not None:
        problem = models_disagree(rec, read_reconstruction(folder, other,
                                                           check_model(folder, other)),
                                  (folder / f"images.{ext}", folder / f"images.{other}"))
        if problem:
            raise InputError(f"{folder}: the .{ext} and .{other} models disagree ({problem}); "
                             "keep one of them")
    return index, rec


def _image_record(rec, image, images_file: Path) -> tuple[str, int, int, tuple, Rigid3 | None]:
    """(camera model, width, height, parameters, world_from_cam or None) of a pycolmap image."""
    cam = rec.cameras[image.camera_id]
    return (cam.model.name, int(cam.width), int(cam.height), tuple(float(p) for p in cam.params),
            image_world_from_cam(image, f"{images_file}: pose of image {image.name!r}"))


def models_disagree(a, b, images_files: tuple[Path, Path]) -> str | None:
    """What differs between two pycolmap readings of a model, read from `images_files` (None:
    nothing): the image names, or an image's camera (model, size, parameters) or pose
    (`same_pose`). Image and camera ids are not compared (a writer may renumber them); what
    each image is, is."""
    images = [{im.name: im for im in rec.images.values()} for rec in (a, b)]
    for mine, theirs, file in ((images[0], images[1], images_files[0]),
                               (images[1], images[0], images_files[1])):
        only = sorted(set(mine) - set(theirs))
        if only:
            return f"image {only[0][:80]!r} is in {file.name} only"
    for name in sorted(images[0]):
        ra = _image_record(a, images[0][name], images_files[0])
        rb = _image_record(b, images[1][name], images_files[1])
        if ra[:3] != rb[:3] or not values_agree(ra[3], rb[3]):
            return f"image {name[:80]!r} has different cameras"
        if (ra[4] is None) != (rb[4] is None):
            posed = images_files[0] if ra[4] is not None else images_files[1]
            return f"image {name[:80]!r} is posed in {posed.name} only"
        if ra[4] is not None and not same_pose(ra[4], rb[4]):
            return f"image {name[:80]!r} has poses {pose_gap(ra[4], rb[4])}"
    return None


def read_model_poses(folder: Path, ext: str) -> dict[str, Rigid3 | None]:
    """world_from_cam (camera-to-world, the model's units) of every image of the model in
    `folder`, by image name; None for an image without a pose. The files are checked first
    (`read_checked`)."""
    _, rec = read_checked(folder, ext)
    images_file = folder / f"images.{ext}"
    return {image.name: image_world_from_cam(image, f"{images_file}: pose of image "
                                                    f"{image.name!r}")
            for image in sorted(rec.images.values(), key=lambda im: im.name)}


def _sequence_of(name: str, root: Path) -> str:
    parent = str(PurePosixPath(name).parent)
    return root.name if parent == "." else parent


def _read_split(path: Path) -> list[str]:
    names = []
    for line in read_text(path, "split", "max_text_bytes").splitlines():
        name = line.strip()
        if name and not name.startswith("#") and name not in names:
            names.append(name)
    return names


def load_colmap(root: Path) -> Dataset:
    root = Path(root)
    folder, ext = find_model(root)
    index, rec = read_checked(folder, ext)
    images_file = folder / f"images.{ext}"
    images_dir = root / "images"
    if not rec.images:
        raise InputError(f"{images_file}: the model has no images")
    if not images_dir.is_dir():
        raise InputError(f"{images_dir}: image folder not found (the model's images go there)")
    cameras: dict[int, Camera] = {}
    sequences: dict[str, list[Frame]] = {}
    for image in sorted(rec.images.values(), key=lambda im: im.name):
        if image.name not in index.image_cameras:  # pycolmap read what was checked
            raise InputError(f"{images_file}: image {image.name!r} not found by the check")
        if image.camera_id not in cameras:
            cameras[image.camera_id] = model_camera(rec.cameras[image.camera_id],
                                                      str(folder / f"cameras.{ext}"))
        camera = cameras[image.camera_id]
        path = _image_path(images_dir, image.name, images_file)
        try:  # what is there said so (not found, a named pipe, a name too long), or its size
            check_frame_files(path, (camera.width, camera.height))
        except InputError as err:
            raise InputError(f"{err} (listed in {images_file})") from None
        seq = _sequence_of(image.name, root)
        frames = sequences.setdefault(seq, [])
        frames.append(Frame(
            name=image.name, image_path=path, camera=camera, sequence=seq,
            world_from_cam=image_world_from_cam(image, f"{images_file}: pose of image "
                                                  f"{image.name!r}"),
            timestamp=len(frames) / 30.0))
    splits, split_files = {}, {}
    for split, fname in (("train", "TrainSplit.txt"), ("test", "TestSplit.txt")):
        if optional_file(root / fname, "split file"):
            splits[split] = _read_split(root / fname)
            split_files[split] = root / fname
    if not splits:  # no split files: everything is for mapping
        splits["train"] = sorted(sequences)
    return Dataset(root, "colmap", dict(sorted(sequences.items())), splits,
                   split_files=split_files, metric=_sfm_metric(root))


def _sfm_metric(root: Path) -> bool:
    """False where `slamreloc sfm` wrote the project without a metric scale (sfm.json)."""
    path = root / "sfm.json"
    if not optional_file(path, "SfM summary"):  # a folder or pipe there: refused
        return True  # a COLMAP project from elsewhere: its units are the user's to know
    metric = read_json(path, "SfM summary").get("metric", True)
    if not isinstance(metric, bool):
        raise InputError(f"{path}: 'metric' must be true or false")
    return metric
