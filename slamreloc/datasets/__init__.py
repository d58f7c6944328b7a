"""Dataset loaders; `load_dataset` detects the layout of a folder."""

from __future__ import annotations

from pathlib import Path

from slamreloc.datasets.base import Dataset
from slamreloc.datasets.colmap import is_colmap, load_colmap
from slamreloc.datasets.io import (read_depth, read_frame_depth, read_frame_image, read_image,
                                   read_intrinsics, read_pose, write_pose)
from slamreloc.datasets.poses import ReferencePoses, apply_poses, read_poses
from slamreloc.datasets.rosbag import BagTopics, default_topics, is_rosbag, load_rosbag
from slamreloc.datasets.sevenscenes import is_sevenscenes, load_sevenscenes
from slamreloc.datasets.tum import is_tum, load_tum
from slamreloc.errors import InputError
from slamreloc.io.fileio import check_folder

__all__ = ["Dataset", "ReferencePoses", "apply_poses", "load_dataset", "read_depth",
           "read_frame_depth", "read_frame_image", "read_image", "read_intrinsics", "read_pose",
           "read_poses", "read_reference",
           "write_pose"]


def load_dataset(root: str | Path, poses: str | Path | None = None) -> Dataset:
    """A ROS 1/2 bag (a file or a ROS 2 bag folder), 7-Scenes (and the synthetic scene, which
    uses its layout), TUM RGB-D or a COLMAP project (sparse model + images/).

    `poses`: a pose file, COLMAP model or dataset (`read_reference`) whose poses replace the
    dataset's own (`apply_poses`); it is read first, so a bad one fails before the dataset."""
    reference = read_reference(poses) if poses is not None else None
    dataset = _load_layout(Path(root))
    return dataset if reference is None else apply_poses(dataset, reference)


def read_reference(path: str | Path) -> ReferencePoses:
    """Poses to use or score against, by frame name: a pose file or COLMAP model
    (`datasets.poses.read_poses`), or a dataset of another layout (7-Scenes, TUM, a ROS bag):
    its own poses, e.g. `evaluate --reference DATASET` to score a map trained with `--poses`
    against the dataset's ground truth too."""
    path = Path(path)
    if is_rosbag(path) or (path.is_dir() and not is_colmap(path)
                           and (is_tum(path) or is_sevenscenes(path))):
        dataset = _load_layout(path)
        posed = {f.name: f.world_from_cam for f in dataset.frames("all")
                 if f.world_from_cam is not None}
        if not posed:
            raise InputError(f"{path}: the dataset has no poses to use as a reference")
        return ReferencePoses(path.resolve(), "dataset", posed)
    return read_poses(path)


def _load_layout(root: Path) -> Dataset:
    if is_rosbag(root):
        return load_rosbag(root)
    if default_topics() != BagTopics():  # the CLI's `--topic`: for a bag only
        raise InputError(f"{root}: `topic` chooses a ROS bag's topics, and this dataset is not "
                         "a bag (leave `topic` out)")
    if not root.is_dir():
        check_folder(root, "dataset")
    if is_tum(root):
        return load_tum(root)
    if is_colmap(root):
        return load_colmap(root)
    if is_sevenscenes(root):
        return load_sevenscenes(root)
    raise InputError(f"{root}: not a known dataset layout (expected 7-Scenes seq-XX/ folders, "
                     "a synthetic scene, TUM rgb.txt, or a COLMAP sparse/ model with images/)")
