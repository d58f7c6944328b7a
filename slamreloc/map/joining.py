"""What may join a map: the one rule of every command that adds a dataset's frames to a map
that holds frames already (`slam --map OLD --out NEW`, `pseudo-label`).

- **One camera.** A map's rows hold keypoints in the pixels of its one camera (`SceneMap.camera`,
  what export writes, what guided matching and pseudo-labelling project with), so every frame
  that joins it is of that camera (`same_camera`): the same lens model, size and parameters.
- **Each frame once.** A map holds each frame once, and its readers look a frame up by name in
  the datasets it records (`MapMeta.dataset_roots`). A dataset holding a frame named as one of
  the map's is refused where the name could not be told apart: it is none of the map's
  datasets, or another of them holds that name too (`check_joining`). A frame the map holds
  already is not added again: pseudo-labelling, whose work is adding frames, refuses it
  (`refuse_held`); a SLAM session tracks it and relocalizes on it without making it a
  keyframe of the map (`LiveMap.add_keyframe`).
"""

from __future__ import annotations

import math
from pathlib import Path

from slamreloc.datasets import load_dataset
from slamreloc.errors import InputError
from slamreloc.types import Camera

PARAM_RTOL = 1e-6  # two cameras' parameters agree to this fraction (what a written camera keeps)


def same_camera(a: Camera, b: Camera) -> bool:
    """The same camera: lens model, width and height equal, every parameter (fx, fy, cx, cy,
    distortion) within PARAM_RTOL of the other's (absolutely 1e-9 near zero)."""
    if (a.model, a.width, a.height) != (b.model, b.width, b.height):
        return False
    pa, pb = [*a.params(), *a.distortion], [*b.params(), *b.distortion]
    return len(pa) == len(pb) and all(math.isclose(x, y, rel_tol=PARAM_RTOL, abs_tol=1e-9)
                                      for x, y in zip(pa, pb))


def describe_camera(camera: Camera) -> str:
    """`PINHOLE 320x240 (fx 262.5, fy 262.5, cx 159.5, cy 119.5)`, distortion after."""
    text = (f"{camera.model} {camera.width}x{camera.height} (fx {camera.fx:.6g}, "
            f"fy {camera.fy:.6g}, cx {camera.cx:.6g}, cy {camera.cy:.6g}")
    if camera.distortion:
        text += ", distortion " + " ".join(f"{d:.6g}" for d in camera.distortion)
    return text + ")"


ONE_CAMERA = "a map holds one camera (its rows' pixels are that camera's)"


def _camera_problem(dataset, frame, camera: Camera, of_what: str, advice: str) -> None:
    """InputError unless `frame` is of `camera` (that of `of_what`, said in the message)."""
    if not same_camera(camera, frame.camera):
        raise InputError(f"{dataset.root}: frame {frame.name[:80]!r} is of the camera "
                         f"{describe_camera(frame.camera)}, {of_what} of the camera "
                         f"{describe_camera(camera)}: {ONE_CAMERA}; {advice}")


def check_joining(prior, map_dir: Path, dataset, frames: list) -> None:
    """InputError, naming the dataset, unless `frames` of `dataset` may join the map `prior`
    (a `SceneMap`, read from `map_dir`): of its camera, and named apart from the frames of its
    other datasets (see the module's docstring). Frames the map holds already are the
    caller's to leave out (`held_frames`)."""
    for frame in frames:
        _camera_problem(dataset, frame, prior.camera, f"the map {map_dir}",
                        "extend it with frames of its camera")
    _names_apart(prior, map_dir, dataset)


def held_frames(prior, frames: list) -> list[str]:
    """The names of `frames` the map `prior` holds already (a map holds each frame once: a
    SLAM session tracks such a frame without adding it again, pseudo-labelling refuses it)."""
    own = set(prior.info.frame_names or ())
    return [f.name for f in frames if f.name in own]


def refuse_held(prior, map_dir: Path, dataset, frames: list) -> None:
    """InputError, naming the dataset, where `frames` hold frames the map holds already."""
    held = held_frames(prior, frames)
    if held:
        which = ("every frame to add (such as {}) is named as one" if len(held) == len(frames)
                 else f"{len(held)} of the {len(frames)} frames to add (such as {{}}) are named "
                 "as ones").format(repr(held[0][:80]))
        raise InputError(f"{dataset.root}: {which} the map {map_dir} holds: a map holds each "
                         "frame once, and looks its frames up by name; add frames it lacks "
                         "(another split or sequence)")


def check_one_camera(dataset, frames: list) -> None:
    """InputError, naming the dataset, unless `frames` (those a map is learned from) are all
    of one camera, the first's: the map they make holds one."""
    for frame in frames[1:]:
        _camera_problem(dataset, frame, frames[0].camera, f"frame {frames[0].name[:80]!r}",
                        "learn a map from the frames of one camera")


def _names_apart(prior, map_dir: Path, dataset) -> None:
    """InputError where a reader of the extended map could not tell which picture one of its
    frames is: `dataset` (which the map will record beside its own datasets) holds a frame
    named as the map's, and is none of the map's datasets still at hand, or is one of them
    while another of them holds that name too. Datasets no longer there (moved) are not
    compared."""
    own = set(prior.info.frame_names or ())
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
        try:
            names = {f.name for f in load_dataset(root).frames("all")}
        except InputError:  # not readable now: no frame of it is looked up either
            continue
        clash = next((n for n in shared if n in names), None)
        if clash is not None:
            raise InputError(f"{dataset.root}: holds frames named as the map {map_dir}'s own "
                             f"(such as {clash[:80]!r}), and so does {root}, another dataset "
                             "of the map's: which one's picture is the map's frame cannot be "
                             "told; extend it with frames named apart")
