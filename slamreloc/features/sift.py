"""OpenCV SIFT with RootSIFT descriptors (128-d, no weights needed)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from slamreloc.features.base import Extractor, ExtractorConfig
from slamreloc.types import Features


@dataclass(frozen=True)
class SiftConfig(ExtractorConfig):
    contrast_threshold: float = 0.01  # lower than OpenCV's 0.04: more keypoints on low texture
    edge_threshold: float = 10.0
    n_octave_layers: int = 3
    root: bool = True  # RootSIFT: L1-normalise, square root (Hellinger kernel)
    # OpenCV always doubles the image for its first octave; with upsample=False (the default)
    # the image is halved first, so the pyramid starts at full resolution: faster, fewer but
    # more repeatable keypoints (docs/history.md). Keypoints are returned in
    # full-resolution pixels either way.
    upsample: bool = False

    def __post_init__(self) -> None:
        super().__post_init__()
        self.check_range("contrast_threshold", 1e-6, 1.0)
        self.check_range("edge_threshold", 1e-3, 1e3)
        self.check_range("n_octave_layers", 1, 16)


class Sift(Extractor):
    name = "sift"
    dim = 128
    Config = SiftConfig
    bytes_per_pixel = 60  # OpenCV's float pyramid: 58 B per working pixel at 12 and 48 MP

    def working_pixels(self, width: int, height: int) -> int:
        return width * height * (4 if self.config.upsample else 1)

    def __init__(self, config: SiftConfig | None = None, **overrides) -> None:
        super().__init__(config, **overrides)
        c = self.config
        # OpenCV's default doubling maps pixel x to 2x + 0.5, which shifts its keypoints by
        # +0.25 px; the precise doubling maps x to 2x. Halved images (upsample=False) keep the
        # default: there the +0.25 half-resolution px cancel INTER_AREA's -0.5 px (a halved
        # pixel i covers full-resolution pixels 2i and 2i + 1), so both settings return
        # unbiased full-resolution keypoints (tests/test_sift.py mirrors an image to check)
        self._sift = cv2.SIFT_create(nfeatures=c.max_keypoints, nOctaveLayers=c.n_octave_layers,
                                     contrastThreshold=c.contrast_threshold,
                                     edgeThreshold=c.edge_threshold,
                                     enable_precise_upscale=c.upsample)

    def _no_features(self) -> Features:
        return Features(np.zeros((0, 2), np.float32), np.zeros((0, self.dim), np.float32),
                        np.zeros(0, np.float32))

    def extract_grey(self, grey: np.ndarray) -> Features:
        scale = 1.0
        if not self.config.upsample:
            if min(grey.shape[:2]) < 2:  # a pixel wide (`--limit min_image_side=1`): no halving
                return self._no_features()
            grey = cv2.resize(grey, (grey.shape[1] // 2, grey.shape[0] // 2),
                              interpolation=cv2.INTER_AREA)
            scale = 2.0
        kps, desc = self._sift.detectAndCompute(grey, None)
        if desc is None or len(kps) == 0:
            return self._no_features()
        # OpenCV can return slightly more than nfeatures (ties); keep the strongest.
        order = np.argsort([-k.response for k in kps])[: self.config.max_keypoints]
        xy = np.array([kps[i].pt for i in order], np.float32) * scale
        scores = np.array([kps[i].response for i in order], np.float32)
        desc = desc[order].astype(np.float32)
        if self.config.root:
            desc /= np.maximum(desc.sum(axis=1, keepdims=True), 1e-8)
            desc = np.sqrt(desc)
        else:
            desc /= np.maximum(np.linalg.norm(desc, axis=1, keepdims=True), 1e-8)
        return Features(xy, desc, scores)
