"""Localizers: image -> camera pose against a map, by regression (the method) or by matching.

Both share feature extraction and PnP; they differ only in how 2D-3D correspondences are made:
`RegressorLocalizer` regresses a world point per descriptor; `MatchingLocalizer` (the classical
baseline) takes the world point of the nearest labelled training descriptor.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

from slamreloc.features import make_extractor
from slamreloc.features.matcher import LOCALIZER_DB_CHUNK, match_descriptors
from slamreloc.pnp import PnPConfig, PoseEstimate, estimate_pose
from slamreloc.precision import autocast, resolve_precision
from slamreloc.regressor.train import resolve_device
from slamreloc.scene_map import SceneMap
from slamreloc.types import Camera, Features

METHODS = ("regressor", "matching")
# Regressed world points scatter by a few centimetres, a few pixels once projected: the final
# refinement's Cauchy loss gets that scale (4 px) instead of pycolmap's 1 px, which is made for
# matched points and down-weights most regressed inliers. On RedKitchen (SfM reference) it
# takes 1cm1deg from 82.0 % to 84.5 % at no cost (BENCHMARKS.md, "Fine accuracy").
REGRESSOR_PNP = PnPConfig(refine_loss_px=4.0)


@dataclass
class Localization:
    estimate: PoseEstimate
    timings_ms: dict[str, float] = field(default_factory=dict)  # features, regressor, pnp, total
    n_keypoints: int = 0


class Localizer:
    method = ""

    def __init__(self, scene_map: SceneMap, pnp: PnPConfig = PnPConfig(), device: str = "cpu"):
        self.map = scene_map
        self.pnp = pnp
        self.device = resolve_device(device)
        self.extractor = make_extractor(scene_map.info.feature_name,
                                        **scene_map.info.feature_options)

    def correspondences(self, feats: Features) -> tuple[np.ndarray, np.ndarray]:
        """(points2d (N, 2), points3d (N, 3)) for PnP."""
        raise NotImplementedError

    def localize(self, image: np.ndarray, camera: Camera) -> Localization:
        """image: RGB uint8 taken by `camera` (any lens model: keypoints are undistorted).
        Returns the pose estimate (failure included) and stage timings."""
        t0 = time.perf_counter()
        feats = self.extractor.extract(image, camera)
        t1 = time.perf_counter()
        p2d, p3d = self.correspondences(feats)
        t2 = time.perf_counter()
        est = estimate_pose(p2d, p3d, camera.pinhole, self.pnp)
        t3 = time.perf_counter()
        ms = {"features": t1 - t0, "regressor": t2 - t1, "pnp": t3 - t2, "total": t3 - t0}
        return Localization(est, {k: 1000 * v for k, v in ms.items()}, len(feats))


class RegressorLocalizer(Localizer):
    method = "regressor"

    def __init__(self, scene_map: SceneMap, pnp: PnPConfig = REGRESSOR_PNP, device: str = "cpu",
                 precision: str = "auto", keep_fraction: float = 0.5):
        """precision: auto | fp32 | bf16 (auto: bf16 where the hardware runs it natively).
        keep_fraction: PnP uses this share of the predictions, the most confident ones, but
        at least 50 (a regressor without a confidence output always uses all)."""
        super().__init__(scene_map, pnp, device)
        self.model = scene_map.regressor.to(self.device).eval()
        self.precision = resolve_precision(precision, self.device.type)
        self.keep_fraction = keep_fraction

    def predict(self, descriptors: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """(N, D) descriptors -> world points (N, 3), metres, and confidences (N,) or None."""
        with torch.inference_mode(), autocast(self.device.type, self.precision):
            x = torch.as_tensor(descriptors, dtype=torch.float32, device=self.device)
            # bf16: pad the batch to a multiple of 256 rows; oneDNN compiles a kernel per batch
            # shape, ~20 ms per query when every image has its own keypoint count. fp32 has
            # no such cost and padding only adds rows (BENCHMARKS.md, precision)
            n = len(x)
            if self.precision == "bf16":
                x = torch.cat([x, x.new_zeros((-n) % 256, x.shape[1])])
            points, confidence = self.model.predict(x)
            return (points[:n].float().cpu().numpy(),
                    None if confidence is None else confidence[:n].float().cpu().numpy())

    def correspondences(self, feats):
        keypoints, points, _ = self.confident_correspondences(feats)
        return keypoints, points

    def confident_correspondences(self, feats):
        """(keypoints, world points, confidences or None) of the predictions PnP uses."""
        points, confidence = self.predict(feats.descriptors)
        if confidence is None or self.keep_fraction >= 1 or len(points) == 0:
            return feats.keypoints, points, confidence
        n_keep = max(round(self.keep_fraction * len(points)), min(len(points), 50))
        keep = np.argsort(-confidence, kind="stable")[:n_keep]
        return feats.keypoints[keep], points[keep], confidence[keep]


class MatchingLocalizer(Localizer):
    """Nearest labelled training descriptor; ratio test unless both neighbours are one point."""

    method = "matching"

    def __init__(self, scene_map: SceneMap, pnp: PnPConfig = PnPConfig(), device: str = "cpu",
                 ratio: float = 0.9, same_point_m: float = 0.05):
        super().__init__(scene_map, pnp, device)
        db = scene_map.database
        self.db_desc = torch.as_tensor(db.descriptors.astype(np.float32))
        self.db_points = db.points
        self.ratio, self.same_point_m = ratio, same_point_m

    def correspondences(self, feats):
        m = match_descriptors(feats.descriptors, self.db_desc, self.ratio, mutual=False,
                              db_points=self.db_points, same_point_m=self.same_point_m,
                              db_chunk=LOCALIZER_DB_CHUNK)
        return feats.keypoints[m[:, 0]], self.db_points[m[:, 1]]


def make_localizer(scene_map: SceneMap, method: str = "regressor", **kwargs) -> Localizer:
    if method == "regressor":
        return RegressorLocalizer(scene_map, **kwargs)
    if method == "matching":
        return MatchingLocalizer(scene_map, **kwargs)
    raise ValueError(f"unknown method '{method}' (known: {', '.join(METHODS)})")
