"""The images the viewer shows: the dataset a map or report names, and RGB reads at a width."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from slamreloc.errors import InputError


def open_dataset(root: str | Path | None):
    """The dataset at `root`, or None when there is none (images are optional)."""
    if not root or not Path(root).is_dir():
        return None
    from slamreloc.datasets import load_dataset

    try:
        return load_dataset(root)
    except InputError:
        return None


def frames_by_name(dataset) -> dict:
    return {} if dataset is None else {f.name: f for f in dataset.frames("all")}


def read_rgb(path: Path | None, width: int | None = None) -> np.ndarray | None:
    """RGB uint8 image (resized to `width` when given), or None if it cannot be read (the
    core's reader: the same bounds and checks as every command's)."""
    from slamreloc.io.images import read_image

    if path is None:
        return None
    try:
        img = read_image(path)
    except InputError:
        return None
    return fit_width(img, width) if width else img


def fit_width(img: np.ndarray, width: int) -> np.ndarray:
    """The image shrunk to `width` pixels (aspect kept); unchanged when not wider."""
    import cv2

    if img.shape[1] <= width:
        return img
    h = max(1, round(img.shape[0] * width / img.shape[1]))
    return cv2.resize(img, (width, h), interpolation=cv2.INTER_AREA)
