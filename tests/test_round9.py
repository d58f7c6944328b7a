"""Issue 43, the ninth attack round: what it found, each as a regression test (the service's
session timestamps are in test_service_hardening.py, the C++ client's in test_cpp_client.py)."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from slamreloc.client import Client
from slamreloc.datasets import load_dataset
from slamreloc.errors import InputError
from slamreloc.io.images import read_depth
from slamreloc.map.scene_map import SceneMap
from slamreloc.map.write import save_map
from slamreloc.proto import relocalizer_pb2 as pb
from slamreloc.proto.messages import depth_from_msg
from tests.fuzzing import fuzz_settings
from tests.test_cli_round5 import one_line_exit_2
from tests.test_fuzz_inputs import _tiny_map


@pytest.fixture(scope="module")
def tiny_map(tmp_path_factory) -> Path:
    return _tiny_map(tmp_path_factory.mktemp("round9") / "map")


def _resave(src: Path, out: Path) -> None:
    m = SceneMap.load(src)
    save_map(out, m.info, m.regressor, m.database)


def _tree(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file()}


# ---- F1: the write lock never follows a link or overwrites a file that is not a lock -------
@pytest.mark.parametrize("target", ["victim.txt", "absent.txt"])
def test_a_lock_path_that_is_a_link_is_refused_and_never_followed(tiny_map, tmp_path, target):
    victim = tmp_path / target
    if target == "victim.txt":
        victim.write_text("keep me\n")
    (tmp_path / "out").mkdir()
    lock = tmp_path / "out" / ".m.lock"
    lock.symlink_to(victim)
    with pytest.raises(InputError, match=r"\.m\.lock: not a regular file"):
        _resave(tiny_map, tmp_path / "out" / "m")
    assert (victim.read_text() == "keep me\n") if target == "victim.txt" else not victim.exists()
    assert lock.is_symlink() and not (tmp_path / "out" / "m").exists()


def test_a_users_file_named_like_the_lock_is_kept(tiny_map, tmp_path):
    lock = tmp_path / ".m.lock"
    lock.write_text("my notes, not a lock\n")
    with pytest.raises(InputError, match="not a slamreloc write lock"):
        _resave(tiny_map, tmp_path / "m")
    assert lock.read_text() == "my notes, not a lock\n"


def test_a_killed_writers_lock_record_is_taken_over(tiny_map, tmp_path):
    (tmp_path / ".m.lock").write_text("4194303\nthis map\n")  # a dead writer's record
    _resave(tiny_map, tmp_path / "m")
    assert SceneMap.load(tmp_path / "m").info.n_labelled > 0
    assert not (tmp_path / ".m.lock").exists()


# ---- F2: a user's folder named like the writer's temporary one is never deleted -------------
@pytest.mark.parametrize("kind", ["tmp", "old"])
def test_a_users_folder_named_like_the_writers_own_is_kept(tiny_map, tmp_path, kind,
                                                          monkeypatch):
    out = tmp_path / "m"
    shutil.copytree(tiny_map, out)
    before = _tree(out)
    mine = tmp_path / f".m.{kind}-{os.getpid()}"
    mine.mkdir()
    (mine / "notes.txt").write_text("mine\n")
    monkeypatch.setenv("SLAMRELOC_NO_RENAME_EXCHANGE", "1")  # the .old folder's path
    with pytest.raises(InputError, match="not made by this process"):
        _resave(tiny_map, out)
    assert (mine / "notes.txt").read_text() == "mine\n" and _tree(out) == before


# ---- F3: a map folder holding other files is not replaced (they would go with it) ----------
def test_a_map_folder_with_other_files_is_not_replaced(tiny_map, tmp_path):
    out = tmp_path / "m"
    shutil.copytree(tiny_map, out)
    (out / "notes.txt").write_text("the operator's\n")
    before = _tree(out)
    with pytest.raises(InputError, match="'notes.txt', which is not a map's"):
        _resave(tiny_map, out)
    assert _tree(out) == before


# ---- F4, F5: one rule for depth, from files, the wire and bags ------------------------------
@fuzz_settings(25)
@given(raw=arrays(np.uint16, (16, 20), elements=st.sampled_from([0, 1, 999, 65534, 65535])),
       units=st.sampled_from([1000.0, 5000.0]))
def test_raw_depth_reads_the_same_from_a_file_and_the_wire(tmp_path_factory, raw, units):
    path = tmp_path_factory.mktemp("depth") / "d.png"
    assert cv2.imwrite(str(path), raw)
    from_file = read_depth(path, units)
    uint16 = depth_from_msg(pb.Depth(encoding=pb.Depth.UINT16, width=20, height=16,
                                     data=raw.astype("<u2").tobytes(), units_per_metre=units),
                            None)
    png16 = depth_from_msg(pb.Depth(encoding=pb.Depth.PNG16, data=path.read_bytes(),
                                    units_per_metre=units), None)
    assert np.array_equal(from_file, uint16) and np.array_equal(from_file, png16)
    assert not from_file[raw == 65535].any()


@fuzz_settings(25)
@given(depth=arrays(np.float32, (16, 16), elements=st.floats(width=32, allow_nan=True,
                                                             allow_infinity=True)))
def test_float_depth_keeps_only_measurements(depth):
    from slamreloc.datasets.rosbag import depth_millimetres

    wire = depth_from_msg(pb.Depth(encoding=pb.Depth.FLOAT32_METRES, width=16, height=16,
                                   data=depth.astype("<f4").tobytes()), None)
    kept = np.isfinite(depth) & (depth > 0) & (depth <= 65.534)
    assert np.array_equal(wire[kept], depth[kept]) and not wire[~kept].any()
    mm = depth_millimetres(depth)  # a bag's 32FC1 depth, by the same rule
    assert not mm[~kept].any()


# ---- F8: a NUL byte in a text file is named, with its line -----------------------------------
def test_a_nul_byte_in_rgb_txt_names_the_file_and_line(tmp_path):
    (tmp_path / "rgb").mkdir()
    (tmp_path / "rgb.txt").write_bytes(b"# list\n0.1 rgb/a\x00b.png\n")
    with pytest.raises(InputError, match=r"rgb\.txt:2: list holds a NUL byte"):
        load_dataset(tmp_path)


# ---- F9: the Python client checks map names by the server's rule before sending ------------
@pytest.mark.parametrize("name", ["a b", "x\n", "é" * 129, "e\u0301"])
def test_the_client_refuses_a_map_name_the_server_would(name):
    with Client("127.0.0.1:9", timeout_s=1) as client:
        for call in (lambda: client.reload_map(name), lambda: client.session(map=name),
                     lambda: client.localize(np.zeros((8, 8, 3), np.uint8), map=name)):
            with pytest.raises(InputError, match="`map`"):
                call()


# ---- CLI side --------------------------------------------------------------------------------
# F1: an optional dataset file that is a pipe, a device or a folder is an error, not "absent"
@pytest.mark.parametrize("name", ["intrinsics.txt", "depth.txt", "groundtruth.txt"])
@pytest.mark.parametrize("kind", ["fifo", "device", "folder"])
def test_an_optional_dataset_file_that_is_not_a_file_is_named(tmp_path, name, kind):
    (tmp_path / "rgb").mkdir()
    cv2.imwrite(str(tmp_path / "rgb" / "a.png"), np.zeros((48, 64, 3), np.uint8))
    (tmp_path / "rgb.txt").write_text("0.1 rgb/a.png\n")
    path = tmp_path / name
    {"fifo": lambda: os.mkfifo(path), "device": lambda: path.symlink_to("/dev/zero"),
     "folder": lambda: path.mkdir()}[kind]()
    with pytest.raises(InputError, match=rf"{name}: .* (a named pipe|a device|a folder), not a "
                                         "file"):
        load_dataset(tmp_path)


# F4: counts of frames an option gives are bounded, as every other count is
@pytest.mark.parametrize("flag", ["--kidnap-every", "--kidnap-skip", "--kidnap-from"])
def test_huge_frame_counts_are_refused(scene_dir, tiny_map, tmp_path, flag):
    extra = [] if flag == "--kidnap-every" else ["--kidnap-every", "40"]
    one_line_exit_2(["slam", str(scene_dir), "--map", str(tiny_map), *extra, flag,
                     str(10 ** 12), "--report", str(tmp_path / "r.json")],
                    f"{flag} must be in 0..10000000")
    assert not (tmp_path / "r.json").exists()


# F6: an error line shows a name's control characters escaped and a huge name cut
def test_an_error_line_escapes_control_characters_and_cuts_huge_names(tiny_map, tmp_path):
    data = tmp_path / "data"
    (data / "rgb").mkdir(parents=True)
    (data / "rgb.txt").write_text(f"0.1 rgb/\x1b[31mred{'x' * 5000}.png\n")
    line = one_line_exit_2(["evaluate", str(tiny_map), str(data), "--report",
                            str(tmp_path / "r.json")], "cannot read image")
    assert "\x1b" not in line and "\\x1b[31mred" in line and len(line) < 1000, line


# F2: a session extending a map with a fused surface keeps that surface
def test_extending_a_map_keeps_its_surface(small_map, tmp_path):
    from slamreloc.slam.live_map import LiveMap

    assert small_map.surface is not None
    out = LiveMap(prior=small_map).save(tmp_path / "extended")
    kept = SceneMap.load(out)
    assert kept.surface is not None and kept.info.surface == small_map.info.surface
    assert np.array_equal(kept.surface.points, small_map.surface.points)
