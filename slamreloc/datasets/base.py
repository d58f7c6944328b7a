"""The Dataset record shared by all layouts: frames grouped in sequences and splits."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from slamreloc.errors import InputError
from slamreloc.types import Frame


@dataclass
class Dataset:
    """Posed (or unposed) RGB-D frames. `depth_registered`: depth pixels align with RGB pixels;
    where they do not, each frame's `depth_camera` and `rgb_from_depth` place its depth."""

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
