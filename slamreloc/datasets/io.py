"""Reading images, depth maps, poses and intrinsics, with one-line errors naming the file."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from slamreloc.errors import InputError
from slamreloc.geometry import Rigid3

INVALID_DEPTH = (0, 65535)  # raw uint16 values that mean "no measurement"


def _imread(path: Path, flags: int, what: str) -> np.ndarray:
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: {what} file not found")
    img = cv2.imread(str(path), flags)
    if img is None or img.size == 0:
        raise InputError(f"{path}: not a readable {what} (empty or corrupt)")
    return img


def read_image(path: Path) -> np.ndarray:
    """RGB uint8 (H, W, 3)."""
    return cv2.cvtColor(_imread(path, cv2.IMREAD_COLOR, "image"), cv2.COLOR_BGR2RGB)


def read_depth(path: Path, units_per_metre: float = 1000.0) -> np.ndarray:
    """float32 depth in metres (H, W); invalid pixels (raw 0 or 65535) are 0."""
    raw = _imread(path, cv2.IMREAD_ANYDEPTH, "depth")
    if raw.ndim != 2:
        raise InputError(f"{path}: depth must be a single-channel image, got shape {raw.shape}")
    depth = raw.astype(np.float32) / units_per_metre
    depth[np.isin(raw, INVALID_DEPTH)] = 0.0
    return depth


def _read_matrix(path: Path, what: str, shape: tuple[int, int]) -> np.ndarray:
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: {what} file not found")
    try:
        m = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except ValueError as err:
        raise InputError(f"{path}: {what} is not a numeric matrix ({err})") from None
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
    """A 3x3 K matrix; raises unless fx, fy > 0 and cx, cy >= 0."""
    k = _read_matrix(path, "intrinsics", (3, 3))
    if not np.all(np.isfinite(k)) or k[0, 0] <= 0 or k[1, 1] <= 0 or k[0, 2] < 0 or k[1, 2] < 0:
        raise InputError(f"{path}: intrinsics must have positive fx, fy and non-negative cx, cy")
    return k


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image, reading only what is needed."""
    img = read_image(path)
    return img.shape[1], img.shape[0]
