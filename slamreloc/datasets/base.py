"""The Dataset record shared by all layouts: frames grouped in sequences and splits."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from slamreloc.errors import InputError
from slamreloc.geometry import Rigid3
from slamreloc.types import Frame

SEVENSCENES_DEPTH_K = (585.0, 585.0, 320.0, 240.0)  # 7-Scenes depth camera at 640x480
# Kinect v1 rig: depth camera -> RGB camera (0.6 deg, 2.6 cm along x), the calibration the
# 7-Scenes "calibrated depth" of DSAC* and ACE is made with (LIRIS activities dataset)
SEVENSCENES_RGB_FROM_DEPTH = (
    (0.99996518012567637, 0.0026765126468950343, -0.0079041012313000904, -0.025558943178152542),
    (-0.0027409311281316700, 0.99996302803027592, -0.0081504520778013286, 0.00010109636268061706),
    (0.0078819942130445332, 0.0081718328771890631, 0.99993554558014031, 0.0020318321729487039),
    (0.0, 0.0, 0.0, 1.0))


@dataclass
class Dataset:
    """Posed (or unposed) RGB-D frames. `depth_registered`: depth pixels align with RGB pixels."""

    root: Path
    kind: str  # "7scenes" | "tum" | "synthetic"
    sequences: dict[str, list[Frame]]
    splits: dict[str, list[str]] = field(default_factory=dict)  # "train"/"test" -> sequences
    depth_registered: bool = False
    depth_units_per_metre: float = 1000.0
    roles: dict[str, str] = field(default_factory=dict)  # synthetic: sequence -> role
    split_files: dict[str, Path] = field(default_factory=dict)  # split -> file that names it
    metric: bool = True  # poses in metres (False: an SfM model without a scale)
    # where the frames' world_from_cam come from: "dataset" (its own pose files), or the
    # resolved path of a pose file given with --poses (`datasets.poses.apply_poses`)
    poses_source: str = "dataset"
    poses_matched: int | None = None  # frames that took a pose from that file (None: own)

    @property
    def poses_origin(self) -> Path:
        """Where the frames' poses were read: the pose file, else the dataset folder (for
        messages about a missing pose)."""
        return self.root if self.poses_source == "dataset" else Path(self.poses_source)

    @property
    def depth_intrinsics(self) -> tuple[float, float, float, float] | None:
        """The depth camera's (fx, fy, cx, cy) at 640x480 where depth is not registered to the
        images (7-Scenes), else None: the RGB camera's own intrinsics apply."""
        return None if self.depth_registered else SEVENSCENES_DEPTH_K

    @property
    def rgb_from_depth(self) -> Rigid3:
        """The depth camera's pose in the RGB camera's frame (identity where registered)."""
        if self.depth_registered:
            return Rigid3.identity()
        return Rigid3.from_matrix(np.array(SEVENSCENES_RGB_FROM_DEPTH), source="7-Scenes rig")

    def frames(self, split: str = "all") -> list[Frame]:
        """Frames of a split: "train", "test", "all", a role, or comma-separated sequences."""
        return [f for seq in self.resolve_split(split) for f in self.sequences[seq]]

    def resolve_split(self, split: str) -> list[str]:
        if split == "all":
            return list(self.sequences)
        if split in self.splits:
            names = self.splits[split]
            where = self.split_files.get(split, self.root)
            missing = [s for s in names if s not in self.sequences]
            if missing:
                raise InputError(f"{where}: split '{split}' names sequence '{missing[0]}', which "
                                 f"has no frames in {self.root}")
            if not names:
                raise InputError(f"{where}: split '{split}' names no sequences")
            return names
        by_role = [s for s, r in self.roles.items() if r == split]
        if by_role:
            missing = [s for s in by_role if s not in self.sequences]
            if missing:
                raise InputError(f"{self.root}: role '{split}' names sequence '{missing[0]}', "
                                 "which has no frames")
            return by_role
        names = [s.strip() for s in split.split(",")]
        if not all(names):
            raise InputError(f"{self.root}: empty sequence name in split '{split}'")
        missing = [s for s in names if s not in self.sequences]
        if missing:
            known = ", ".join(["train", "test", "all", *self.roles.values(), *self.sequences])
            raise InputError(f"{self.root}: unknown split or sequence '{missing[0]}' "
                             f"(known: {known})")
        return names
