"""Absolute trajectory error (translation RMSE, metres), as evo's `evo_ape` computes it: with no
alignment, or after the SE(3) Umeyama alignment of the estimate onto the reference (`-a`)."""

from __future__ import annotations

import numpy as np

from slamreloc.geometry import Rigid3, umeyama


def umeyama_se3(source: np.ndarray, target: np.ndarray) -> Rigid3:
    """target_from_source minimising sum |target - (R source + t)|^2 over (N, 3) point pairs
    (Umeyama 1991, no scale)."""
    return umeyama(source, target, with_scale=False).rigid


def ate_rmse(estimate: list[Rigid3], reference: list[Rigid3], align: bool = False) -> float:
    """RMSE of camera-centre distances (metres); `align`: SE(3)-align the estimate first,
    which takes 3 or more poses (fewer: NaN, never an unaligned distance reported as
    aligned)."""
    est = np.array([p.translation for p in estimate])
    ref = np.array([p.translation for p in reference])
    if len(est) == 0 or align and len(est) < 3:
        return float("nan")
    if align:
        est = umeyama_se3(est, ref).transform(est)
    return float(np.sqrt(np.mean(np.sum((est - ref) ** 2, axis=1))))
