"""The Dataset record shared by all layouts: frames grouped in sequences and splits."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from slamreloc.errors import InputError
from slamreloc.types import Frame, frame_name_problem


@dataclass
class Dataset:
    """Posed (or unposed) RGB-D frames. `depth_registered`: depth pixels align with RGB pixels;
    where they do not, each frame's `depth_camera` and `rgb_from_depth` place its depth."""

    root: Path
    kind: str  # one of registry.DATASET_KINDS: "7scenes" | "synthetic" | "tum" | "colmap" ...
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

    def __post_init__(self) -> None:
        """Every frame's name is one a map can keep (`frame_name_problem`): a name made from
        a file or folder name (a bag's stem, a photo's) is refused here, naming the dataset,
        not after the work by the map it would be written into."""
        for frames in self.sequences.values():
            for frame in frames:
                problem = frame_name_problem(frame.name)
                if problem:
                    raise InputError(f"{self.root}: frame name {frame.name[:80]!r} {problem}: "
                                     "its name comes from the files' or folders' names; "
                                     "rename them")

    @property
    def poses_origin(self) -> Path:
        """Where the frames' poses were read: the pose file, else the dataset folder (for
        messages about a missing pose)."""
        return self.root if self.poses_source == "dataset" else Path(self.poses_source)

    def frames(self, split: str = "all") -> list[Frame]:
        """Frames of a split: "train", "test", "all", a role, a sequence, or a comma-separated
        list of these (`resolve_split`)."""
        return [f for seq in self.resolve_split(split) for f in self.sequences[seq]]

    def resolve_split(self, split: str) -> list[str]:
        """The sequences of `split`: "all", a split ("train", "test"), a role ("kidnap"), a
        sequence name, or a comma-separated list of these (`kidnap,seq-03`), in that order. A
        list that names a sequence twice, directly or through a split or role it also names,
        is refused: its frames would be used twice."""
        items = [s.strip() for s in split.split(",")]
        if not all(items):
            raise InputError(f"{self.root}: `split` {split[:200]!r}: an empty name (give a "
                             "split, role or sequence, or a comma-separated list of them)")
        names: list[str] = []
        given_as: dict[str, str] = {}  # sequence -> the item of the list that named it
        for item in items:
            for seq in self._resolve_one(item, split):
                if seq in given_as:
                    first = given_as[seq]
                    what = (f"'{item}' twice" if first == item else
                            f"sequence '{seq}' twice ({_as(first, seq)} and {_as(item, seq)})")
                    raise InputError(f"{self.root}: `split` {split[:200]!r} names {what}: its "
                                     "frames would be used twice")
                given_as[seq] = item
                names.append(seq)
        return names

    def _resolve_one(self, name: str, split: str) -> list[str]:
        """The sequences of one item of a split list."""
        if name == "all":
            return list(self.sequences)
        if name in self.splits:
            names = self.splits[name]
            where = self.split_files.get(name, self.root)
            missing = [s for s in names if s not in self.sequences]
            if missing:
                raise InputError(f"{where}: split '{name}' names sequence '{missing[0]}', which "
                                 f"has no frames in {self.root}")
            if not names:
                raise InputError(f"{where}: split '{name}' names no sequences")
            return list(names)
        by_role = [s for s, r in self.roles.items() if r == name]
        if by_role:
            missing = [s for s in by_role if s not in self.sequences]
            if missing:
                raise InputError(f"{self.root}: role '{name}' names sequence '{missing[0]}', "
                                 "which has no frames")
            return by_role
        if name in self.sequences:
            return [name]
        known = ", ".join(dict.fromkeys(["all", *self.splits, *self.roles.values(),
                                         *self.sequences]))
        within = f" (in `split` {split[:200]!r})" if name != split.strip() else ""
        raise InputError(f"{self.root}: unknown split or sequence {name[:200]!r}{within} "
                         f"(known splits, roles and sequences: {known[:2000]}; a "
                         "comma-separated list may combine them)")


def _as(item: str, seq: str) -> str:
    """How a split list's item named a sequence (for a message)."""
    return f"as '{seq}'" if item == seq else f"in '{item}'"
