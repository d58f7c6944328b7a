"""What may join a map: the one rule of every command that adds a dataset's frames to a map
that holds frames already (`slam --map OLD --out NEW`, `pseudo-label`).

- **One camera.** A map's rows hold keypoints in the pixels of its one camera (`SceneMap.camera`,
  what export writes, what guided matching and pseudo-labelling project with), so every frame
  that joins it is of that camera (`Camera.same_as`): the same lens model, size and parameters.
- **Each frame once.** A map holds each frame once, and its readers look a frame up by name in
  the datasets it records (`MapMeta.dataset_roots`). A dataset holding a frame named as one of
  the map's is refused where the name could not be told apart: it is none of the map's
  datasets, or another of them holds that name too (`check_joining`). A frame the map holds
  already (by name, or by picture: the same pixels, `io.images.picture_digest`, whatever the
  file's name, format or bytes) is not added again: pseudo-labelling, whose work is adding
  frames, refuses it (`refuse_held`); a SLAM session tracks it and relocalizes on it without
  making it a keyframe of the map (`LiveMap.add_keyframe`). A map records its frames'
  pictures (`MapMeta.frame_pictures`), so they are known wherever its datasets are now; for a
  map that did not record them, those of its datasets still at hand are read.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

from slamreloc.datasets import load_dataset, read_frame_image
from slamreloc.errors import InputError
from slamreloc.io.images import picture_digest
from slamreloc.types import Camera

ONE_CAMERA = "a map holds one camera (its rows' pixels are that camera's)"


def _camera_problem(dataset, frame, camera: Camera, of_what: str, advice: str) -> None:
    """InputError unless `frame` is of `camera` (that of `of_what`, said in the message)."""
    if not camera.same_as(frame.camera):
        raise InputError(f"{dataset.root}: frame {frame.name[:80]!r} is of the camera "
                         f"{frame.camera.describe()}, {of_what} of the camera "
                         f"{camera.describe()}: {ONE_CAMERA}; {advice}")


@dataclass(frozen=True)
class Held:
    """What a map holds (`held_by`): its frames' `names` (in the datasets it took them from)
    and `pictures` (`io.images.picture_digest`), for a frame that would join it to be
    compared with (`holds`)."""

    names: frozenset[str] = frozenset()
    pictures: frozenset[str] = frozenset()

    def holds(self, name: str, picture: str | None) -> bool:
        """Whether the frame `name` whose pixels have the digest `picture` is the map's."""
        return name in self.names or (picture is not None and picture in self.pictures)


def check_joining(prior, map_dir: Path, dataset, frames: list) -> Held:
    """InputError, naming the dataset, unless `frames` of `dataset` may join the map `prior`
    (a `SceneMap`, read from `map_dir`): of its camera, and named apart from the frames of its
    other datasets (see the module's docstring). Returns what the map holds (`held_by`), for
    the caller to leave out (a SLAM session, as it reads each frame) or refuse
    (`refuse_held`). The map's datasets are read once for both."""
    for frame in frames:
        _camera_problem(dataset, frame, prior.camera, f"the map {map_dir}",
                        "extend it with frames of its camera")
    own = set(prior.info.frame_names or ())
    readable = _map_datasets(prior)
    _names_apart(prior, map_dir, dataset, own, readable)
    return Held(frozenset(own), _map_pictures(prior, readable, own))


def held_by(prior) -> Held:
    """What the map `prior` holds (`Held`), as `check_joining` returns it: for a caller that
    adds frames to it without that check (a `LiveMap` made in code)."""
    own = set(prior.info.frame_names or ())
    return Held(frozenset(own), _map_pictures(prior, _map_datasets(prior), own))


def _map_datasets(prior) -> dict[Path, list]:
    """The frames ("all") of each dataset the map records that is still at hand and readable
    (`MapMeta.dataset_roots`), by root: one that is not cannot be compared."""
    readable = {}
    for root in map(Path, prior.info.dataset_roots()):
        try:
            if root.exists():
                readable[root] = load_dataset(root).frames("all")
        except InputError:
            continue
    return readable


def _map_pictures(prior, readable: dict[Path, list], own: set[str]) -> frozenset[str]:
    """The pictures of the map's frames: those it recorded, and for a frame whose picture it
    did not record ("", or none recorded: maps of 0.1.0 and before, and the frames such a map
    passed on to an update or extension) that of its frame in its datasets still at hand
    (`readable`) where the image reads (a frame whose file is gone or no longer an image is
    no picture to compare)."""
    names = prior.info.frame_names or ()
    recorded = prior.info.frame_pictures or ("",) * len(names)
    unknown = {n for n, p in zip(names, recorded) if not p} & own
    frames = [f for frames_of in readable.values() for f in frames_of if f.name in unknown]
    return frozenset(filter(None, (*recorded, *_pictures(frames, quiet=True))))


def _pictures(frames: list, quiet: bool = False) -> list[str | None]:
    """Each frame's picture, its image read as every reader reads it (within the image bounds:
    InputError naming the file; `quiet`: None for an image that does not read)."""
    def one(frame) -> str | None:
        try:
            return picture_digest(read_frame_image(frame))
        except InputError:
            if quiet:
                return None
            raise

    with ThreadPoolExecutor(2) as pool:
        return list(pool.map(one, frames))


def refuse_held(map_dir: Path, dataset, frames: list, held: Held) -> list[str]:
    """InputError, naming the dataset, where `frames` hold frames the map holds already (by
    name or by picture, `held` from `check_joining`); else each frame's picture, in order,
    for the map they join to record."""
    pictures = _pictures(frames)
    taken = [f.name for f, p in zip(frames, pictures) if held.holds(f.name, p)]
    if taken:
        which = ("every frame to add (such as {}) is one" if len(taken) == len(frames)
                 else f"{len(taken)} of the {len(frames)} frames to add (such as {{}}) are "
                 "ones").format(repr(taken[0][:80]))
        raise InputError(f"{dataset.root}: {which} the map {map_dir} holds (by name, or the "
                         "same picture): a map holds each frame once; add frames it lacks "
                         "(another split or sequence)")
    return pictures


def check_one_camera(dataset, frames: list) -> None:
    """InputError, naming the dataset, unless `frames` (those a map is learned from) are all
    of one camera, the first's: the map they make holds one."""
    for frame in frames[1:]:
        _camera_problem(dataset, frame, frames[0].camera, f"frame {frames[0].name[:80]!r}",
                        "learn a map from the frames of one camera")


def _names_apart(prior, map_dir: Path, dataset, own: set[str],
                 readable: dict[Path, list]) -> None:
    """InputError where a reader of the extended map could not tell which picture one of its
    frames (names `own`) is: `dataset` (which the map will record beside its own datasets)
    holds a frame named as the map's, and is none of the map's datasets still at hand, or is
    one of them while another of them (`readable`: `_map_datasets`) holds that name too.
    Datasets no longer there (moved) are not compared."""
    shared = [f.name for f in dataset.frames("all") if f.name in own]
    if not shared:
        return
    session = dataset.root.resolve()
    at_hand = [r for r in map(Path, prior.info.dataset_roots()) if r.exists()]
    others = [r for r in at_hand if r.resolve() != session]
    if at_hand and len(others) == len(at_hand):
        raise InputError(f"{dataset.root}: holds frames named as the map {map_dir}'s own (such "
                         f"as {shared[0][:80]!r}), which come from the map's "
                         f"{'datasets' if len(at_hand) > 1 else 'dataset'} "
                         f"({', '.join(map(str, at_hand))[:400]}); the extended map would take "
                         "its frames for these: extend it with frames of one of those, or "
                         "named apart")
    for root in others:
        if root not in readable:  # not readable now: no frame of it is looked up either
            continue
        names = {f.name for f in readable[root]}
        clash = next((n for n in shared if n in names), None)
        if clash is not None:
            raise InputError(f"{dataset.root}: holds frames named as the map {map_dir}'s own "
                             f"(such as {clash[:80]!r}), and so does {root}, another dataset "
                             "of the map's: which one's picture is the map's frame cannot be "
                             "told; extend it with frames named apart")
