"""Issue 43, the ninth round's open findings and the tenth attack round, as regression tests:
map metadata that disagrees with the map's files (F8), view reports whose fields do not mean
what their names say (F7), the server's bound on learning sessions (F6); the tenth round's
service findings (G1-G5; G3, a save the map writer refuses, is in test_service_saves.py)."""

from __future__ import annotations

import errno
import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import time
import unicodedata
from pathlib import Path

import cv2
import grpc
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from slamreloc.client import Client, RemoteError, depth_msg
from slamreloc.datasets import load_dataset
from slamreloc.errors import InputError
from slamreloc.io.images import MAX_DEPTH_M, depth_from_raw, depth_units_problem
from slamreloc.map import write as map_write
from slamreloc.map.format import META
from slamreloc.map.scene_map import SceneMap
from slamreloc.proto import relocalizer_pb2 as pb
from slamreloc.proto.messages import ServiceError, depth_from_msg
from slamreloc.service.server import ServeConfig, start_server
from slamreloc.viewer import ViewerInputs, build_scene, load_scene_data, make_server
from slamreloc.viewer.reports import read_json
from tests.fuzzing import fuzz_settings, run_cli
from tests.test_cli_round5 import one_line_exit_2
from tests.test_fuzz_inputs import _tiny_map
from tests.test_round9 import _resave


@pytest.fixture(scope="module")
def tiny_map(tmp_path_factory) -> Path:
    return _tiny_map(tmp_path_factory.mktemp("round10") / "map")


def _edited(src: Path, out: Path, edit) -> Path:
    """A copy of the map `src` whose metadata `edit` changed (in place, on the parsed JSON)."""
    shutil.copytree(src, out)
    doc = json.loads((out / META).read_text())
    edit(doc)
    (out / META).write_text(json.dumps(doc))
    return out


# ---- F8: counts the metadata records must be the database's ---------------------------------
@pytest.mark.parametrize("edit, message", [
    (lambda d: d["labels"].update(n_labelled=5), "holds 64 rows, but slamreloc_map.json says "
                                                 "'labels.n_labelled' 5"),
    (lambda d: d["labels"].update(n_labelled=10 ** 9), "'labels.n_labelled' 1000000000"),
    (lambda d: d["labels"].update(n_frames=999), "holds 2 training frames, but "
                                                 "slamreloc_map.json says 'labels.n_frames' 999"),
    (lambda d: d["labels"].update(n_keyframes=3), "'labels.n_keyframes' 3"),
])
def test_label_counts_that_disagree_with_the_database_are_refused(tiny_map, tmp_path, edit,
                                                                   message):
    out = _edited(tiny_map, tmp_path / "m", edit)
    scene_map = SceneMap.load(out)
    with pytest.raises(InputError) as err:
        scene_map.database  # noqa: B018 - read on first use, checked there
    assert str(err.value).startswith(f"{out / 'database.npz'}: ") and message in str(err.value)
    # through the command line: one line, exit 2, nothing written
    one_line_exit_2(["export", str(out), "--tum", str(tmp_path / "t.txt")], message)
    assert not (tmp_path / "t.txt").exists()


def test_label_counts_that_agree_are_read(tiny_map, tmp_path):
    out = _edited(tiny_map, tmp_path / "m", lambda d: d["labels"].update(n_frames=2,
                                                                           n_keyframes=1))
    assert len(SceneMap.load(out).database.points) == 64


@pytest.mark.parametrize("edit, message", [
    (lambda d: d["labels"].update(n_keyframes=-3), "'labels.n_keyframes' is a count"),
    (lambda d: d.update(surface={"n_points": -1}), "'surface.n_points' is a count"),
    (lambda d: d.update(dataset={"kind": "tum"}) or d["dataset"].update(kind="bogus"),
     "'dataset.kind' must be one of"),
    (lambda d: d["files"].update({"unknown.npz": d["files"]["database.npz"]}),
     "'files' lists 'unknown.npz'"),
    (lambda d: d["regressor"].update(parameters=d["regressor"]["parameters"] + 1),
     "'regressor.parameters' is"),
    (lambda d: d["frame_names"].__setitem__(0, "seq-01/./frame-000000"),
     "is not a plain relative path"),
])
def test_metadata_that_cannot_be_true_is_refused_by_every_command(tiny_map, tmp_path, edit,
                                                                  message):
    out = _edited(tiny_map, tmp_path / "m", edit)
    one_line_exit_2(["export", str(out), "--tum", str(tmp_path / "t.txt")], str(out / META),
                    message)
    one_line_exit_2(["view", str(out), "--port", "0"], message)


# ---- F7: view reports whose counts, measures and names mean what they say -------------------
def _report(tmp_path: Path, doc: dict, name: str = "r.json") -> Path:
    path = tmp_path / name
    path.write_text(json.dumps(doc))
    return path


@pytest.mark.parametrize("doc, message", [
    ({"n_queries": "six", "per_query": []}, "n_queries is a count, a whole number >= 0; got 'six'"),
    ({"per_query": [{"name": "a", "num_inliers": -7}]},
     "per_query[0].num_inliers is a count, a whole number >= 0; got -7"),
    ({"per_query": [{"name": "a", "num_inliers": 7.5}]}, "per_query[0].num_inliers is a count"),
    ({"per_query": [{"name": "a", "translation_error_m": -1.0}]},
     "per_query[0].translation_error_m is a measure (distance, angle or time), a number >= 0; "
     "got -1.0"),
    ({"ate_rmse_m": "big", "events": []}, "ate_rmse_m is a measure"),
    ({"timings_s": {"features": -2}, "events": []}, "timings_s.features is a measure"),
    ({"n_pseudo_labels": 1, "poses": {"../../etc/passwd": [[1, 0, 0, 0]] * 4}},
     "poses: the frame name '../../etc/passwd' is not a path inside the dataset"),
    ({"n_pseudo_labels": 1, "poses": {"a\nb": [[1, 0, 0, 0]] * 4}},
     "holds a line break or another control character"),
    ({"n_queries": 1, "recall": {"1cm1deg": 5.0}}, "recall.1cm1deg is a share, a number in "
                                                   "[0, 1]; got 5.0"),
    ({"per_query": [{"name": "a", "rotation_error_deg": 1e6}]},
     "per_query[0].rotation_error_deg is an angle between two directions, in [0, 180]"),
])
def test_report_fields_of_the_wrong_meaning_are_refused(tmp_path, doc, message):
    path = _report(tmp_path, doc)
    with pytest.raises(InputError) as err:
        read_json(path)
    assert str(err.value).startswith(f"{path}: ") and message in str(err.value), err.value


@pytest.mark.parametrize("doc, message", [
    ({"n_queries": 2, "n_localized": 3, "per_query": []}, "n_localized 3 is more than "
                                                          "n_queries 2"),
    ({"n_queries": 1, "per_query": [{"name": "../../etc/passwd"}]},
     "per_query[0].name '../../etc/passwd' is not a path inside the dataset"),
    ({"events": [{"type": "kidnap", "frame": 1, "world_from_cam": [[2, 0, 0, 0], [0, 1, 0, 0],
                                                                   [0, 0, 1, 0], [0, 0, 0, 1]]}]},
     "events[0].world_from_cam: rotation"),
    ({"events": [{"type": "kidnap", "frame": 1, "position": [1e300, 0, 0]}]},
     "events[0].position lies beyond 1e+09 m"),
])
def test_report_entries_that_cannot_be_true_are_refused(viewer_case, tmp_path, doc, message):
    path = _report(tmp_path, doc)
    with pytest.raises(InputError) as err:
        load_scene_data(ViewerInputs(viewer_case.map_dir, reports=[path]))
    assert str(err.value).startswith(f"{path}: ") and message in str(err.value), err.value


def test_slam_report_frame_indices_are_not_negative(viewer_case, tmp_path):
    path = _report(tmp_path, {"events": [{"type": "kidnap", "frame": -10 ** 18}]})
    with pytest.raises(InputError, match=r"events\[0\]\.frame is a frame index, a whole number "
                                         r">= 0; got -1000000000000000000"):
        load_scene_data(ViewerInputs(viewer_case.map_dir, reports=[path]))
    path = _report(tmp_path, {"events": [], "kidnap_frames": [3, -1]}, "k.json")
    with pytest.raises(InputError, match=r"kidnap_frames\[1\] is a frame index"):
        load_scene_data(ViewerInputs(viewer_case.map_dir, reports=[path]))


@pytest.mark.parametrize("target", ["missing.txt", "fifo", "folder"])
def test_a_slam_reports_trajectory_must_be_a_readable_file(viewer_case, tmp_path, target):
    import os

    if target == "fifo":
        os.mkfifo(tmp_path / "fifo")
    elif target == "folder":
        (tmp_path / "folder").mkdir()
    path = _report(tmp_path, {"events": [], "trajectory": target})
    with pytest.raises(InputError, match=rf"{path}: its 'trajectory' .*{target}"):
        load_scene_data(ViewerInputs(viewer_case.map_dir, reports=[path]))


_COUNT_KEYS = st.sampled_from(["n_queries", "n_kidnaps", "num_inliers", "n_rows"])
_MEASURE_KEYS = st.sampled_from(["ate_rmse_m", "translation_error_m", "rotation_error_deg",
                                 "median_ms", "total_s", "median_reproj_error_px"])


@fuzz_settings(200)
@given(key=_COUNT_KEYS | _MEASURE_KEYS,
       value=st.none() | st.booleans() | st.integers(-10 ** 6, 10 ** 6)
       | st.floats(-1e6, 1e6) | st.text(max_size=4),
       nested=st.booleans())
def test_counts_and_measures_anywhere_in_a_report(tmp_path_factory, key, value, nested):
    """A count is null or a whole number >= 0, a measure null or a number >= 0 (an angle, at
    most 180), at any depth; anything else is refused naming the field."""
    tmp = tmp_path_factory.mktemp("r")
    doc = {"events": [], **({"live": {key: value}} if nested else {key: value})}
    field = f"live.{key}" if nested else key
    is_number = isinstance(value, (int, float)) and not isinstance(value, bool)
    ok = value is None or (is_number and value >= 0 and (
        isinstance(value, int) or not key.startswith(("n_", "num_")))
        and (value <= 180 or not key.endswith("_deg")))
    path = _report(tmp, doc)
    if ok:
        assert read_json(path) == doc
    else:
        with pytest.raises(InputError, match=rf"{path}: {field} is an? "):
            read_json(path)


# ---- tenth round, service G1: a hard link at the write lock is refused, never written -------
def test_a_lock_that_is_a_hard_link_is_refused_and_left_alone(tiny_map, tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("")  # empty, as a fresh lock would be
    os.link(victim, tmp_path / ".m.lock")
    with pytest.raises(InputError, match=r"\.m\.lock: a file with 2 names \(hard links\)"):
        _resave(tiny_map, tmp_path / "m")
    assert victim.read_text() == "" and not (tmp_path / "m").exists()


# ---- G2, H3: a folder at this process's temporary name ----------------------------------
# (contract moved at attack round 14: whether a writer lives is decided by the map's write
# lock, which holds across PID namespaces, not by whether a process of that id lives here)
@pytest.mark.parametrize("age_s", [0.0, 86400.0])
def test_a_killed_writers_temporary_with_this_process_id_is_cleaned_a_users_kept(
        tiny_map, tmp_path, age_s):
    """A killed writer's `.m.tmp-PID` holding only a map's files, with this process's id (a
    container gives the same id every run), new or backdated: under the map's lock no writer
    of it lives, so it is debris and goes; the save succeeds. The same name holding a user's
    file as well is refused and kept (the message says to move it)."""
    mine = tmp_path / f".m.tmp-{os.getpid()}"
    mine.mkdir()
    (mine / "database.npz").write_bytes(b"a killed save's bytes")
    if age_s:
        old = time.time() - age_s
        os.utime(mine / "database.npz", (old, old))
        os.utime(mine, (old, old))
    _resave(tiny_map, tmp_path / "m")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m"]
    mine.mkdir()
    (mine / "database.npz").write_bytes(b"a user's bytes")
    (mine / "notes.txt").write_text("mine\n")
    with pytest.raises(InputError, match="not made by this process"):
        _resave(tiny_map, tmp_path / "m")
    assert (mine / "notes.txt").read_text() == "mine\n"


# ---- H1: a file written into the map's folder while it is replaced is kept -----------------
@pytest.mark.parametrize("exchange", [True, False])
def test_a_file_written_into_the_map_during_a_resave_is_kept(tiny_map, tmp_path, monkeypatch,
                                                             exchange):
    out = tmp_path / "m"
    _resave(tiny_map, out)
    if not exchange:
        monkeypatch.setenv("SLAMRELOC_NO_RENAME_EXCHANGE", "1")

    def operator_writes(name: str) -> None:  # after the target's check, before the swap
        if name == "before-swap":
            (out / "EXPORT.txt").write_text("the operator's")

    monkeypatch.setattr(map_write, "_crash_point", operator_writes)
    _resave(tiny_map, out)
    assert (out / "EXPORT.txt").read_text() == "the operator's"
    assert SceneMap.load(out).info.n_labelled == 64
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m"]  # nothing left beside it


# ---- H2: an old copy this process could not remove does not block its next write -----------
def test_an_old_copy_that_could_not_be_removed_is_removed_at_the_next_write(
        tiny_map, tmp_path, monkeypatch, capsys):
    out = tmp_path / "m"
    _resave(tiny_map, out)
    calls = []
    real_rmdir = Path.rmdir

    def busy_once(self):
        calls.append(self)
        if len(calls) == 1:
            raise OSError(errno.EBUSY, "Device or resource busy", str(self))
        return real_rmdir(self)

    monkeypatch.setattr(Path, "rmdir", busy_once)
    _resave(tiny_map, out)
    assert "not removed (Device or resource busy)" in capsys.readouterr().err
    assert [p.name for p in tmp_path.iterdir() if p.name != "m"]  # the old copy is left
    _resave(tiny_map, out)  # the next write takes it away, as its own
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m"]
    assert SceneMap.load(out).info.n_labelled == 64


# ---- G4: one depth rule, also for raw depth deeper than the bound once scaled ---------------
@fuzz_settings(40)
@given(raw=arrays(np.uint16, (16, 20), elements=st.sampled_from([0, 1, 65, 999, 1500, 65534,
                                                                   65535])),
       units=st.sampled_from([1.0, 10.0, 1000.0, 5000.0]))
def test_raw_depth_follows_the_float_rule_once_scaled(raw, units):
    from_raw = depth_from_raw(raw, units)
    as_float = depth_from_msg(pb.Depth(encoding=pb.Depth.FLOAT32_METRES, width=20, height=16,
                                       data=(raw.astype(np.float32) / np.float32(units))
                                       .astype("<f4").tobytes()), None)
    expected = np.where(np.isin(raw, (0, 65535)), 0.0, as_float)
    assert np.array_equal(from_raw, expected)
    assert from_raw.max() <= MAX_DEPTH_M


# ---- H4: depth units that leave no raw value within the depth bound are refused -------------
@pytest.mark.parametrize("units", [0.001, 0.0152])
def test_depth_units_too_small_to_carry_depth_are_refused(units):
    assert "fewer units per metre leave no raw value" in depth_units_problem(units)
    raw = np.full((16, 16), 1000, np.uint16)
    with pytest.raises(ServiceError, match="units_per_metre must be in"):
        depth_from_msg(pb.Depth(encoding=pb.Depth.UINT16, width=16, height=16,
                                data=raw.tobytes(), units_per_metre=units), None)
    assert depth_units_problem(1 / MAX_DEPTH_M) is None and depth_units_problem(1000.0) is None


# ---- H5: the client never sends raw depth units as metres, nor metres as raw units ----------
def test_the_client_refuses_depth_of_the_wrong_kind():
    with pytest.raises(InputError, match="depth is uint16: metres are floats"):
        depth_msg(np.full((16, 16), 1732, np.uint16))
    assert depth_msg(np.full((16, 16), 1.732, np.float32)).encoding == pb.Depth.FLOAT32_METRES


def test_a_session_refuses_depth_of_the_wrong_kind(tiny_map):
    running = start_server({"m": tiny_map}, ServeConfig(port=0, watch_s=0))
    image = np.zeros((48, 64, 3), np.uint8)
    try:
        with Client(running.address, timeout_s=30) as client, client.session(
                map="m", odometry="client") as session:
            with pytest.raises(InputError, match="depth is uint16: metres are floats"):
                session.send(image, depth=np.full((48, 64), 1732, np.uint16))
            with pytest.raises(InputError, match="sends raw whole units 0..65535"):
                session.send(image, depth=np.full((48, 64), 1.7, np.float32),
                             depth_encoding="uint16")
            assert client.health().serving
    finally:
        running.stop()


# ---- F6: the server bounds the learning sessions open at once (their memory) -----------------
def test_learning_sessions_are_bounded_server_wide(tmp_path):
    folder = tmp_path / "learned"
    folder.mkdir()
    running = start_server({}, ServeConfig(port=0, watch_s=0, learned_maps=folder,
                                           max_learning_sessions=1))
    try:
        with Client(running.address, timeout_s=30) as client:
            first = client.session(odometry="auto", learn=True)
            with pytest.raises(RemoteError) as refused:
                client.session(odometry="auto", learn=True)
            assert refused.value.kind == "OVERLOADED" and "1 learning sessions open" in str(
                refused.value)
            first.close()
            deadline = time.monotonic() + 30
            while True:  # its place comes back once its handler has ended
                try:
                    client.session(odometry="auto", learn=True).close()
                    break
                except RemoteError as err:
                    assert err.kind == "OVERLOADED" and time.monotonic() < deadline
                    time.sleep(0.1)
            assert client.health().serving
    finally:
        running.stop()
    code, err = run_cli(["serve", "--learned-maps", str(folder), "--port", "0",
                         "--max-learning-sessions", "0"])
    assert code == 2 and err.strip() == "error: --max-learning-sessions 0: 1 to 4096"


# ---- G5: a map name the clients refuse is refused by the server for the same reason ---------
def test_the_server_says_the_name_rule_of_an_unknown_map(tiny_map):
    running = start_server({"m": tiny_map}, ServeConfig(port=0, watch_s=0))
    try:
        with Client(running.address, timeout_s=30) as client:
            name = unicodedata.normalize("NFD", "café")
            with pytest.raises(InputError, match="composed form"):  # the client's own check
                client.reload_map(name)
            try:  # the answer a client that does not check gets (the C++ one)
                client.stub.ReloadMap(pb.ReloadMapRequest(map=name), timeout=30,
                                      metadata=client.metadata)
                raise AssertionError("an NFD name was taken")
            except grpc.RpcError as rpc:
                err = RemoteError.from_rpc(rpc)
            assert err.kind == "UNKNOWN_MAP" and "is not in Unicode's composed form" in \
                err.message
    finally:
        running.stop()


# ---- tenth round, CLI F11, F12: reports slamreloc writes are read as written -----------------
def test_an_evaluate_reports_dataset_poses_is_not_a_frame_name_table(tmp_path):
    """`dataset.poses` (where the poses came from) is a string; only a pseudo-label report's
    own `poses` maps frame names."""
    path = _report(tmp_path, {"n_queries": 1, "per_query": [],
                              "dataset": {"root": "/d", "poses": "dataset"}})
    assert read_json(path)["dataset"]["poses"] == "dataset"


def test_a_slam_report_of_a_session_that_never_anchored_is_shown(viewer_case, tmp_path):
    (tmp_path / "t.txt").write_text("# a session that never anchored: no poses\n")
    path = _report(tmp_path, {"events": [{"type": "kidnap", "frame": 3}], "trajectory": "t.txt"})
    server = make_server("127.0.0.1", 0)
    try:
        data = load_scene_data(ViewerInputs(viewer_case.map_dir, reports=[path]))
        assert len(data.slams[0].trajectory) == 0
        build_scene(server, data).stop()
    finally:
        server.stop()
    path = _report(tmp_path, {"events": [], "trajectory": ""}, "e.json")
    with pytest.raises(InputError, match="'trajectory' is empty"):
        load_scene_data(ViewerInputs(viewer_case.map_dir, reports=[path]))


# ---- tenth round, CLI F1: outputs replace only what slamreloc wrote --------------------------
def test_outputs_never_replace_another_datasets_files(small_map, scene_dir, tmp_path):
    other = tmp_path / "other"
    shutil.copytree(scene_dir, other)
    (other / "groundtruth.txt").write_text("1.0 0 0 0 0 0 0 1\n")  # a TUM dataset's own
    before = {p: p.read_bytes() for p in (other / "groundtruth.txt", other / "scene.json")}
    one_line_exit_2(["evaluate", str(small_map.root), str(scene_dir), "--split", "query",
                     "--report", str(tmp_path / "r.json"),
                     "--trajectory", str(other / "groundtruth.txt")],
                    "--trajectory", "not a TUM trajectory slamreloc wrote")
    one_line_exit_2(["evaluate", str(small_map.root), str(scene_dir), "--split", "query",
                     "--report", str(other / "scene.json")],
                    "--report", "not a slamreloc report")
    assert all(p.read_bytes() == b for p, b in before.items())


# ---- F2, F3: a writer's temporary path that is in the way is never written through or deleted
def test_a_link_at_a_temporary_file_name_is_never_written_through(tiny_map, tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    (tmp_path / f".t.tmp-{os.getpid()}.txt").symlink_to(victim)
    one_line_exit_2(["export", str(tiny_map), "--tum", str(tmp_path / "t.txt")],
                    "its temporary path", "not made by this process")
    assert victim.read_text() == "precious\n" and not (tmp_path / "t.txt").exists()


def test_a_folder_at_a_temporary_folder_name_is_never_deleted(tiny_map, tmp_path):
    mine = tmp_path / f".col.tmp-{os.getpid()}"
    mine.mkdir()
    (mine / "cameras.txt").write_text("a user's\n")
    code, err = run_cli(["export", str(tiny_map), "--colmap", str(tmp_path / "col")])
    last = err.strip().splitlines()[-1]  # after the points' bar, which completed
    assert code == 2 and last.startswith("error: ") and "not made by this process" in last
    assert (mine / "cameras.txt").read_text() == "a user's\n"
    assert not (tmp_path / "col").exists()


# ---- F5: an empty folder is a valid --colmap target, before and after the work ---------------
def test_export_colmap_into_an_empty_folder(tiny_map, tmp_path):
    (tmp_path / "col").mkdir()
    code, err = run_cli(["export", str(tiny_map), "--colmap", str(tmp_path / "col")])
    assert code == 0, err
    assert sorted(p.name for p in (tmp_path / "col").iterdir()) == [
        "cameras.txt", "images.txt", "points3D.txt", "slamreloc_export.json"]


# ---- F4: a full disk names the output ----------------------------------------------------------
def test_a_full_disk_names_the_output(tiny_map, tmp_path, monkeypatch):
    def full(path, arrays):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(map_write, "_write_npz", full)
    with pytest.raises(OSError) as err:
        _resave(tiny_map, tmp_path / "m")
    assert err.value.filename == str(tmp_path / "m") and "No space left" in str(err.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # nothing half-written


# ---- F6: a terminal that cannot show a file name gets it escaped, not an error ---------------
def test_output_to_a_terminal_of_another_encoding(small_map, scene_dir, tmp_path):
    """F6, and F7: a name that would split an output line's fields is percent-encoded."""
    image, spaced = tmp_path / "日本.png", tmp_path / "my photo #1.png"
    for path in (image, spaced):
        shutil.copy(scene_dir / "seq-02" / "frame-000000.color.png", path)
    run = subprocess.run([sys.executable, "-m", "slamreloc.cli", "localize",
                          str(small_map.root), str(image), str(spaced)], capture_output=True,
                         env={**os.environ, "PYTHONIOENCODING": "latin-1"}, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    lines = run.stdout.decode("latin-1").splitlines()
    assert "\\u65e5\\u672c.png" in lines[0]
    assert lines[1].split()[0].endswith("my%20photo%20%231.png") and len(lines[1].split()) == 9


# ---- F9: an image a pixel wide, allowed by --limit, has no features (no traceback) -----------
def test_an_image_a_pixel_wide_is_no_traceback(tiny_map, tmp_path):
    image = tmp_path / "px.png"
    assert cv2.imwrite(str(image), np.zeros((240, 1, 3), np.uint8))
    code, err = run_cli(["--limit", "min_image_side=1", "localize", str(tiny_map),
                         "--intrinsics", "262.5", "262.5", "0", "119.5", str(image)])
    assert "Traceback" not in err and code in (0, 2), err


# ---- F8, F10: map arrays that no training or pose makes are refused at load ------------------
@pytest.mark.parametrize("name, edit, message", [
    ("regressor.npz", lambda a: a.update(out_scale=np.full_like(a["out_scale"], 3e38)),
     "out_scale holds values beyond 1e+09"),
    ("regressor.npz", lambda a: a.update(in_std=np.full_like(a["in_std"], 1e-30)),
     "in_std holds values below 1e-09"),
    ("database.npz", lambda a: a["world_from_cam"].__setitem__((0, 0, slice(None, 3)),
                                                                 -a["world_from_cam"][0, 0, :3]),
     "not rigid poses"),
    ("database.npz", lambda a: a["world_from_cam"].__setitem__((1, 0, 3), 1e30),
     "places a camera beyond 1e+09 m"),
])
def test_map_arrays_that_cannot_be_true_are_refused(tiny_map, tmp_path, name, edit, message):
    out = tmp_path / "m"
    shutil.copytree(tiny_map, out)
    arrays = dict(np.load(out / name))
    edit(arrays)
    np.savez(out / name, **arrays)
    doc = json.loads((out / META).read_text())
    doc["files"][name] = hashlib.sha256((out / name).read_bytes()).hexdigest()
    (out / META).write_text(json.dumps(doc))
    with pytest.raises(InputError, match=re.escape(message)):
        SceneMap.load(out).database  # noqa: B018 - read on first use, checked there


# ---- F15: a 7-Scenes frame without its image is an error, not a frame fewer -----------------
def test_a_frame_without_its_image_is_named(scene_dir, tmp_path):
    copy = tmp_path / "scene"
    shutil.copytree(scene_dir, copy)
    (copy / "seq-01" / "frame-000015.color.png").unlink()
    with pytest.raises(InputError, match=r"frame-000015\.(pose\.txt|depth\.png): frame "
                                         r"seq-01/frame-000015 has no colour image"):
        load_dataset(copy)


# ---- eleventh round, CLI G1: a file name's undecodable bytes are encoded, not an error -------
def test_a_line_name_of_undecodable_bytes_is_percent_encoded():
    from slamreloc.cli.jobs import line_name

    assert line_name(os.fsdecode(b"x\xff.png")) == "x%FF.png"
    assert line_name("a b/#c.png") == "a%20b/%23c.png" and line_name("plain.png") == "plain.png"


# ---- G5: a full disk while the write lock is taken names the lock and leaves none ------------
def test_a_full_disk_at_the_lock_names_it_and_leaves_none(tiny_map, tmp_path, monkeypatch):
    from slamreloc.io import folder_lock

    def full(fd, data, offset):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(folder_lock.os, "pwrite", full)
    with pytest.raises(OSError) as err:
        _resave(tiny_map, tmp_path / "m")
    assert err.value.filename == str(tmp_path / ".m.lock")
    assert sorted(p.name for p in tmp_path.iterdir()) == []


# ---- G6: surface points beyond the coordinate bound are refused, whatever their dtype --------
@pytest.mark.parametrize("scale, dtype", [(1e36, np.float32), (1e300, np.float64)])
def test_surface_points_beyond_the_bound_are_refused(scale, dtype):
    from slamreloc.map.surface import Surface

    points = (np.ones((4, 3)) * scale).astype(dtype)
    normals = np.tile(np.array([[0.0, 0.0, 1.0]], dtype), (4, 1))
    with pytest.raises(InputError, match="surface 'points' beyond 1e\\+09 m"):
        Surface.from_arrays({"points": points, "normals": normals}, "s.npz")
