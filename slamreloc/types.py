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
        if min(self.width, self.height) <= 0 or min(self.fx, self.fy) <= 0:
            raise InputError(f"intrinsics must be positive, got {self}")

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
