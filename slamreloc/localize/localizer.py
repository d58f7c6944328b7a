"""Localizers: image -> camera pose against a map, by regression (the method) or by matching.

Both share feature extraction and PnP; they differ only in how 2D-3D correspondences are made:
`RegressorLocalizer` regresses a world point per descriptor; `MatchingLocalizer` (the classical
baseline) takes the world point of the nearest labelled training descriptor.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from slamreloc.errors import InputError
from slamreloc.features import make_extractor
from slamreloc.features.matcher import LOCALIZER_DB_CHUNK, match_descriptors
from slamreloc.localize.guided import GuidedConfig, GuidedMatcher
from slamreloc.localize.pnp import PnPConfig, PoseEstimate, estimate_pose, refine_from
from slamreloc.runtime.precision import autocast, resolve_precision
from slamreloc.registry import METHODS
from slamreloc.regressor.train import resolve_device
from slamreloc.map.scene_map import SceneMap
from slamreloc.types import Camera, Features

# Regressed world points scatter by a few centimetres, a few pixels once projected: the final
# refinement's Cauchy loss gets that scale (4 px) instead of pycolmap's 1 px, which is made for
# matched points and down-weights most regressed inliers (measured: docs/history.md, "Fine
# accuracy").
REGRESSOR_PNP = PnPConfig(refine_loss_px=4.0)


@dataclass
class Localization:
    estimate: PoseEstimate
    # features, regressor, pnp (with the guided refinement), total
    timings_ms: dict[str, float] = field(default_factory=dict)
    n_keypoints: int = 0
    # the regressor's median confidence (class probability) over the RANSAC inliers
    inlier_confidence: float | None = None
    # database points the final refinement ran on (guided matching; 0: it did not run or
    # found too few, and the pose is RANSAC's on the regressed points)
    n_guided: int = 0


class Localizer:
    method = ""
    guided: GuidedMatcher | None = None  # the regressor's last refinement (RegressorLocalizer)

    def __init__(self, scene_map: SceneMap, pnp: PnPConfig = PnPConfig(), device: str = "cpu"):
        self.map = scene_map
        self.pnp = pnp
        self.device = resolve_device(device)
        self.extractor = make_extractor(scene_map.info.feature_name,
                                        **scene_map.info.feature_options)

    def correspondences(self, feats: Features) -> tuple[np.ndarray, np.ndarray]:
        """(points2d (N, 2), points3d (N, 3)) for PnP-RANSAC."""
        raise NotImplementedError

    def localize(self, image: np.ndarray, camera: Camera) -> Localization:
        """image: RGB uint8 taken by `camera` (any lens model: keypoints are undistorted).
        Returns the pose estimate (failure included) and stage timings."""
        if not isinstance(camera, Camera):
            raise InputError(f"camera: must be a slamreloc Camera (the image's intrinsics), got "
                             f"{type(camera).__name__}")
        t0 = time.perf_counter()
        feats = self.extractor.extract(image, camera)
        t1 = time.perf_counter()
        result = self.localize_features(feats, camera)
        result.timings_ms = {"features": 1000 * (t1 - t0), **result.timings_ms,
                             "total": 1000 * (time.perf_counter() - t0)}
        return result

    def localize_features(self, feats: Features, camera: Camera) -> Localization:
        """The pose from features already extracted with `self.extractor` (what `localize`
        does after extraction); timings of the correspondence ("regressor") and PnP stages."""
        t1 = time.perf_counter()
        p2d, p3d = self.correspondences(feats)
        t2 = time.perf_counter()
        est = estimate_pose(p2d, p3d, camera.pinhole, self.pnp)
        t3 = time.perf_counter()
        return Localization(est, {"regressor": 1000 * (t2 - t1), "pnp": 1000 * (t3 - t2)},
                            len(feats))


class RegressorLocalizer(Localizer):
    method = "regressor"

    def __init__(self, scene_map: SceneMap, pnp: PnPConfig = REGRESSOR_PNP, device: str = "cpu",
                 precision: str = "auto", keep_fraction: float = 0.5,
                 refine_on_all: bool = False, guided: GuidedConfig | None = GuidedConfig()):
        """precision: auto | fp32 | bf16 (auto: bf16 on AMX CPUs and CUDA, where it is the
        faster; `slamreloc.runtime.precision`).
        keep_fraction: PnP-RANSAC uses this share of the predictions, the most confident ones,
        but at least 50 (a regressor without a confidence output always uses all).
        refine_on_all: the final refinement then runs again from RANSAC's pose on every
        prediction within the RANSAC threshold of it, confident or not; off by default, as
        it gained too little for its time (docs/history.md, "Fine accuracy").
        guided: from the regressor's pose, match the query keypoints to the map's database
        near it and near their regressed points (`localize.guided`) and run the final
        refinement on the database's world points, which are as precise as the labels; where
        the regressed points alone find no pose, RANSAC runs on the rows near them. It runs
        on maps whose labels agree with their images (`GuidedConfig.max_label_error_px`).
        None, a map whose labels do not, or one shipped without its database (with a
        warning): the pose stays RANSAC's on the regressed points, and the database is never
        read. What it gains and costs:
        BENCHMARKS.md, "Localization on RedKitchen, against both references"."""
        super().__init__(scene_map, pnp, device)
        self.model = scene_map.regressor.to(self.device).eval()
        self.precision = resolve_precision(precision, self.device.type, use="query")
        self.keep_fraction = keep_fraction
        self.refine_on_all = refine_on_all
        self.guided = None
        if guided is not None and guided.applies_to(scene_map.info.label_reproj_error_px):
            if scene_map.has_database:
                self.guided = GuidedMatcher(scene_map.database, guided)
            else:
                warnings.warn(f"{scene_map.root}: no training database, so no guided "
                              "refinement: poses come from the regressed points alone",
                              stacklevel=2)

    def predict(self, descriptors: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """(N, D) descriptors -> world points (N, 3), metres, and confidences (N,) or None."""
        with torch.inference_mode(), autocast(self.device.type, self.precision):
            x = torch.as_tensor(descriptors, dtype=torch.float32, device=self.device)
            # bf16: pad the batch to a multiple of 256 rows; oneDNN compiles a kernel per batch
            # shape, a large cost per query when every image has its own keypoint count. fp32
            # has no such cost and padding only adds rows (docs/history.md, "Precision by hardware")
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
        """(keypoints, world points, confidences or None) of the predictions RANSAC uses."""
        points, confidence = self.predict(feats.descriptors)
        keep = self._confident(confidence)
        return (feats.keypoints[keep], points[keep],
                None if confidence is None else confidence[keep])

    def _confident(self, confidence: np.ndarray | None) -> np.ndarray | slice:
        """Indices of the `keep_fraction` most confident predictions (all: a slice)."""
        if confidence is None or self.keep_fraction >= 1 or len(confidence) == 0:
            return slice(None)
        n = len(confidence)
        n_keep = max(round(self.keep_fraction * n), min(n, 50))
        return np.argsort(-confidence, kind="stable")[:n_keep]

    def localize_features(self, feats, camera):
        t1 = time.perf_counter()
        points, confidence = self.predict(feats.descriptors)
        keep = self._confident(confidence)
        t2 = time.perf_counter()
        est = estimate_pose(feats.keypoints[keep], points[keep], camera.pinhole, self.pnp)
        used = np.arange(len(feats))[keep]  # the keypoint behind each of RANSAC's points
        if not est.success and self.guided is not None:
            # too few regressed points agree on a pose: the rows near them, chosen by
            # descriptor (no pose needed), give RANSAC points as precise as the labels
            used, rows = self.guided.near_points(feats, points)
            est = estimate_pose(feats.keypoints[used], self.guided.db.points[rows]
                                .astype(np.float64), camera.pinhole, self.pnp)
        if est.success and self.refine_on_all:
            # Regressed points scatter by a few pixels; RANSAC needs the confident share to
            # find the pose, but near it every prediction that agrees adds its constraint
            refined = refine_from(est.cam_from_world, feats.keypoints, points, camera.pinhole,
                                  self.pnp)
            if refined is not None:
                est = replace(est, cam_from_world=refined)
        n_guided = 0
        if est.success and self.guided is not None:
            p2d, p3d = self.guided.correspondences(est.cam_from_world, feats, camera, points)
            refined = refine_from(est.cam_from_world, p2d, p3d, camera.pinhole, self.pnp,
                                  max_error_px=self.guided.config.radius_px)
            if refined is not None:
                est, n_guided = replace(est, cam_from_world=refined), len(p2d)
        t3 = time.perf_counter()
        inlier_confidence = None
        if est.success and confidence is not None:
            inlier_confidence = float(np.median(confidence[used][est.inlier_mask]))
        return Localization(est, {"regressor": 1000 * (t2 - t1), "pnp": 1000 * (t3 - t2)},
                            len(feats), inlier_confidence, n_guided)


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
