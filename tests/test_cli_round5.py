"""The fifth attack round on the CLI and its files, as regression tests: outputs under a broken
link refused before the work, empty option values, the learned map's write lock held for a
whole `slam --out` session, special files where a pose or weights file is expected, a frame's
depth that is not a file, byte-order marks, principal points, a missing device, outputs
written together when interrupted."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from slamreloc.datasets import load_dataset
from slamreloc.errors import InputError
from slamreloc.geometry import Rigid3, read_tum_trajectory
from slamreloc.io.fileio import outputs_together
from slamreloc.map.lock import map_write_lock
from slamreloc.types import Camera
from tests.fuzzing import run_cli
from tests.test_fuzz_inputs import make_sevenscenes

REPO = Path(__file__).resolve().parents[1]


def one_line_exit_2(argv: list[str], *needles: str) -> str:
    code, err = run_cli(argv)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith("error: "), (code, err)
    for needle in needles:
        assert needle in lines[0], (needle, err)
    return lines[0]


def test_an_output_under_a_broken_link_is_refused_before_the_work(small_map, scene_dir,
                                                                   tmp_path):
    """Finding 1: `--report dd/r.json` with dd a link to nothing failed only after the whole
    evaluation, with `[Errno 17] File exists: 'dd'`; now at once, naming the link."""
    link = tmp_path / "dd"
    link.symlink_to(tmp_path / "nowhere")
    line = one_line_exit_2(["evaluate", str(small_map.root), str(scene_dir),
                            "--report", str(link / "r.json")], str(link), "does not exist")
    assert "Errno" not in line
    assert not (tmp_path / "nowhere").exists()


@pytest.mark.parametrize("option", ["--report", "--trajectory", "--split"])
def test_an_empty_option_value_is_refused(small_map, scene_dir, tmp_path, option):
    """Finding 6: `--trajectory ''` was the path '.' ("PosixPath('.') has an empty name")."""
    argv = ["evaluate", str(small_map.root), str(scene_dir), "--report", str(tmp_path / "r.json")]
    argv = [*argv, option, ""] if option != "--report" else [*argv[:3], option, ""]
    one_line_exit_2(argv, option, "empty value")


def test_slam_out_holds_the_maps_write_lock_for_the_whole_session(kidnap_scene, tmp_path):
    """Finding 3: another command writing MAP while `slam --out MAP` runs had its map replaced
    by the session's save; the session now holds MAP's write lock from its start, so a second
    writer (here this test) makes it fail at once."""
    out = tmp_path / "learned"
    with map_write_lock(out):
        res = subprocess.run([sys.executable, "-m", "slamreloc.cli", "slam", str(kidnap_scene),
                              "--out", str(out), "--report", str(tmp_path / "r.json")],
                             capture_output=True, text=True, timeout=120, cwd=REPO)
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2 and len(lines) == 1, res.stderr
    assert "another process" in lines[0] and str(os.getpid()) in lines[0], lines
    assert not (tmp_path / "r.json").exists() and not out.exists()


def test_a_special_file_as_odometry_or_weights_is_named(small_map, scene_dir, kidnap_scene,
                                                       tmp_path):
    """Finding 4: a FIFO given as `--odometry` or `--superpoint-weights` was "not found"; it is
    "not a regular file (a named pipe)", as `--poses` says; a folder likewise."""
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    one_line_exit_2(["slam", str(kidnap_scene), "--map", str(small_map.root), "--odometry",
                     str(fifo), "--report", str(tmp_path / "r.json")], "a named pipe")
    (tmp_path / "folder").mkdir()
    one_line_exit_2(["slam", str(kidnap_scene), "--map", str(small_map.root), "--odometry",
                     str(tmp_path / "folder"), "--report", str(tmp_path / "r.json")],
                    "a folder")
    one_line_exit_2(["map", str(scene_dir), "--out", str(tmp_path / "m"), "--features",
                     "superpoint", "--superpoint-weights", str(fifo)], "a named pipe")


def test_superpoint_weights_go_with_superpoint_only(scene_dir, tmp_path):
    """Finding 11 (and 9): without weights the error names the option, not an internal
    field; weights given with SIFT are refused, not ignored."""
    one_line_exit_2(["map", str(scene_dir), "--out", str(tmp_path / "m"), "--features",
                     "superpoint"], "--superpoint-weights")
    weights = tmp_path / "w.pth"
    weights.write_bytes(b"x")
    one_line_exit_2(["map", str(scene_dir), "--out", str(tmp_path / "m"),
                     "--superpoint-weights", str(weights)], "--features superpoint")
    assert not (tmp_path / "m").exists()


@pytest.mark.skipif(torch.cuda.is_available(), reason="the machine has a CUDA device")
def test_a_missing_device_is_refused_before_the_work(scene_dir, tmp_path):
    """Finding 12: `map --device cuda` without a GPU computed features, labels and the
    surface first; now it stops before them."""
    code, err = run_cli(["map", str(scene_dir), "--out", str(tmp_path / "m"), "--device",
                         "cuda"])
    lines = err.strip().splitlines()
    assert code == 2 and lines[-1].startswith("error: ") and "CUDA" in lines[-1], err
    assert "features" not in err and not (tmp_path / "m").exists()


@pytest.mark.parametrize("kind", ["folder", "device", "broken link"])
def test_a_depth_image_that_is_not_a_file_is_refused(tmp_path, kind):
    """Finding 5: a frame's depth.png that is a folder (or a link to /dev/zero, or to nothing)
    was read as "no depth"; it is refused, naming it."""
    root = make_sevenscenes(tmp_path / "ds")
    depth = root / "seq-01" / "frame-000001.depth.png"
    depth.unlink()
    if kind == "folder":
        depth.mkdir()
    else:
        depth.symlink_to("/dev/zero" if kind == "device" else tmp_path / "nothing")
    with pytest.raises(InputError) as err:
        load_dataset(root).frames("train")
    assert str(depth) in str(err.value) and "not a regular file" in str(err.value)


def test_a_byte_order_mark_is_read_like_json_reads_it(tmp_path):
    """Finding 7: a pose file saved with a byte-order mark glued it to the first frame's name
    ("no pose for query frame ..."); every text file now drops it, as JSON does."""
    path = tmp_path / "poses.txt"
    path.write_bytes(b"\xef\xbb\xbfseq-02/frame-000000 0 0 0 0 0 0 1\n")
    (name, pose), = read_tum_trajectory(path)
    assert name == "seq-02/frame-000000"
    assert np.allclose(pose.matrix(), Rigid3.identity().matrix())


@settings(max_examples=40, deadline=None, derandomize=True)
@given(width=st.integers(1, 4000), height=st.integers(1, 4000),
       u=st.floats(-3, 3), v=st.floats(-3, 3))
def test_the_principal_point_lies_within_one_image_of_the_image(width, height, u, v):
    """Finding 8: a principal point a million pixels away was taken; it must lie within one
    image size of the image (cx in [-width, 2 width], cy likewise)."""
    cx, cy = u * width, v * height
    inside = -1 <= u <= 2 and -1 <= v <= 2
    try:
        Camera(width, height, 500.0, 500.0, cx, cy)
    except InputError as err:
        assert not inside and "within one image size" in str(err)
        return
    assert inside


def test_outputs_interrupted_while_written_are_all_new(tmp_path):
    """Finding 2: an evaluation interrupted between its writes left a new report beside an old
    plot. A Ctrl-C or SIGTERM during `outputs_together` waits for the last write, then ends
    the command: all outputs are new."""
    a, b = tmp_path / "a", tmp_path / "b"
    for signum in (signal.SIGINT, signal.SIGTERM):
        previous = signal.signal(signal.SIGTERM, lambda *_: (_ for _ in ()).throw(
            KeyboardInterrupt))
        try:
            with pytest.raises(KeyboardInterrupt):
                with outputs_together():
                    a.write_text(str(signum))
                    os.kill(os.getpid(), signum)  # arrives between the two writes
                    b.write_text(str(signum))
        finally:
            signal.signal(signal.SIGTERM, previous)
        assert a.read_text() == b.read_text() == str(signum)
