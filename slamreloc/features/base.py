"""The base class every local-feature extractor shares (a default config, one entry point)."""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import ClassVar

import numpy as np

from slamreloc.types import Features


@dataclass(frozen=True)
class ExtractorConfig:
    """Options common to all extractors; subclasses add their own fields."""

    max_keypoints: int = 2048


class Extractor:
    """Detects keypoints and describes them. Subclasses set `name`, `dim`, `Config`."""

    name: ClassVar[str] = ""
    dim: ClassVar[int] = 0
    Config: ClassVar[type[ExtractorConfig]] = ExtractorConfig

    def __init__(self, config: ExtractorConfig | None = None, **overrides) -> None:
        config = config or self.Config()
        self.config = replace(config, **overrides) if overrides else config

    def __call__(self, image: np.ndarray) -> Features:
        """image: (H, W, 3) uint8 RGB or (H, W) uint8 grey. Returns at most max_keypoints."""
        if image.ndim == 3:
            image = _to_grey(image)
        return self.extract_grey(image)

    def extract_grey(self, grey: np.ndarray) -> Features:
        raise NotImplementedError

    def config_dict(self) -> dict:
        return {f.name: getattr(self.config, f.name) for f in fields(self.config)}


def _to_grey(rgb: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
