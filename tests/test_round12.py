"""Issue 43, the twelfth attack round as regression tests: a session whose client never reads
its answers (K1), poses that are no rigid motion sent by the Python client (K2), a save over a
map folder of links (K3)."""

from __future__ import annotations

import errno
import queue
import threading
import time
from pathlib import Path

import grpc
import numpy as np
import pytest

from slamreloc.geometry import Rigid3
from slamreloc.proto import relocalizer_pb2 as pb

from slamreloc.service.server import SERVICE_NAME, ServeConfig, start_server
from tests.fuzzing import run_cli
from tests.test_fuzz_inputs import _tiny_map


@pytest.fixture(scope="module")
def tiny_map(tmp_path_factory) -> Path:
    return _tiny_map(tmp_path_factory.mktemp("round12") / "map")


def _health(address: str) -> pb.HealthResponse:
    with grpc.insecure_channel(address) as channel:
        body = channel.unary_unary(f"/{SERVICE_NAME}/Health")(
            pb.HealthRequest().SerializeToString(), timeout=10)
    return pb.HealthResponse.FromString(body)


# ---- K1: a client that never reads its answers is cancelled like one that sends nothing -----
def test_a_session_that_never_reads_its_answers_is_cancelled(tiny_map):
    running = start_server({"m": tiny_map}, ServeConfig(
        port=0, watch_s=0, max_sessions=1, session_idle_s=1.0, open_timeout_s=1.0))
    # a small receive window (no BDP growth): the server's sends block after a few hundred
    # answers the client does not read
    channel = grpc.insecure_channel(running.address, options=[("grpc.http2.bdp_probe", 0)])
    try:
        requests: queue.Queue = queue.Queue()
        requests.put(pb.SessionRequest(open=pb.SessionOpen(map="m")).SerializeToString())
        for _ in range(20000):  # each answered with an error: no frame in it
            requests.put(pb.SessionRequest().SerializeToString())
        end = threading.Event()
        call = channel.stream_stream(f"/{SERVICE_NAME}/Session")(
            iter(lambda: requests.get() if not requests.empty() or not end.wait() else None,
                 None), timeout=120)
        deadline = time.monotonic() + 60
        while _health(running.address).num_sessions == 0 and time.monotonic() < deadline:
            time.sleep(0.1)
        assert _health(running.address).num_sessions == 1
        # the client reads nothing and sends nothing more: the slot comes free
        while _health(running.address).num_sessions and time.monotonic() < deadline:
            time.sleep(0.2)
        assert _health(running.address).num_sessions == 0
        with grpc.insecure_channel(running.address) as other:  # and another client gets it
            answers = other.stream_stream(f"/{SERVICE_NAME}/Session")(iter([
                pb.SessionRequest(open=pb.SessionOpen(map="m")).SerializeToString()]),
                timeout=30)
            first = pb.SessionUpdate.FromString(next(answers))
            assert first.WhichOneof("message") == "opened", first
        end.set()
        call.cancel()
    finally:
        channel.close()
        running.stop()


# ---- K2: the client sends only rigid motions, as the server and pose files take them --------
@pytest.mark.parametrize("pose, message", [
    (lambda: Rigid3(np.diag([1.0, 1.0, -1.0]), np.zeros(3)), "not orthonormal"),  # reflection
    (lambda: Rigid3(2 * np.eye(3), np.zeros(3)), "not orthonormal"),
    (lambda: Rigid3(np.array([[1.0, 0.25, 0], [0, 1, 0], [0, 0, 1]]), np.zeros(3)),
     "not orthonormal"),  # a shear
    (lambda: Rigid3(np.eye(3), np.array([2e9, 0, 0])), "translation beyond"),
    (lambda: Rigid3.from_qt([0, 0, 0, 2], np.zeros(3)), "quaternion norm 2, not 1"),
    (lambda: Rigid3(np.eye(3), np.array([np.nan, 0, 0])), "non-finite"),
])
def test_the_client_refuses_a_pose_that_is_no_rigid_motion(tiny_map, pose, message):
    from slamreloc.client import Client
    from slamreloc.errors import InputError

    running = start_server({"m": tiny_map}, ServeConfig(port=0, watch_s=0))
    try:
        with Client(running.address) as client:
            with pytest.raises(InputError, match=message):
                client.localize(np.zeros((48, 64, 3), np.uint8), world_from_cam_prior=pose())
            with client.session("m") as session, pytest.raises(InputError, match=message):
                session.send(np.zeros((48, 64, 3), np.uint8), odometry_world_from_cam=pose())
    finally:
        running.stop()


# ---- K3: a save over a map folder of links says they are links -------------------------------
def test_a_map_folder_of_links_is_refused_naming_the_links(tiny_map, tmp_path):
    from slamreloc.errors import InputError
    from slamreloc.map.format import META
    from slamreloc.map.write import check_map_target

    links = tmp_path / "links"
    links.mkdir()
    for p in tiny_map.iterdir():
        (links / p.name).symlink_to(p)
    with pytest.raises(InputError, match="its '[^']+', .* are symbolic links, not a map "
                                         "writer's files; refusing to replace it"):
        check_map_target(links)
    assert (links / META).is_symlink()


# ---- CLI round 12 ----------------------------------------------------------------------------
def _export_tum(tiny_map: Path, path: Path) -> None:
    from tests.fuzzing import run_cli

    code, err = run_cli(["export", str(tiny_map), "--tum", str(path)])
    assert code == 0, err


def test_a_linked_trajectorys_names_file_is_not_an_output(tiny_map, tmp_path):
    """H1: `ln/g.txt` links to a trajectory elsewhere, and reads `ln/g.names.txt`."""
    from tests.test_cli_round5 import one_line_exit_2

    (tmp_path / "real").mkdir()
    (tmp_path / "ln").mkdir()
    _export_tum(tiny_map, tmp_path / "real" / "gt.txt")
    (tmp_path / "ln" / "g.txt").symlink_to(tmp_path / "real" / "gt.txt")
    (tmp_path / "ln" / "g.names.txt").write_bytes((tmp_path / "real" / "gt.names.txt")
                                                  .read_bytes())
    before = (tmp_path / "ln" / "g.names.txt").read_bytes()
    one_line_exit_2(["export", str(tiny_map), "--tum", str(tmp_path / "ln" / "g.foo")],
                    "also names the stamps of the trajectory")
    assert (tmp_path / "ln" / "g.names.txt").read_bytes() == before


@pytest.mark.parametrize("mark", ["fifo", "deep", "zero"])
def test_an_odd_export_mark_is_no_mark(tiny_map, tmp_path, mark):
    """H2: whatever sits at the mark's name, it is read within bounds or not at all."""
    import os

    from slamreloc.map.export import EXPORT_MARK
    from tests.fuzzing import run_cli

    model = tmp_path / "model"
    code, err = run_cli(["export", str(tiny_map), "--colmap", str(model)])
    assert code == 0, err
    (model / EXPORT_MARK).unlink()
    if mark == "fifo":
        os.mkfifo(model / EXPORT_MARK)
    elif mark == "zero":
        (model / EXPORT_MARK).symlink_to("/dev/zero")
    else:
        (model / EXPORT_MARK).write_text("[" * 100_000 + "]" * 100_000)
    code, err = run_cli(["export", str(tiny_map), "--colmap", str(model)], hang_s=60)
    assert code == 2 and "refusing to replace it" in err, err


def test_an_aligned_error_needs_three_poses():
    """H4: fewer than 3 poses fix no alignment: no aligned error, never an unaligned one."""
    import math

    from slamreloc.slam.metrics import ate_rmse

    a = [Rigid3(np.eye(3), np.array([0.0, 0, 0])), Rigid3(np.eye(3), np.array([1.0, 0, 0]))]
    b = [Rigid3(np.eye(3), np.array([5.0, 0, 0])), Rigid3(np.eye(3), np.array([6.0, 0, 0]))]
    assert math.isnan(ate_rmse(a, b, align=True)) and ate_rmse(a, b) == 5.0


def test_sfm_refuses_a_photo_of_a_format_it_does_not_read(scene_dir, tmp_path):
    """H5: a GIF among the photos is named, never left out unsaid; PNM is read as `localize`
    reads it."""
    import shutil

    from slamreloc.sfm import IMAGE_SUFFIXES
    from tests.test_cli_round5 import one_line_exit_2

    assert {".ppm", ".pgm", ".pnm"} <= set(IMAGE_SUFFIXES)
    photos = tmp_path / "photos"
    photos.mkdir()
    for k in range(3):
        shutil.copy(scene_dir / "seq-01" / f"frame-{k:06d}.color.png", photos / f"p{k}.png")
    (photos / "x.gif").write_bytes(b"GIF89a")
    one_line_exit_2(["sfm", str(photos), "--out", str(tmp_path / "out")], "x.gif",
                    "a format sfm does not read")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("camera", ["opencv", " OPENCV", "OPENCV\u00a0"])
def test_sfm_reads_a_camera_model_as_every_command_does(camera):
    """H6: one spelling of a camera model for sfm and `localize --camera`."""
    from slamreloc.errors import InputError
    from slamreloc.sfm import SfmConfig, initial_camera

    with pytest.raises(InputError, match="unknown camera model"):
        initial_camera(SfmConfig(camera=camera), None)
    assert initial_camera(SfmConfig(camera="OPENCV"), None) == ("OPENCV", "")


@pytest.mark.parametrize("doc, message", [
    ({"n_queries": 0, "per_query": [], "map": {"size_bytes": -1}}, "map.size_bytes is a count"),
    ({"events": [], "backend_fps": -5}, "backend_fps is a measure"),
    ({"events": [], "relocalization_ms_per_call": -3}, "relocalization_ms_per_call is a measure"),
    ({"events": [], "frames_to_recover": [-3, 2]}, "frames_to_recover[0] is a count"),
    ({"events": [], "frames_to_recover": [2.5]}, "frames_to_recover[0] is a count"),
    ({"events": [], "truth_aligned_on_keyframes": "yes"}, "truth_aligned_on_keyframes is true "
                                                          "or false"),
    ({"n_queries": 0, "per_query": [], "guided_refinement": 3}, "guided_refinement is true"),
    ({"events": [], "kidnap_every": -4}, "kidnap_every is a count"),
    ({"events": [], "live_map": {"learner_share": -1}}, "live_map.learner_share is a measure"),
])
def test_report_fields_of_every_kind_follow_their_rule(tmp_path, doc, message):
    """H7: the name rules cover every field slamreloc's reports write."""
    import json

    from slamreloc.errors import InputError
    from slamreloc.viewer.reports import read_json

    path = tmp_path / "r.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError) as err:
        read_json(path)
    assert message in str(err.value), err.value


@pytest.mark.parametrize("section, values, message", [
    ("labels", {"n_keypoints": 100, "n_depth_labels": 101}, "'labels.n_depth_labels' must be a "
                                                          "count of at most"),
    ("labels", {"n_keypoints": 10}, "'labels.n_labelled' must be a count of at most"),
    ("train", {"noise_anneal": "no"}, "train.noise_anneal is true or false"),
    ("labels", {"mean_track_length": -1}, "labels.mean_track_length is a measure"),
    ("labels", {"n_tracks": 65}, "'labels.n_tracks' must be a count of at most"),
    ("labels", {"n_keypoints": 128, "labelled_fraction": 0.9}, "'labels.labelled_fraction' "
                                                              "must be 'labels.n_labelled' / "),
    ("labels", {"n_keypoints": 128, "n_tracks": 10, "mean_track_length": 0.5},
     "'labels.mean_track_length' must be a number of observations in 1..12.8"),
    ("labels", {"n_keypoints": 128, "n_tracks": 10, "mean_track_length": 13},
     "'labels.mean_track_length' must be a number of observations in 1..12.8"),
    ("labels", {"n_tracks": 0, "mean_track_length": 2}, "'labels.mean_track_length' must be 0"),
    ("labels", {"n_depth_labels": 5, "n_track_depth_disagreements": 6},
     "'labels.n_track_depth_disagreements' must be a count of at most 'labels.n_depth_labels'"),
])
def test_map_records_hold_what_their_counts_allow(tiny_map, tmp_path, section, values,
                                                  message):
    """H8."""
    import json
    import shutil

    from slamreloc.map.format import META
    from tests.test_cli_round5 import one_line_exit_2

    out = tmp_path / "m"
    shutil.copytree(tiny_map, out)
    doc = json.loads((out / META).read_text())
    doc.setdefault(section, {}).update(values)
    (out / META).write_text(json.dumps(doc))
    one_line_exit_2(["export", str(out), "--tum", str(tmp_path / "t.txt")], message)


@pytest.mark.parametrize("stdout", ["closed", "full"])
def test_localize_says_when_its_output_cannot_be_written(tiny_map, scene_dir, stdout):
    """H9: a closed standard output or a full disk behind it is an error naming it."""
    import os
    import subprocess
    import sys

    image = scene_dir / "seq-02" / "frame-000000.color.png"
    argv = [sys.executable, "-m", "slamreloc.cli", "localize", str(tiny_map), "--method",
            "matching", "--intrinsics", "60", "60", "32", "24", str(image)]
    with open("/dev/full", "w") as full:
        run = subprocess.run(argv, capture_output=False, stderr=subprocess.PIPE, text=True,
                             stdout=full if stdout == "full" else None, timeout=300,
                             preexec_fn=(lambda: os.close(1)) if stdout == "closed" else None)
    lines = run.stderr.strip().splitlines()
    assert run.returncode == 2 and len(lines) == 1, run.stderr
    assert "standard output" in lines[0], lines[0]


def test_a_reports_text_is_shown_as_text(tmp_path):
    """Round 12 CLI minor: a report's strings go into the viewer's markdown panels as text,
    never as HTML or table syntax."""
    from slamreloc.viewer.gui import md_text, report_table

    table = report_table({"n_queries": 1, "method": "<img src=x onerror=alert(1)>|x",
                          "map": {"root": "a*b*[c](d)`e`"}})
    assert "<img" not in table and "&lt;img src=x onerror=alert(1)&gt;\\|x" in table
    assert "| map.root | a\\*b\\*\\[c\\](d)\\`e\\` |" in table
    assert md_text("two\nlines") == "two lines"


# ---- H3: a command's map and report are both new, or both as they were ---------------------
def _tree(folder: Path) -> dict[str, bytes | None]:
    """Every path under `folder` (hidden ones too): a file's bytes, a folder's None."""
    return {str(p.relative_to(folder)): p.read_bytes() if p.is_file() else None
            for p in sorted(folder.rglob("*"))}


def _no_space(path, data):
    raise OSError(errno.ENOSPC, "No space left on device", str(path))


def test_pseudo_label_on_a_full_disk_at_the_report_keeps_the_map_it_had(
        small_map, scene_dir, tmp_path, monkeypatch):
    """H3: `pseudo-label` swapped its new map in, then failed writing the report: a new map
    beside an old report. The map and the report are now put in place together."""
    from slamreloc.pseudo_label import write

    argv = ["pseudo-label", str(small_map.root), str(scene_dir), "--out", str(tmp_path / "new"),
            "--report", str(tmp_path / "r.json"), "--rounds", "1", "--epochs", "1"]
    # two trainings: on a busy 2-core machine the first took over the 60 s hang guard
    code, err = run_cli(argv, hang_s=300.0)
    assert code == 0, err
    before = _tree(tmp_path)
    monkeypatch.setattr(write, "write_json", _no_space)
    code, err = run_cli([*argv[:-1], "2"], hang_s=300.0)
    assert code == 2 and "No space left" in err and "r.json" in err, err
    assert _tree(tmp_path) == before  # the old map and report, and no temporary left
