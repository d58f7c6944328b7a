"""Poses from elsewhere: a pose file or COLMAP model read into `ReferencePoses` (`read_poses`),
and `apply_poses`, which gives a dataset's frames those poses instead of its own (`--poses`);
`evaluate --reference` scores against poses read the same way.

Every pose is world_from_cam (camera-to-world) in the file's own world frame and units
(metres, unless the file is a model without a metric scale). The format is told from content:

- a COLMAP model: a folder holding cameras and images (.bin or .txt; points3D is not read),
  or a folder with sparse/0/ or sparse/ holding them. Names are the images' names;
  world_from_cam is the inverse of COLMAP's cam_from_world; unposed images are left out.
- a named file: `name tx ty tz qx qy qz qw` per line (camera centre in metres, camera-to-world
  rotation as a quaternion, scalar last), `#` comments: e.g. the 7-Scenes SfM pseudo ground
  truth, names like `seq-01/frame-000000`.
- TUM: `timestamp tx ty tz qx qy qz qw` per line (the first column a number), with the frame
  names of the sidecar `<stem>.names.txt` (`stamp name` per line) where there is one: what
  `evaluate --trajectory`, `slam --trajectory` and `export --tum` write.

A frame of a dataset takes the pose of (`match_poses`; the first rule that finds one wins):
1. its name (`Frame.name`, e.g. `seq-01/frame-000000`) or its image file's path relative to
   the dataset root (`seq-01/frame-000000.color.png`), exactly;
2. the same with image suffixes stripped on both sides (`.color.png`, `.png`, `.jpg`, ...);
3. for poses without a name (TUM without the sidecar): its timestamp, within 20 ms
   (`geometry.nearest_stamps`); one pose may not stand for frames of two sequences.
A file that names one frame in several of these ways must give it one pose (InputError
naming both names otherwise). Frames the file has no pose for become unposed.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from slamreloc.datasets.base import Dataset
from slamreloc.datasets.colmap import MODEL_DIRS, find_model, read_model_poses
from slamreloc.errors import InputError
from slamreloc.geometry import (
    Rigid3,
    names_sidecar,
    nearest_stamps,
    pose_gap,
    read_named_trajectory,
    read_names_sidecar,
    read_tum_trajectory,
    refuse_json_text,
    same_pose,
)
from slamreloc.io.fileio import open_regular, read_text
from slamreloc.io.outputs import reads_as
from slamreloc.io.numbers import written_as_number
from slamreloc.types import Frame

MAX_DT = 0.02  # seconds: a pose without a name stands for the frame this close in time
KINDS = ("colmap", "named", "tum", "dataset")  # "dataset": `datasets.read_reference`
# an image file name's suffix, with the 7-Scenes / TUM colour-image infix
_IMAGE_SUFFIX = re.compile(r"(\.(color|rgb))?\.(png|jpe?g|bmp|tiff?|webp|ppm|pgm)$",
                           re.IGNORECASE)


@dataclass(frozen=True, eq=False)
class ReferencePoses:
    """Camera poses read from `source` (`read_poses`): world_from_cam (camera-to-world, the
    file's world frame and units) by frame name, and the poses that carry a timestamp only."""

    source: Path  # the file or model folder, resolved
    kind: str  # one of KINDS
    world_from_cam: dict[str, Rigid3]  # by the name the file gives
    stamps: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (M,) s, unnamed poses
    stamped_world_from_cam: list[Rigid3] = field(default_factory=list)  # row for row

    def __len__(self) -> int:
        return len(self.world_from_cam) + len(self.stamps)

    def count(self) -> str:
        """"1 pose", "600 poses": for messages."""
        return f"{len(self)} pose{'' if len(self) == 1 else 's'}"

    def first(self) -> str:
        """The first pose's name (or timestamp), for messages."""
        if self.world_from_cam:
            return repr(next(iter(self.world_from_cam)))
        return f"t = {self.stamps[0]:.6f} s" if len(self.stamps) else "none"


@dataclass(frozen=True)
class FrameKey:
    """What a pose file may know a frame by."""

    name: str  # Frame.name
    image: str | None = None  # the image file relative to the dataset root, POSIX
    timestamp: float | None = None  # seconds
    sequence: str = ""

    @staticmethod
    def of(frame: Frame, root: Path) -> FrameKey:
        try:
            image = Path(frame.image_path).relative_to(root).as_posix()
        except ValueError:  # an image outside the dataset folder (a ROS bag's still)
            image = None
        return FrameKey(frame.name, image, frame.timestamp, frame.sequence)

    def ids(self) -> list[str]:
        """The names a pose file may give the frame: its name, then its image's path."""
        return [self.name] + ([self.image] if self.image and self.image != self.name else [])


def read_own_trajectory(path: Path) -> None:
    """A TUM trajectory slamreloc wrote: every writer of one (`evaluate`, `slam`, `export
    --tum`) puts its frame names in the sidecar beside it (`names_sidecar`), which a dataset's
    own trajectory (a TUM dataset's groundtruth.txt) lacks. InputError otherwise."""
    sidecar = names_sidecar(path)
    if not sidecar.is_file():
        raise InputError(f"{path}: no {sidecar.name} beside it, so not a trajectory slamreloc "
                         "wrote")
    read_written_names(sidecar)
    read_tum_trajectory(path)


def check_names_sidecar_free(trajectory: Path, option: str) -> None:
    """InputError unless the names sidecar of the trajectory output `trajectory` (`X.names.txt`,
    shared by every `X.*`) belongs to no other trajectory: a TUM file `X.*` beside it other
    than `trajectory` (an `X.txt` when writing `X.csv`, or an input's `X.txt` when writing
    `X.foo`) would have its stamps read against the new names."""
    trajectory = Path(trajectory)
    sidecar = names_sidecar(trajectory)
    if not trajectory.parent.is_dir():
        return
    for entry in trajectory.parent.iterdir():
        if (entry.name in (trajectory.name, sidecar.name) or names_sidecar(entry) != sidecar
                or not entry.is_file()):  # a link to a trajectory elsewhere reads this sidecar
            continue
        try:
            if not read_tum_trajectory(entry):  # no stamps to misread (`> X.out` made it)
                continue
        except InputError:
            continue
        raise InputError(f"{trajectory}: {option} would write its frame names to {sidecar}, "
                         f"which also names the stamps of the trajectory {entry}; give the "
                         "output another name (every X.* trajectory shares X.names.txt)")


WRITTEN_STAMP = re.compile(r"-?[0-9]+\.[0-9]{6}")  # a stamp as `write_tum_trajectory` writes it


def read_written_names(path: Path) -> None:
    """A frame-names sidecar as slamreloc writes it: `read_names_sidecar`'s lines, each stamp
    written with six decimals, each name not a row of three or more numbers (a TUM
    trajectory's): what an output may replace as its own names file (a user's `1 buy milk`
    list is not one). InputError otherwise."""
    read_names_sidecar(path)  # bounded, a regular file, 'stamp name' lines
    text = read_text(path, "frame names file", "max_text_bytes")
    for number, line in enumerate(text.splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        stamp, _, name = line.strip().partition(" ")
        words = name.split()
        if not WRITTEN_STAMP.fullmatch(stamp) or len(words) >= 3 and all(
                written_as_number(word) for word in words):
            raise InputError(f"{path}:{number}: not a line slamreloc writes ('%.6f NAME')")


# `check_outputs`' `files` entries: a TUM trajectory output (`--trajectory`, `export --tum`)
# and the frame-names sidecar written beside it (`names_sidecar`) may replace only their kind
NAMES_FILE = reads_as(read_written_names, "a frame-names file slamreloc wrote ('stamp name' "
                                          "lines)")
TUM_FILE = reads_as(read_own_trajectory,
                    "a TUM trajectory slamreloc wrote (its frame names in the .names.txt file "
                    "beside it)")


def poses_by_name(path, names, poses) -> dict:
    """{frame name: its pose} of a trajectory read from `path` (unnamed rows left out);
    InputError `PATH: frame NAME has more than one pose` where a name repeats: the rule of
    every reader of named poses (`--poses`, `--reference`, `view --trajectory`)."""
    named: dict = {}
    for name, pose in zip(names, poses):
        if name is None:
            continue
        if name in named:
            raise InputError(f"{path}: frame {name!r} has more than one pose")
        named[name] = pose
    return named


def _refuse_repeated_names(path: Path) -> None:
    """InputError `FILE:LINE: frame NAME has more than one pose` at the first frame name given
    twice in a pose file, found by a pass over the lines' first words before the lines are
    parsed (a 2 M line file with a repeat fails in a second, not after a minute). Only lines
    the parser would read as `name tx ty tz qx qy qz qw` count: a first word written as a
    number (a timestamp, even one out of range: `1e400`, `nan`) is no name, and a line of
    another field count is left to the parser, which says what is wrong with it."""
    text = read_text(path, "pose", "max_text_bytes")
    refuse_json_text(text, path, "pose")
    first_line: dict[str, int] = {}
    for i, line in enumerate(text.splitlines(), 1):
        words = line.split()
        if len(words) != 8 or words[0].startswith("#") or written_as_number(words[0]):
            continue
        seen = first_line.setdefault(words[0], i)
        if seen != i:
            raise InputError(f"{path}:{i}: frame {words[0][:80]!r} has more than one pose "
                             f"(also on line {seen})")


def strip_image_suffix(name: str) -> str:
    """`seq-01/frame-000000.color.png` -> `seq-01/frame-000000` (unchanged without one)."""
    return _IMAGE_SUFFIX.sub("", name)


def read_poses(path: str | Path) -> ReferencePoses:
    """A COLMAP model folder, a named pose file or a TUM file (module docstring); InputError
    naming the file (and line) for anything unreadable or empty."""
    path = Path(path)
    if path.is_dir():
        folder, ext = find_model(path, (".", *MODEL_DIRS))
        posed = {n: p for n, p in read_model_poses(folder, ext).items() if p is not None}
        if not posed:
            raise InputError(f"{folder / f'images.{ext}'}: the model has no posed images")
        return ReferencePoses(path.resolve(), "colmap", posed)
    with open_regular(path, "pose"):  # not found, or a pipe, a device, a socket: named so
        pass
    _refuse_repeated_names(path)
    traj = read_named_trajectory(path)
    if not traj.poses:
        raise InputError(f"{path}: no poses (expected lines 'name tx ty tz qx qy qz qw' or "
                         "'timestamp tx ty tz qx qy qz qw', or a COLMAP model folder)")
    named = poses_by_name(path, traj.names, traj.poses)
    unnamed = [i for i, name in enumerate(traj.names) if name is None]
    return ReferencePoses(path.resolve(), "tum" if traj.numeric else "named", named,
                          traj.stamps[unnamed], [traj.poses[i] for i in unnamed])


def match_poses(reference: ReferencePoses, keys: list[FrameKey]) -> list[Rigid3 | None]:
    """The reference's world_from_cam for each frame (None where it has none), by the rules
    of the module docstring. InputError where the file gives one frame different poses under
    several of its names (`seq-01/frame-000000` and `seq-01/frame-000000.color.png`): as for
    a name given twice, which one is the camera's is not for the reader to guess."""
    exact = reference.world_from_cam
    by_stripped: dict[str, list[str]] = {}  # stripped name -> the file's names stripping to it
    for name in exact:
        by_stripped.setdefault(strip_image_suffix(name), []).append(name)
    claimed: dict[str, int] = {}  # a name of the file -> the frame it names exactly
    for i, key in enumerate(keys):
        for name in key.ids():
            if name in exact:
                claimed.setdefault(name, i)
    out: list[Rigid3 | None] = []
    for i, key in enumerate(keys):
        hits = [n for n in key.ids() if n in exact]
        # the names that strip to the frame's, unless they name another frame exactly
        near = list(dict.fromkeys(n for s in map(strip_image_suffix, key.ids())
                                  for n in by_stripped.get(s, ()) if claimed.get(n, i) == i))
        _one_pose(reference, key, list(dict.fromkeys(hits + near)))
        hit = hits[0] if hits else near[0] if near else None
        out.append(None if hit is None else exact[hit])
    if len(reference.stamps):
        _match_stamps(reference, keys, out)
    return out


def _one_pose(reference: ReferencePoses, key: FrameKey, names: list[str]) -> None:
    """InputError unless the file's `names` that stand for the frame `key` give it one pose."""
    first = names[0] if names else None
    for name in names[1:]:
        a, b = reference.world_from_cam[first], reference.world_from_cam[name]
        if not same_pose(a, b):
            raise InputError(f"{reference.source}: gives frame {key.name!r} two poses, as "
                             f"{first!r} and as {name!r} ({pose_gap(a, b)}); give each frame "
                             "one pose")


def _match_stamps(reference: ReferencePoses, keys: list[FrameKey],
                  out: list[Rigid3 | None]) -> None:
    """Fill `out` where still None with the unnamed pose nearest in time (within MAX_DT)."""
    todo = [i for i, key in enumerate(keys) if out[i] is None and key.timestamp is not None]
    if not todo:
        return
    rows = nearest_stamps(reference.stamps, [keys[i].timestamp for i in todo], MAX_DT)
    sequence_of_row: dict[int, str] = {}
    for i, row in zip(todo, rows.tolist()):
        if row < 0:
            continue
        seq = sequence_of_row.setdefault(row, keys[i].sequence)
        if seq != keys[i].sequence:
            raise InputError(
                f"{reference.source}: its poses carry timestamps without frame names, and "
                f"t = {reference.stamps[row]:.6f} s is a frame of both {seq} and "
                f"{keys[i].sequence}; name the frames ('name tx ty tz qx qy qz qw' lines, or "
                "the '.names.txt' sidecar of 'stamp name' lines)")
        out[i] = reference.stamped_world_from_cam[row]


def apply_poses(dataset: Dataset, reference: ReferencePoses) -> Dataset:
    """`dataset` with every frame's world_from_cam replaced by the reference's (None where it
    has no pose for the frame); `poses_source` names the file. InputError when the file has a
    pose for no frame of the dataset."""
    root = Path(dataset.root)
    keys = {seq: [FrameKey.of(f, root) for f in frames]
            for seq, frames in dataset.sequences.items()}
    flat = [k for seq_keys in keys.values() for k in seq_keys]
    matched = match_poses(reference, flat)
    n_matched = sum(p is not None for p in matched)
    if n_matched == 0:
        example = flat[0].name if flat else "none"
        raise InputError(f"{reference.source}: names no frame of {root} ({reference.count()}, "
                         f"the first {reference.first()}; the dataset's frames are named like "
                         f"{example!r})")
    it = iter(matched)
    sequences = {seq: [replace(f, world_from_cam=next(it)) for f in frames]
                 for seq, frames in dataset.sequences.items()}
    return replace(dataset, sequences=sequences, poses_source=str(reference.source),
                   poses_matched=n_matched)
