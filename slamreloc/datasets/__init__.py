"""Dataset loaders; `load_dataset` detects the layout of a folder."""

from __future__ import annotations

from pathlib import Path

from slamreloc.datasets.base import Dataset
from slamreloc.datasets.colmap import is_colmap, load_colmap
from slamreloc.datasets.io import read_depth, read_image, read_intrinsics, read_pose, write_pose
from slamreloc.datasets.rosbag import is_rosbag, load_rosbag
from slamreloc.datasets.sevenscenes import is_sevenscenes, load_sevenscenes
from slamreloc.datasets.tum import is_tum, load_tum
from slamreloc.errors import InputError

__all__ = ["Dataset", "load_dataset", "read_depth", "read_image", "read_intrinsics",
           "read_pose", "write_pose"]


def load_dataset(root: str | Path) -> Dataset:
    """A ROS 1/2 bag (a file or a ROS 2 bag folder), 7-Scenes (and the synthetic scene, which
    uses its layout), TUM RGB-D or a COLMAP project (sparse model + images/)."""
    root = Path(root)
    if is_rosbag(root):
        return load_rosbag(root)
    if not root.is_dir():
        raise InputError(f"{root}: dataset folder not found")
    if is_tum(root):
        return load_tum(root)
    if is_colmap(root):
        return load_colmap(root)
    if is_sevenscenes(root):
        return load_sevenscenes(root)
    raise InputError(f"{root}: not a known dataset layout (expected 7-Scenes seq-XX/ folders, "
                     "a synthetic scene, TUM rgb.txt, or a COLMAP sparse/ model with images/)")
