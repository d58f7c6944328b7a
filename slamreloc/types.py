"""Typed records passed between pipeline stages (frames in pixels and metres)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from slamreloc.errors import InputError
from slamreloc.geometry import Rigid3


@dataclass(frozen=True)
class Camera:
    """Pinhole intrinsics in pixels, OpenCV convention (pixel centres at integer coordinates)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        problem = camera_problem(self.width, self.height, self.fx, self.fy, self.cx, self.cy)
        if problem:
            raise InputError(f"invalid camera: {problem}")

    @property
    def K(self) -> np.ndarray:  # noqa: N802 - the usual name
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    def params(self) -> list[float]:
        return [self.fx, self.fy, self.cx, self.cy]

    def scaled_to(self, width: int, height: int) -> Camera:
        sx, sy = width / self.width, height / self.height
        return Camera(width, height, self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy)

    def to_pycolmap(self):
        import pycolmap

        return pycolmap.Camera(model="PINHOLE", width=self.width, height=self.height,
                               params=self.params())

    def to_dict(self) -> dict:
        return {"width": self.width, "height": self.height, "fx": self.fx, "fy": self.fy,
                "cx": self.cx, "cy": self.cy}


MAX_INTRINSIC = 1e7  # pixels: beyond any real camera (a 65536-pixel image at 0.4 degrees)


def _show(v) -> str:
    if isinstance(v, (int, float, np.number)) and not isinstance(v, bool):
        return f"{float(v):g}" if abs(float(v)) < 1e16 or not float(v).is_integer() \
            else str(int(v))
    return repr(v)[:40]


def camera_problem(width, height, fx, fy, cx, cy) -> str | None:
    """What is wrong with pinhole intrinsics (None when nothing): sizes whole numbers in
    1..65536, fx and fy in [1, 1e7] pixels, cx and cy finite within +-1e7 pixels."""
    for name, v in (("width", width), ("height", height)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 0 < v <= 1 << 16:
            return f"{name} must be a whole number of pixels in 1..65536, got {_show(v)}"
    for name, v in (("fx", fx), ("fy", fy), ("cx", cx), ("cy", cy)):
        if isinstance(v, bool) or not isinstance(v, (int, float, np.number)) or \
                not abs(float(v)) <= MAX_INTRINSIC:  # False for NaN
            return (f"{name} must be a finite number within +-{MAX_INTRINSIC:g} pixels, got "
                    f"{_show(v)}")
    if fx < 1 or fy < 1:
        return (f"focal lengths must be positive (at least 1 pixel), got fx={_show(fx)}, "
                f"fy={_show(fy)}")
    return None


@dataclass
class Frame:
    """One image of a dataset. `world_from_cam` is None when the frame has no ground truth."""

    name: str  # unique inside its dataset, e.g. "seq-01/frame-000000"
    image_path: Path
    camera: Camera
    depth_path: Path | None = None
    world_from_cam: Rigid3 | None = None
    sequence: str = ""
    timestamp: float = 0.0


@dataclass
class Features:
    """Local features of one image: keypoints in pixels, L2-normalised float32 descriptors."""

    keypoints: np.ndarray  # (N, 2) float32, x right / y down
    descriptors: np.ndarray  # (N, D) float32
    scores: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))  # (N,)

    def __len__(self) -> int:
        return len(self.keypoints)

    def subset(self, idx: np.ndarray) -> Features:
        scores = self.scores[idx] if len(self.scores) else self.scores
        return Features(self.keypoints[idx], self.descriptors[idx], scores)
