"""Training rows from simulated views: each mapping image is warped by random affine maps (the
local effect of a viewpoint change: tilt, in-plane rotation, scale, as ASIFT simulates them),
features are extracted from the warped image, and each warped keypoint that lands back within
`match_px` of a labelled keypoint of the original image takes that keypoint's world point.

The rows only train the regressor (descriptors of the same 3D points seen obliquely, as a query
from an unseen viewpoint sees them); the map's database keeps the real keypoints only.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from slamreloc.datasets import read_frame_image
from slamreloc.features import Extractor
from slamreloc.runtime.progress import track
from slamreloc.types import Features, Frame


@dataclass(frozen=True)
class AugmentConfig:
    """views: warped copies per mapping image (0: none); max_tilt: the largest ASIFT tilt t
    (a plane seen at arccos(1/t) from its normal: 1.5 is 48 deg); max_rotation_deg: in-plane
    rotation; scale: (min, max) zoom; match_px: how near (pinhole pixels of the original
    image) a warped keypoint must land to an original labelled one to take its point."""

    views: int = 0
    max_tilt: float = 1.5
    max_rotation_deg: float = 15.0
    scale: tuple[float, float] = (0.8, 1.25)
    match_px: float = 1.0
    seed: int = 0

    def to_dict(self) -> dict:
        return asdict(self)


def random_affine(rng: np.random.Generator, width: int, height: int,
                  config: AugmentConfig) -> np.ndarray:
    """(2, 3) affine map of original pixels to warped pixels, about the image centre: a
    squeeze by 1/t along direction phi, then an in-plane rotation psi and a zoom."""
    def rotation(rad: float) -> np.ndarray:
        c, s = np.cos(rad), np.sin(rad)
        return np.array([[c, -s], [s, c]])

    tilt = rng.uniform(1.0, config.max_tilt)
    phi = rng.uniform(0.0, np.pi)
    psi = np.deg2rad(rng.uniform(-config.max_rotation_deg, config.max_rotation_deg))
    scale = np.exp(rng.uniform(*np.log(config.scale)))
    linear = scale * rotation(psi) @ rotation(phi) @ np.diag([1.0 / tilt, 1.0]) @ rotation(phi).T
    centre = np.array([width / 2.0, height / 2.0])
    return np.hstack([linear, (centre - linear @ centre)[:, None]])


def _empty(dim: int) -> tuple[np.ndarray, np.ndarray]:
    return np.zeros((0, dim), np.float32), np.zeros((0, 3), np.float32)


def _frame_rows(frame: Frame, feats: Features, points: np.ndarray, extractor: Extractor,
                affines: list[np.ndarray], match_px: float) -> tuple[np.ndarray, np.ndarray]:
    """The (M, D) descriptors of one frame's warped views (one per affine map) and the (M, 3)
    world points they take; the image is read, and its labelled keypoints indexed, once."""
    labelled = np.flatnonzero(~np.isnan(points[:, 0]))
    if not len(labelled) or not affines:
        return _empty(extractor.dim)
    tree = cKDTree(feats.keypoints[labelled])
    image = read_frame_image(frame)
    height, width = image.shape[:2]
    rows = []
    for affine in affines:
        view = extractor(cv2.warpAffine(image, affine, (width, height), flags=cv2.INTER_LINEAR,
                                        borderMode=cv2.BORDER_CONSTANT))
        if not len(view):
            continue
        back = cv2.invertAffineTransform(affine)
        uv = view.keypoints.astype(np.float64) @ back[:, :2].T + back[:, 2]
        if frame.camera.distorted:
            uv = frame.camera.undistort(uv)
        dist, nearest = tree.query(uv, distance_upper_bound=match_px)
        hit = np.isfinite(dist)
        rows.append((view.descriptors[hit], points[labelled[nearest[hit]]]))
    if not rows:
        return _empty(extractor.dim)
    return np.concatenate([d for d, _ in rows]), np.concatenate([p for _, p in rows])


def augmented_rows(frames: list[Frame], feats: list[Features], points: list[np.ndarray],
                   extractor: Extractor, config: AugmentConfig,
                   progress: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """(M, D) float32 descriptors and (M, 3) world points (metres, the map's frame) of
    `config.views` warped views of every frame; `points[i]`: frame i's labels (NaN where
    unlabelled), aligned with `feats[i].keypoints`."""
    rng = np.random.default_rng(config.seed)
    affines = [[random_affine(rng, f.camera.width, f.camera.height, config)
                for _ in range(config.views)] for f in frames]
    with ThreadPoolExecutor(2) as pool:
        results = pool.map(lambda i: _frame_rows(frames[i], feats[i], points[i], extractor,
                                                 affines[i], config.match_px),
                           range(len(frames)))
        rows = list(track(results, "simulated views", total=len(frames), enabled=progress))
    if not rows:
        return _empty(extractor.dim)
    return (np.concatenate([d for d, _ in rows]).astype(np.float32),
            np.concatenate([p for _, p in rows]).astype(np.float32))
