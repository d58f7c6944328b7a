"""Attack rounds 35 and 36: what may join a map (`slamreloc/map/joining.py`), one rule for
`slam --map OLD --out NEW`, `pseudo-label` and a learning session: frames of the map's one
camera (T1-T3), each frame once (T4), no frame named as another dataset's map frame (T5); and
a session that adds nothing to OLD writes no NEW (T6)."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import cv2
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slamreloc.synthetic import render_scene
from slamreloc.types import Camera
from tests.conftest import SMALL_SCENE
from tests.fuzzing import run_cli


def _one_line_exit_2(argv: list) -> str:
    code, err = run_cli([str(a) for a in argv])
    lines = err.strip().splitlines()
    assert code == 2 and lines and lines[-1].startswith("error: "), (code, err)
    return lines[-1]


def _without(root: Path, *sequences: str) -> Path:
    """The synthetic dataset `root` without `sequences` (folders and scene.json entries)."""
    scene = json.loads((root / "scene.json").read_text())
    for name in sequences:
        shutil.rmtree(root / name)
        del scene["sequences"][name]
    (root / "scene.json").write_text(json.dumps(scene, indent=2))
    return root


@pytest.fixture(scope="module")
def other_camera_scene(tmp_path_factory) -> Path:
    """The small scene's room at half its size (another camera), without the map's sequence
    names (seq-01), so only the camera tells it apart from a dataset the map may take."""
    root = tmp_path_factory.mktemp("r35") / "half"
    render_scene(root, replace(SMALL_SCENE, width=160, height=120, fx=131.25, fy=131.25,
                               cx=79.5, cy=59.5, n_map=2, n_query=2, n_kidnap=6,
                               n_unlabelled=6))
    return _without(root, "seq-01", "seq-02")


@pytest.mark.parametrize("command", ["slam", "pseudo-label"])
def test_frames_of_another_camera_do_not_join_a_map(command, small_map, other_camera_scene,
                                                    tmp_path):
    """T1, T2: a 320x240 map extended by a session, or updated, with 160x120 frames recorded
    its own camera only: export then wrote a camera the new rows lie outside of."""
    out = tmp_path / "new"
    argv = ([command, other_camera_scene, "--split", "kidnap", "--map", small_map.root]
            if command == "slam" else [command, small_map.root, other_camera_scene])
    last = _one_line_exit_2([*argv, "--out", out, "--report", tmp_path / "r.json"])
    assert last.startswith(f"error: {other_camera_scene}: frame 'seq-0"), last
    assert ("is of the camera PINHOLE 160x120 (fx 131.25, fy 131.25, cx 79.5, cy 59.5), the "
            f"map {small_map.root} of the camera PINHOLE 320x240 (fx 262.5") in last, last
    assert "a map holds one camera" in last
    assert not out.exists() and not (tmp_path / "r.json").exists()


def test_a_map_is_learned_from_the_frames_of_one_camera(tmp_path):
    """From nothing too (`slam --out`, the frames a map is learned from): the first frame's
    camera is the map's, and a later frame of another is named with both cameras."""
    from slamreloc.datasets import Dataset
    from slamreloc.errors import InputError
    from slamreloc.map.joining import check_one_camera
    from slamreloc.types import Frame

    cam = Camera(320, 240, 262.5, 262.5, 159.5, 119.5)
    frames = [Frame(f"s/{i}", tmp_path / f"{i}.png", cam) for i in range(3)]
    dataset = Dataset(tmp_path, "synthetic", {"s": frames})
    check_one_camera(dataset, frames)
    frames.append(Frame("s/3", tmp_path / "3.png", cam.scaled_to(640, 480)))
    with pytest.raises(InputError) as err:
        check_one_camera(dataset, frames)
    assert str(err.value).startswith(
        f"{tmp_path}: frame 's/3' is of the camera PINHOLE 640x480 (fx 525, fy 525, cx 319, "
        "cy 239), frame 's/0' of the camera PINHOLE 320x240 (fx 262.5, fy 262.5, cx 159.5, "
        "cy 119.5): a map holds one camera"), err.value


def test_a_learning_session_refuses_a_frame_of_another_camera(kidnap_scene, tmp_path):
    """T3: the camera is given in frame 0; a later frame of another size defaulted to it,
    scaled, and the saved map recorded frame 0's camera for rows of both."""
    from slamreloc.client import Client, RemoteError
    from slamreloc.datasets import load_dataset
    from slamreloc.service.server import ServeConfig, start_server
    from slamreloc.slam.feed import read_frames
    from slamreloc.slam.live_map import LiveMapConfig

    dataset = load_dataset(kidnap_scene)
    frames = list(read_frames(dataset, dataset.frames("kidnap")[:3], depth=True))
    (tmp_path / "l").mkdir()
    running = start_server({}, ServeConfig(port=0, watch_s=0, learned_maps=tmp_path / "l",
                                           live=LiveMapConfig(feature_options={"upsample":
                                                                                True})))
    try:
        with Client(running.address) as client, client.session(odometry="auto") as session:
            f = frames[0]
            assert session.send(f.image, camera=f.camera, depth=f.depth,
                                timestamp=f.timestamp).index == 0
            big = frames[1]
            image = cv2.resize(big.image, (640, 480))
            depth = cv2.resize(big.depth, (640, 480), interpolation=cv2.INTER_NEAREST)
            for camera in (None, big.camera.scaled_to(640, 480)):
                with pytest.raises(RemoteError) as err:
                    session.send(image, camera=camera, depth=depth, timestamp=big.timestamp)
                assert err.value.kind == "BAD_CAMERA", err.value
                assert str(err.value).startswith("BAD_CAMERA: frame.camera: PINHOLE 640x480"), \
                    err.value
                assert "a map holds one camera" in str(err.value)
            # the session carries on with frames of its camera
            f = frames[2]
            assert session.send(f.image, camera=f.camera, depth=f.depth,
                                timestamp=f.timestamp).index == 1
    finally:
        running.stop()


def test_frames_the_map_holds_are_not_added_again(small_map, scene_dir, tmp_path):
    """T4: pseudo-label refused only the split the map was built from, so frames the map
    held otherwise (a session's, an update's) were added twice. A map holds each frame once:
    pseudo-label refuses them; a SLAM session tracks them without adding them, so a session
    of nothing else writes no map."""
    last = _one_line_exit_2(["pseudo-label", small_map.root, scene_dir, "--split",
                             "seq-02,seq-01", "--out", tmp_path / "n", "--report",
                             tmp_path / "r.json"])
    assert last == (f"error: {scene_dir}: 60 of the 80 frames to add (such as "
                    f"'seq-01/frame-000000') are ones the map {small_map.root} holds (by name, "
                    "or the same picture): a map holds each frame once; add frames it lacks "
                    "(another split or sequence)"), last
    last = _one_line_exit_2(["slam", scene_dir, "--split", "seq-01", "--map", small_map.root,
                             "--out", tmp_path / "n", "--report", tmp_path / "r.json",
                             "--save-every", "0"])
    assert last.startswith(f"error: {tmp_path / 'n'}: no map written: the session added no "
                           f"keyframe to {small_map.root}"), last
    assert not (tmp_path / "n").exists() and not (tmp_path / "r.json").exists()


def test_a_copy_of_the_maps_dataset_is_refused_by_pseudo_label_as_by_slam(
        small_map, scene_dir, tmp_path):
    """T5: a copy of the map's dataset (its frame names, another folder) was taken by
    pseudo-label and refused by `slam --map --out`; the new map held two datasets naming
    the same frames. Now one rule, naming the dataset the names come from."""
    copy = tmp_path / "copy"
    shutil.copytree(scene_dir, copy)
    for argv in (["pseudo-label", small_map.root, copy],
                 ["slam", copy, "--split", "seq-02", "--map", small_map.root]):
        last = _one_line_exit_2([*argv, "--out", tmp_path / "n", "--report",
                                 tmp_path / "r.json"])
        assert last.startswith(f"error: {copy}: holds frames named as the map "), last
        assert f"which come from the map's dataset ({scene_dir.resolve()})" in last, last
        assert not (tmp_path / "n").exists()


def test_a_session_that_never_anchors_writes_no_extended_map(small_map, tmp_path):
    """T6: `slam --map OLD --out NEW` of a session that never anchored in OLD (another room)
    wrote NEW, OLD retrained, recording the session's dataset as its own. Now nothing is
    written and the error says why."""
    room = tmp_path / "elsewhere"
    render_scene(room, replace(SMALL_SCENE, seed=7, n_map=2, n_query=2, n_kidnap=12,
                               n_unlabelled=2))
    _without(room, "seq-01", "seq-02")
    out = tmp_path / "new"
    code, err = run_cli(["slam", str(room), "--split", "kidnap", "--map", str(small_map.root),
                         "--out", str(out), "--report", str(tmp_path / "r.json"),
                         "--learn-every", "1", "--save-every", "0"])
    last = err.strip().splitlines()[-1]
    assert code == 2 and last == (
        f"error: {out}: no map written: the session added no keyframe to {small_map.root} (it "
        "never anchored in it, or saw nothing it lacks): track a split that overlaps the "
        "map's places and goes beyond them"), err
    assert not out.exists() and not (tmp_path / "r.json").exists()


_VALUE = st.floats(1.0, 1000.0)


@settings(max_examples=60, deadline=None)
@given(fx=_VALUE, cx=_VALUE, rel=st.sampled_from([0.0, 1e-8, 1e-7, 1e-5, 1e-3]),
       k1=st.sampled_from([0.0, 0.01]))
def test_same_as_is_every_parameter_within_its_tolerance(fx, cx, rel, k1):
    """Generated: a camera is the same as itself with a parameter moved by less than 1e-6
    of it, not by more; another size, model or distortion is another camera."""
    model = "OPENCV" if k1 else "PINHOLE"
    dist = (k1, 0.0, 0.0, 0.0) if k1 else ()
    a = Camera(640, 480, fx, fx, cx, 240.0, model, dist)
    b = Camera(640, 480, fx * (1 + rel), fx, cx, 240.0, model, dist)
    assert a.same_as(b) == (rel < 1e-6) and a.same_as(a)
    assert not a.same_as(replace(a, width=641))
    assert not a.same_as(Camera(640, 480, fx, fx, cx, 240.0, "OPENCV",
                                     (k1 + 0.02, 0.0, 0.0, 0.0)))


# ---- attack round 36 ---------------------------------------------------------------------------
def test_a_map_is_not_built_from_frames_of_two_cameras(scene_dir, tmp_path):
    """U1: `map` of a COLMAP project of two cameras recorded the first one only (`slam --out`
    refused the same project): one rule, before any work."""
    from slamreloc.datasets import load_dataset
    from tests.colmap_project import write_colmap_project

    frames = load_dataset(scene_dir).frames("seq-01")[:6]
    other = replace(frames[0].camera, fx=300.0, fy=300.0)
    project = write_colmap_project([replace(f, camera=other) if i % 2 else f
                                    for i, f in enumerate(frames)], tmp_path / "col")
    last = _one_line_exit_2(["map", project, "--out", tmp_path / "m", "--epochs", "1"])
    assert last.startswith(f"error: {project}: frame 'seq-01/frame-000001.color.png' is of "
                           "the camera PINHOLE 320x240 (fx 300, fy 300"), last
    assert "a map holds one camera" in last and not (tmp_path / "m").exists()


def test_the_maps_own_pictures_under_other_names_are_not_added_again(small_map, scene_dir,
                                                                      tmp_path):
    """U2: the map's own frames as a COLMAP project (named `seq-01/frame-000000.color.png`,
    where the map holds `seq-01/frame-000000`) were pseudo-labelled against their own labels
    and added a second time; a frame is held by its picture too (its decoded pixels)."""
    from slamreloc.datasets import load_dataset
    from tests.colmap_project import write_colmap_project

    frames = load_dataset(scene_dir).frames("seq-01")[:4]
    project = write_colmap_project(frames, tmp_path / "col")
    last = _one_line_exit_2(["pseudo-label", small_map.root, project, "--out", tmp_path / "n",
                             "--report", tmp_path / "r.json"])
    assert last == (f"error: {project}: every frame to add (such as "
                    f"'seq-01/frame-000000.color.png') is one the map {small_map.root} holds "
                    "(by name, or the same picture): a map holds each frame once; add frames it "
                    "lacks (another split or sequence)"), last
    assert not (tmp_path / "n").exists()
