"""Reading the small text files of a dataset (poses, intrinsics), with one-line errors naming
the file and line. Images and depth maps are read by `slamreloc.io.images` (re-exported here)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from slamreloc.errors import InputError
from slamreloc.geometry import Rigid3
from slamreloc.io import fileio
from slamreloc.io.images import check_frame_files, image_header, image_size, read_depth, read_image
from slamreloc.io.numbers import number_problem
from slamreloc.types import Frame, camera_problem, k_matrix_problem

__all__ = ["check_frame_files", "image_header", "image_size", "read_depth", "read_frame_depth",
           "read_frame_image", "read_image", "read_intrinsics", "read_pose", "read_text",
           "write_pose"]
MAX_TEXT_BYTES = 1 << 20  # a pose or an intrinsics matrix


def read_frame_image(frame: Frame) -> np.ndarray:
    """A dataset frame's image, RGB uint8 (H, W, 3), held to the rule of the dataset's load
    (`check_frame_files`): a file replaced since by one of another size is refused."""
    return read_image(frame.image_path, size=(frame.camera.width, frame.camera.height))


def read_frame_depth(frame: Frame, units_per_metre: float) -> np.ndarray:
    """A dataset frame's depth map as stored: float32 metres in its depth camera's pixels
    (`frame.depth_camera`, or the image's where registered, whose size is then held to the
    rule of the dataset's load); InputError without one."""
    if frame.depth_path is None:
        raise InputError(f"{frame.image_path}: no depth image")
    registered = frame.depth_camera is None
    return read_depth(frame.depth_path, units_per_metre,
                      (frame.camera.width, frame.camera.height) if registered else None)


def read_text(path: Path, what: str, limit: int | str = "max_text_bytes") -> str:
    """A text file's contents (`slamreloc.io.fileio.read_text`); a binary or oversized file
    is an InputError naming it."""
    return fileio.read_text(path, what, limit)


def _read_matrix(path: Path, what: str, shape: tuple[int, int]) -> np.ndarray:
    path = Path(path)
    text = read_text(path, what, MAX_TEXT_BYTES)
    lines = [(i, line.split()) for i, line in enumerate(text.splitlines(), 1)
             if line.strip() and not line.lstrip().startswith("#")]
    rows = [words for _, words in lines]
    if len({len(r) for r in rows}) > 1:
        raise InputError(f"{path}: {what} is not a numeric matrix (rows of different lengths)")
    for i, words in lines:  # `slamreloc.io.numbers`: plain ASCII decimals, finite
        problem = next((p for p in map(number_problem, words) if p), None)
        if problem:
            word = next(w for w in words if number_problem(w))
            raise InputError(f"{path}:{i}: {what} is not a numeric matrix ({word[:40]!r} is "
                             f"{problem})")
    m = np.array([[float(v) for v in words] for _, words in lines], dtype=np.float64)
    m = m.reshape(len(rows), -1) if rows else np.zeros((0, 0))
    if m.shape != shape:
        raise InputError(f"{path}: {what} must be a {shape[0]}x{shape[1]} matrix, "
                         f"got shape {m.shape}")
    return m


def read_pose(path: Path) -> Rigid3:
    """A 4x4 camera-to-world matrix in metres (7-Scenes pose.txt) -> world_from_cam."""
    return Rigid3.from_matrix(_read_matrix(path, "pose", (4, 4)), source=str(path))


def write_pose(path: Path, world_from_cam: Rigid3) -> None:
    np.savetxt(path, world_from_cam.matrix(), fmt="%.9f")


def read_intrinsics(path: Path) -> np.ndarray:
    """A 3x3 pinhole K matrix [[fx 0 cx] [0 fy cy] [0 0 1]] in pixels; InputError naming the
    file unless it is one (a skew or a last row other than 0 0 1 would be silently ignored).
    The principal point is checked against the images' size by the caller's `Camera` (one
    rule for every camera: `centre_problem`)."""
    k = _read_matrix(path, "intrinsics", (3, 3))
    problem = k_matrix_problem(k)
    if problem:
        raise InputError(f"{path}: intrinsics: {problem}")
    problem = camera_problem(1, 1, k[0, 0], k[1, 1], k[0, 2], k[1, 2])
    if problem:
        raise InputError(f"{path}: intrinsics: {problem}")
    return k


