"""SIFT keypoints are where the image content is: no constant offset at either pyramid setting.

A constant offset of every keypoint acts like a wrong principal point: the labels triangulated
from the map's images and the PnP on a query both inherit it. Mirroring an image exposes it:
a keypoint at x + b is found again at (w - 1 - x) + b in the mirror, so mapping the mirror's
keypoints back gives x - b, and the two differ by 2b.
"""

from __future__ import annotations

import numpy as np
import pytest

from slamreloc.datasets import load_dataset, read_image
from slamreloc.features.sift import Sift


def _grey(scene_dir) -> np.ndarray:
    frame = load_dataset(scene_dir).frames("test")[0]
    rgb = read_image(frame.image_path)
    return np.ascontiguousarray(rgb.mean(axis=2).round().astype(np.uint8))


def _offsets(sift: Sift, grey: np.ndarray) -> np.ndarray:
    """(M, 2) half the differences between keypoints and their mirrored twins (px)."""
    h, w = grey.shape
    a = sift.extract_grey(grey).keypoints
    b = sift.extract_grey(np.ascontiguousarray(grey[::-1, ::-1])).keypoints
    back = np.stack([w - 1 - b[:, 0], h - 1 - b[:, 1]], axis=1)
    dist = np.linalg.norm(a[:, None] - back[None], axis=2)
    j = dist.argmin(axis=1)
    twin = dist[np.arange(len(a)), j] < 1.0
    return (a[twin] - back[j[twin]]) / 2


@pytest.mark.parametrize("upsample", [False, True])
def test_keypoints_have_no_constant_offset(scene_dir, upsample):
    off = _offsets(Sift(upsample=upsample), _grey(scene_dir))
    assert len(off) >= 50
    # OpenCV's default doubling alone would put the mean at +0.25 px, an uncorrected halving at
    # -0.5 px (full-resolution pixels); what is left is subpixel interpolation noise
    assert np.all(np.abs(off.mean(axis=0)) < 0.03), off.mean(axis=0)
    assert np.all(np.abs(np.median(off, axis=0)) < 0.03), np.median(off, axis=0)


def test_keypoints_follow_an_even_shift(scene_dir):
    """Shifting the image by an even number of pixels (whole pixels after halving) shifts
    every keypoint by exactly that much."""
    grey = _grey(scene_dir)
    shift = 6
    moved = np.ascontiguousarray(np.pad(grey, ((shift, 0), (shift, 0)), mode="edge")[
        :grey.shape[0], :grey.shape[1]])
    sift = Sift()
    a, b = sift.extract_grey(grey).keypoints, sift.extract_grey(moved).keypoints
    dist = np.linalg.norm(a[:, None] + shift - b[None], axis=2)
    twin = dist.min(axis=1) < 0.05
    assert twin.sum() >= 0.5 * len(a)
