"""The base class every local-feature extractor shares (a default config, one entry point, the
memory bound on the images it works on)."""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import ClassVar

import numpy as np

from slamreloc.errors import InputError, OutOfMemory, is_out_of_memory
from slamreloc.io.limits import bytes_text, limits, over_limit
from slamreloc.types import Camera, Features


@dataclass(frozen=True)
class ExtractorConfig:
    """Options common to all extractors; subclasses add their own fields."""

    max_keypoints: int = 2048  # 0: no limit (SuperPoint)

    def __post_init__(self) -> None:
        self.check_range("max_keypoints", 0, 1 << 20)

    def check_range(self, name: str, low: float, high: float) -> None:
        """InputError unless option `name` is a number in [low, high]."""
        v = getattr(self, name)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not low <= v <= high:
            raise InputError(f"feature option {name} must be in {low}..{high}, got {v!r}")


class Extractor:
    """Detects keypoints and describes them. Subclasses set `name`, `dim`, `Config`."""

    name: ClassVar[str] = ""
    dim: ClassVar[int] = 0
    Config: ClassVar[type[ExtractorConfig]] = ExtractorConfig
    # peak memory per working pixel (bytes), measured (BENCHMARKS.md, "Input bounds")
    bytes_per_pixel: ClassVar[int] = 64

    def __init__(self, config: ExtractorConfig | None = None, **overrides) -> None:
        config = config or self.Config()
        self.config = replace(config, **overrides) if overrides else config

    def __call__(self, image: np.ndarray) -> Features:
        """image: (H, W, 3) uint8 RGB, (H, W, 4) RGBA or (H, W) grey. Returns at most
        max_keypoints."""
        problem = image_array_problem(image)
        if problem:
            raise InputError(f"image: {problem}")
        self.check_size(image.shape[1], image.shape[0], "image")
        try:
            if image.ndim == 3:
                image = _to_grey(image)
            return self.extract_grey(image)
        except Exception as err:  # only running out of memory is turned
            if not is_out_of_memory(err):  # into a one-line error; anything else is a bug
                raise
            raise OutOfMemory(f"image: out of memory extracting {self.name} features of a "
                              f"{image.shape[1]}x{image.shape[0]} image; give a smaller image "
                              "or run with more memory (lower `limit` max_feature_bytes to "
                              "refuse such images up front)") from None

    def extract(self, image: np.ndarray, camera: Camera | None = None) -> Features:
        """Features of `image` with keypoints in `camera`'s pinhole pixels: undistorted where
        the camera has a lens-distortion model (`slamreloc.camera_models`)."""
        feats = self(image)
        if camera is None or not camera.distorted:
            return feats
        return Features(camera.undistort(feats.keypoints).astype(np.float32),
                        feats.descriptors, feats.scores)

    def working_pixels(self, width: int, height: int) -> int:
        """Pixels of the image the extractor works on for a width x height input."""
        return width * height

    def check_size(self, width: int, height: int, source) -> None:
        """InputError (naming `source`) unless features of a width x height image fit in
        `max_feature_bytes` of memory; checked before any pixel is touched."""
        need = self.working_pixels(width, height) * self.bytes_per_pixel
        limit = limits().max_feature_bytes
        if need > limit:
            raise InputError(f"{source}: {self.name} features of a {width}x{height} image need "
                             + over_limit("max_feature_bytes", f"~{bytes_text(need)} of memory"))

    def check_frames(self, frames) -> None:
        """`check_size` for each image size among `frames` (dataset frames), naming the first
        frame of that size; before a long run starts."""
        seen = set()
        for frame in frames:
            size = (frame.camera.width, frame.camera.height)
            if size not in seen:
                seen.add(size)
                self.check_size(*size, frame.image_path)

    def extract_grey(self, grey: np.ndarray) -> Features:
        raise NotImplementedError

    def config_dict(self) -> dict:
        return {f.name: getattr(self.config, f.name) for f in fields(self.config)}


def image_array_problem(image) -> str | None:
    """Why `image` is not an image array the extractors take (uint8 (H, W) grey, (H, W, 3)
    RGB or (H, W, 4) RGBA, as the readers decode them), or None."""
    if not isinstance(image, np.ndarray):
        return f"must be a numpy array (uint8, H x W x 3 RGB or H x W grey), got " \
               f"{type(image).__name__}"
    if image.dtype != np.uint8:
        return f"must be uint8 (0-255), got {image.dtype}: convert it (a float image in 0-1: " \
               "times 255)"
    if image.ndim not in (2, 3) or image.ndim == 3 and image.shape[2] not in (3, 4):
        return f"must be H x W x 3 RGB, H x W x 4 RGBA or H x W grey, got shape {image.shape}"
    return None


def _to_grey(rgb: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
