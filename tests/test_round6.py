"""The sixth attack round, as regression tests: a read-only command that removed a user's
like-named files beside a map, addresses checked as one thing and bound as another, a Ray
config whose empty token file turned authentication off, a session slot held after its client
left, the Python client on a stream that ends or answers wrongly, map metadata and model files
read without their rules, one rule for camera strings and K matrices."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import grpc
import numpy as np
import pytest

from slamreloc.client import ClientSession, RemoteError
from slamreloc.errors import InputError
from slamreloc.map.format import META, WEIGHTS, sha256_file
from slamreloc.map.meta import MapMeta
from slamreloc.map.scene_map import SceneMap
from slamreloc.proto import relocalizer_pb2 as pb
from slamreloc.types import Camera, k_matrix_problem
from tests.fuzzing import run_cli
from tests.test_cli_round5 import one_line_exit_2




# ---- files beside a map ------------------------------------------------------------------
def test_a_readers_clean_up_takes_only_a_killed_writers_debris(small_map, scene_dir, tmp_path):
    """Findings 1 and 2: `localize` removed anything named `.NAME.tmp-*` / `.NAME.old-*`
    beside the map (a user's notes), and a map named `m[1]` took `.m1.tmp-7` for its own (the
    name was a glob pattern). Only folders a writer leaves (`.NAME.tmp-PID` holding map files,
    `.NAME.old-PID` holding a map) are debris."""
    maps = tmp_path / "maps"
    maps.mkdir()
    for name in ("m", "m[1]"):
        shutil.copytree(small_map.root, maps / name)
    mine = [maps / ".m.old-mine", maps / ".m.tmp-notes", maps / ".m1.tmp-777",
            maps / ".m.tmp-12", maps / ".m.old-20240101"]
    mine[0].mkdir()
    (mine[0] / "notes.txt").write_text("mine\n")
    mine[1].write_text("mine\n")
    mine[2].mkdir()
    mine[3].mkdir()  # a writer's name, a user's contents
    (mine[3] / "notes.txt").write_text("mine\n")
    shutil.copytree(small_map.root, mine[4])  # a dated backup of the map: a map, kept
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()  # a writer that was killed: its process id is free
    debris = maps / f".m.tmp-{gone.pid}"
    debris.mkdir()
    shutil.copy(small_map.root / WEIGHTS, debris / WEIGHTS)
    image = sorted(scene_dir.glob("seq-02/*.color.png"))[0]
    for name in ("m", "m[1]"):
        code, err = run_cli(["localize", str(maps / name), str(image)])
        assert code == 0, err
    assert all(p.exists() for p in mine), [p for p in mine if not p.exists()]
    assert not debris.exists()


# ---- addresses -----------------------------------------------------------------------------
def test_view_refuses_an_address_of_another_machine_instead_of_trying_ports_for_ever():
    """Finding 12 (CLI): `view --host 8.8.8.8` hung (viser tried port after port)."""
    from slamreloc.viewer.server import check_address

    with pytest.raises(InputError, match="not an address of this machine"):
        check_address("192.0.2.1", 0)  # TEST-NET-1: never this machine's
    check_address("127.0.0.1", 0)


# ---- tokens and the Ray config ---------------------------------------------------------------
@pytest.mark.parametrize("args, needle", [
    ({"token_file": "EMPTY"}, "is empty"),
    ({"token_file": "BLANK"}, "is empty"),
    ({"token_file": ""}, "`token_file` must name a file"),
    ({"token_file": None}, "`token_file` must name a file"),
    ({"replicas": 2.9}, "`replicas` must be a whole number"),
    ({"replicas": True}, "`replicas` must be a whole number"),
    ({"replica_cpus": "x"}, "`replica_cpus` must be a number"),
    ({"watch_s": None}, "`watch_s` must be a number"),
    ({"maps": {"m": None}}, "must be a map folder's path"),
    # round 8: NUL bytes, a share of a CPU Ray refuses, names the gRPC engine refuses
    ({"token_file": "tok\0en"}, "`token_file` must name a file"),
    ({"maps": {"m": "/tmp/m\0x"}}, "holds a NUL byte"),
    ({"replica_cpus": 1e-300}, "`replica_cpus` 1e-300: 0.01 to 64"),
    ({"maps": {"m" * 129: "/tmp"}}, "more than 128"),
])
def test_a_ray_config_keeps_the_clis_rules(tmp_path, args, needle):
    """Finding 2 (service): an empty `token_file` built the app with no token (no
    authentication on a proxy that listens on every interface); `replicas: 2.9` became 2."""
    pytest.importorskip("ray.serve")
    from slamreloc.service.ray_app import build_app

    (tmp_path / "EMPTY").write_text("")
    (tmp_path / "BLANK").write_text(" \n\t\n")
    if args.get("token_file") in ("EMPTY", "BLANK"):
        args = {"token_file": str(tmp_path / args["token_file"])}
    with pytest.raises(InputError, match=needle):
        build_app({"maps": {"m": str(tmp_path / "m")}, **args})


def test_the_token_rule_is_one_for_the_file_and_the_environment(tmp_path, monkeypatch):
    """Finding 3 (service): `--token-file` dropped the blanks around a token and
    $SLAMRELOC_TOKEN did not; an empty variable meant "no token" and an empty file an error."""
    from slamreloc.service.server import read_token

    token = "s3cret-token-0123456789"
    path = tmp_path / "token"
    path.write_text(token + "\n")
    monkeypatch.setenv("SLAMRELOC_TOKEN", token + "\n")
    assert read_token(path) == read_token(None) == token
    for empty in ("", " \n"):
        path.write_text(empty)
        monkeypatch.setenv("SLAMRELOC_TOKEN", empty)
        for source in (path, None):
            with pytest.raises(InputError, match="is empty"):
                read_token(source)
    monkeypatch.delenv("SLAMRELOC_TOKEN")
    assert read_token(None) is None


# ---- sessions --------------------------------------------------------------------------------
@pytest.fixture
def held_rounds(monkeypatch):
    """A save's training round that runs until its session is cancelled: (entered, cancelled)
    events."""
    from slamreloc.service import sessions

    waiting, cancelled = threading.Event(), threading.Event()
    cancel = sessions.Session.cancel

    def train_for_save(self):
        waiting.set()
        assert cancelled.wait(60)

    def cancelling(self):
        cancelled.set()
        cancel(self)

    monkeypatch.setattr(sessions.Session, "train_for_save", train_for_save)
    monkeypatch.setattr(sessions.Session, "cancel", cancelling)
    return waiting, cancelled


def test_a_client_that_leaves_during_a_save_frees_its_slot_at_once(tmp_path, held_rounds):
    """Finding 6 (service): a learning client that asked for a save and left held its
    `--max-sessions` slot until the save's training round ended (about 100 s); every other
    session was refused OVERLOADED meanwhile. The slot is now freed when the stream ends, the
    round is cancelled, and nothing is written."""
    from slamreloc.client import Client
    from slamreloc.service.server import ServeConfig, start_server

    waiting, cancelled = held_rounds
    folder = tmp_path / "learned"
    folder.mkdir()
    running = start_server({}, ServeConfig(port=0, watch_s=0, learned_maps=folder,
                                           max_sessions=1))
    try:
        with Client(running.address, timeout_s=20) as client:
            leaving = client.session(odometry="auto", learn=True)
            saver = threading.Thread(target=lambda: pytest.raises(RemoteError, leaving.save,
                                                                  "left"), daemon=True)
            saver.start()
            assert waiting.wait(30)
            t0 = time.monotonic()
            leaving._updates.cancel()  # the client goes away mid-save
            while True:
                try:
                    with client.session(odometry="auto", learn=True):
                        break
                except RemoteError as err:
                    assert err.kind == "OVERLOADED", err
                    assert time.monotonic() - t0 < 10, "the slot stayed taken"
                    time.sleep(0.1)
            assert cancelled.is_set()
            saver.join(30)
        assert os.listdir(folder) == []  # nothing written for a client that left
    finally:
        running.stop()


def test_stopping_the_server_cancels_a_saves_round(tmp_path, held_rounds):
    """Finding 5 (service): SIGTERM while a save waited for its final training round: the
    process exited 95 s later (the round ran to its end). Stopping now cancels learning
    sessions' rounds; the waiting save is refused and nothing is written."""
    from slamreloc.client import Client
    from slamreloc.service.server import ServeConfig, start_server

    waiting, cancelled = held_rounds
    folder = tmp_path / "learned"
    folder.mkdir()
    running = start_server({}, ServeConfig(port=0, watch_s=0, learned_maps=folder))
    answers: list = []
    client = Client(running.address, timeout_s=20)
    session = client.session(odometry="auto", learn=True)

    def save():
        try:
            answers.append(session.save("late"))
        except RemoteError as err:
            answers.append(err)

    saver = threading.Thread(target=save, daemon=True)
    saver.start()
    assert waiting.wait(30)
    t0 = time.monotonic()
    running.stop()
    assert time.monotonic() - t0 < 20
    saver.join(30)
    client.close()
    assert answers and isinstance(answers[0], RemoteError), answers
    assert os.listdir(folder) == []


class _FakeStub:
    def __init__(self, answers, hang: bool = False):
        self.answers, self.hang = answers, hang

    def Session(self, requests, metadata=None):  # noqa: N802 - the gRPC method's name
        answers, hang = self.answers, self.hang

        class Call:
            cancelled = False

            def __iter__(self):
                yield from answers
                while hang and not self.cancelled:
                    time.sleep(0.01)

            def cancel(self):
                self.cancelled = True

        return Call()


def _session(answers, hang: bool = False, timeout_s: float = 5.0) -> ClientSession:
    client = SimpleNamespace(stub=_FakeStub(answers, hang), metadata=(), timeout_s=timeout_s)
    return ClientSession(client, pb.SessionOpen())


OPENED = pb.SessionUpdate(opened=pb.SessionOpened())


def test_the_client_says_what_a_session_stream_did_wrong():
    """Finding 8 (service): a stream that ended without the final trajectory raised a bare
    StopIteration from `close()`; an error answering a close returned an empty trajectory; a
    non-frame answer to a frame came back as an empty FrameResult; `timeout_s` did not bound a
    session's answers."""
    with pytest.raises(RemoteError, match="ended the session without an answer"):
        _session([OPENED]).close()
    error = pb.SessionUpdate(error=pb.SessionError(kind=pb.OVERLOADED, message="busy"))
    with pytest.raises(RemoteError) as err:
        _session([OPENED, error]).close()
    assert err.value.code == grpc.StatusCode.RESOURCE_EXHAUSTED and "busy" in str(err.value)
    image = np.zeros((16, 16, 3), np.uint8)
    with pytest.raises(RemoteError, match="answered saved where frame was due"):
        _session([OPENED, pb.SessionUpdate(saved=pb.MapSaved())]).send(image)
    t0 = time.monotonic()
    with pytest.raises(RemoteError) as err:
        _session([OPENED], hang=True, timeout_s=0.5).send(image)
    assert err.value.code == grpc.StatusCode.DEADLINE_EXCEEDED
    assert time.monotonic() - t0 < 5


# ---- map files ---------------------------------------------------------------------------------
def _meta_with(small_map, tmp_path, **changes) -> Path:
    doc = json.loads((small_map.root / META).read_text())
    for key, value in changes.items():
        doc[key] = value
    path = tmp_path / META
    path.write_text(json.dumps(doc))
    return path


@pytest.mark.parametrize("bad, needle", [
    ("", "is empty"), ("a\nb", "line break"), ("/etc/passwd", "not a path inside"),
    ("../x", "not a path inside"), ("seq-01/../../x", "not a path inside")])
def test_frame_names_in_a_maps_metadata_keep_the_frame_name_rule(small_map, tmp_path, bad,
                                                                 needle):
    """Finding 3 (CLI): frame names with a line break, empty, absolute or with '..' were
    taken; `export` then wrote a forged line into a TUM names file. A name given twice stays
    (a map updated with frames it holds keeps each observation), as does a space (photos)."""
    names = list(json.loads((small_map.root / META).read_text())["frame_names"])
    _meta_with(small_map, tmp_path, frame_names=[bad, *names[1:]])
    with pytest.raises(InputError, match=f"'frame_names'\\[0\\] .* {needle}"):
        MapMeta.read(tmp_path)
    for kept in (["My Photos/IMG 1.jpg", *names[1:]], [names[0], *names[:-1]]):
        _meta_with(small_map, tmp_path, frame_names=kept)
        assert list(MapMeta.read(tmp_path).frame_names) == kept


def test_a_big_endian_archive_reads_as_the_same_values(small_map, tmp_path):
    """Finding 5 (CLI): a regressor.npz stored big-endian ended in torch's "given numpy
    array has byte order different" naming no file; the values are the same, and read."""
    root = tmp_path / "m"
    shutil.copytree(small_map.root, root)
    with np.load(root / WEIGHTS) as npz:
        arrays = {k: npz[k] for k in npz.files}
    swapped = {k: v.astype(v.dtype.newbyteorder(">")) if v.dtype.kind in "fiu" else v
               for k, v in arrays.items()}
    assert any(not v.dtype.isnative for v in swapped.values())
    np.savez(root / WEIGHTS, **swapped)
    doc = json.loads((root / META).read_text())
    doc["files"][WEIGHTS] = sha256_file(root / WEIGHTS)
    (root / META).write_text(json.dumps(doc))
    theirs, ours = SceneMap.load(root).regressor, small_map.regressor
    for (name, a), (_, b) in zip(theirs.state_dict().items(), ours.state_dict().items()):
        assert np.array_equal(a.numpy(), b.numpy()), name


@pytest.mark.parametrize("root", ["/data/\0x", "/" + "a" * 5000])
def test_a_recorded_root_no_path_can_be_is_refused_naming_the_field(small_map, tmp_path, root):
    """Finding 6 (CLI): `[Errno 36] File name too long` / `embedded null byte`, naming
    neither the file nor the key."""
    doc = json.loads((small_map.root / META).read_text())
    with pytest.raises(InputError, match=r"'dataset.root' is not a path this system can hold"):
        MapMeta.from_json({**doc, "dataset": {"root": root}}, tmp_path / META)


def test_a_maps_camera_keeps_every_camera_rule_naming_the_file(small_map, tmp_path):
    """Finding 7 (CLI): a map camera with its principal point far outside the image ended as
    "invalid camera: ..." naming no file; `--intrinsics` likewise."""
    doc = json.loads((small_map.root / META).read_text())
    path = _meta_with(small_map, tmp_path, camera={**doc["camera"], "cx": 1e6})
    with pytest.raises(InputError) as err:
        MapMeta.read(tmp_path)
    assert str(err.value).startswith(f"{path}: 'camera': cx must lie"), err.value


# ---- cameras and K matrices ----------------------------------------------------------------------
@pytest.mark.parametrize("text", ["pinhole 320 240 262 262 160 120",
                                  "PINHOLE\u00a0320 240 262 262 160 120",
                                  "PINHOLE +320 240 262 262 160 120"])
def test_a_camera_string_keeps_cameras_txts_rule(text):
    """Finding 13 (CLI): a lower-case model, a no-break space as separator and a signed width
    were taken by `--camera` while cameras.txt refuses them."""
    with pytest.raises(InputError):
        Camera.parse(text, "--camera")
    assert Camera.parse("1 PINHOLE 320 240 262 262 160 120\t").width == 320


def test_a_fisheye_focal_length_too_short_is_said_to_be_one():
    """Finding 14 (CLI): f = 10 on a 320 px fisheye was "distortion [0, 0, 0, 0] folds back";
    the problem is a field of view over 180 degrees."""
    with pytest.raises(InputError, match="more than 90 degrees off its axis"):
        Camera.parse("OPENCV_FISHEYE 320 240 10 10 160 120 0 0 0 0")
    assert Camera.parse("OPENCV_FISHEYE 320 240 200 200 160 120 0 0 0 0").model == \
        "OPENCV_FISHEYE"


@pytest.mark.parametrize("k, ok", [
    ([[500, 0, 320], [0, 500, 240], [0, 0, 1]], True),
    ([[500, 0, 320], [0, 500, 240], [0, 0, 2]], False),
    ([[500, 1, 320], [0, 500, 240], [0, 0, 1]], False),
    ([[500, 0, 320], [0, 500, 240], [0, np.nan, 1]], False)])
def test_one_rule_for_k_in_intrinsics_files_and_ros_camera_info(tmp_path, k, ok):
    """Finding 8 (CLI): a ROS CameraInfo whose K had last row 0 0 2 was taken while the same K
    in intrinsics.txt was refused."""
    from slamreloc.datasets.io import read_intrinsics
    from slamreloc.datasets.rosbag import camera_from_info

    assert (k_matrix_problem(k) is None) is ok
    path = tmp_path / "intrinsics.txt"
    path.write_text("\n".join(" ".join(str(v) for v in row) for row in k) + "\n")
    info = SimpleNamespace(k=[float(v) for row in k for v in row], d=[], width=640,
                           height=480, distortion_model="plumb_bob")
    if ok:
        read_intrinsics(path)
        assert camera_from_info(info, (640, 480), "bag").fx == 500
        return
    with pytest.raises(InputError, match="intrinsics"):  # NaN: the number rule's first
        read_intrinsics(path)
    with pytest.raises(InputError, match="K must"):
        camera_from_info(info, (640, 480), "bag")


# ---- COLMAP and TUM datasets -------------------------------------------------------------------
def test_colmap_text_models_with_a_byte_order_mark_and_special_model_files(tmp_path):
    """Findings 9 and 15 (CLI): images.txt starting with a byte-order mark ended in pycolmap's
    C++ `Check failed`; a cameras.bin that is a named pipe was "images.bin without
    cameras.bin"."""
    from slamreloc.datasets.colmap import find_model
    from slamreloc.datasets.colmap_check import check_model

    text = tmp_path / "text"
    text.mkdir()
    (text / "cameras.txt").write_text("1 PINHOLE 320 240 262 262 160 120\n")
    (text / "images.txt").write_bytes(b"\xef\xbb\xbf# a comment\n")
    with pytest.raises(InputError, match="byte-order mark"):
        check_model(text, "txt")
    binary = tmp_path / "bin"
    binary.mkdir()
    (binary / "images.bin").write_bytes(b"\0" * 8)
    os.mkfifo(binary / "cameras.bin")
    with pytest.raises(InputError, match=r"cameras.bin: COLMAP model is not a regular file "
                                         r"\(a named pipe\)"):
        find_model(binary, (".",))


def test_a_tum_datasets_bad_intrinsics_are_named_once(tmp_path):
    """Finding 16 (CLI): the path of intrinsics.txt was printed twice."""
    import cv2

    from slamreloc.datasets import load_dataset

    (tmp_path / "rgb").mkdir()
    cv2.imwrite(str(tmp_path / "rgb" / "a.png"), np.zeros((48, 64, 3), np.uint8))
    (tmp_path / "rgb.txt").write_text("0.000000 rgb/a.png\n")
    (tmp_path / "intrinsics.txt").write_text("525 0 319.5\n0 525 239.5\n0 0 2\n")
    with pytest.raises(InputError) as err:
        load_dataset(tmp_path).frames("all")
    assert str(err.value).count("intrinsics.txt") == 1, err.value


# ---- sfm outputs ---------------------------------------------------------------------------------
def test_a_second_sfm_into_the_same_folder_fails_at_once(scene_dir, tmp_path):
    """Finding 10 (CLI): two `sfm --out D` at once: the second did all its work, then
    `[Errno 39] Directory not empty`. It now fails at its start, naming the other writer;
    an earlier output is said to be one sfm never writes over (finding 11)."""
    photos = tmp_path / "photos"
    photos.mkdir()
    for i, image in enumerate(sorted(scene_dir.glob("seq-01/*.color.png"))[:3]):
        (photos / f"p{i}.png").write_bytes(image.read_bytes())
    out = tmp_path / "out"
    holder = _holding(out)
    try:
        one_line_exit_2(["sfm", str(photos), "--out", str(out)],
                        f"another process (pid {holder.pid}) is writing")
    finally:
        holder.kill()
        holder.wait()
    out.mkdir()
    (out / "sfm.json").write_text("{}")
    one_line_exit_2(["sfm", str(photos), "--out", str(out)], "writes a new or an empty "
                    "folder only")


# ---- the seventh round ---------------------------------------------------------------------------
def _holding(out: Path) -> subprocess.Popen:
    """Another process holding `out`'s write lock (a lock is re-entrant within one)."""
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time\nfrom slamreloc.io.folder_lock import "
         "folder_write_lock\nfrom slamreloc.sfm import SFM_DEBRIS\n"
         "with folder_write_lock(sys.argv[1], 'this dataset', SFM_DEBRIS):\n    print('held', "
         "flush=True)\n    time.sleep(120)", str(out)], stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "held"
    return holder


def test_no_output_is_written_where_another_process_is_writing_a_map(small_map, tmp_path):
    """Round 7, finding 1: `export --tum mz3` while `slam --out mz3` ran wrote a file there;
    the session then failed and its work was lost. An output under a live writer's lock is
    refused at once."""
    out = tmp_path / "mz3"
    holder = _holding(out)
    try:
        for option in ("--tum", "--ply"):
            one_line_exit_2(["export", str(small_map.root), option, str(out)],
                            f"another process (pid {holder.pid}) is writing this dataset;")
    finally:
        holder.kill()
        holder.wait()
    assert not out.exists()


def test_a_reference_that_fits_no_similarity_is_refused():
    """Round 7, findings 2 and 3: a reference whose cameras all lie at one point gave scale
    0 and a zero matrix; a mirrored one a negative scale; both were scored."""
    from slamreloc.geometry import Rigid3
    from slamreloc.localize.evaluate import align_to_reference

    rng = np.random.default_rng(0)
    centres = rng.normal(size=(6, 3))
    names = [f"f{i}" for i in range(6)]
    ours = {n: Rigid3(np.eye(3), c) for n, c in zip(names, centres)}
    assert align_to_reference(ours, ours)[0].scale == pytest.approx(1.0)
    collapsed = {n: Rigid3(np.eye(3), np.zeros(3)) for n in names}
    with pytest.raises(InputError, match="all lie at one point"):
        align_to_reference(ours, collapsed, "ref.txt")
    mirrored = {n: Rigid3(np.eye(3), -c) for n, c in zip(names, centres)}
    with pytest.raises(InputError, match="the fitted similarity has scale"):
        align_to_reference(ours, mirrored, "ref.txt")


def test_topics_are_given_once_and_for_bags_only(scene_dir):
    """Round 7, findings 4 and 5: `--topic pose=/a --topic pose=/b` kept one silently, and
    `--topic` on a dataset that is no bag was ignored."""
    from slamreloc.datasets import load_dataset
    from slamreloc.datasets.rosbag import BagTopics, parse_topics, set_topics

    with pytest.raises(InputError, match="`topic` pose is given twice"):
        parse_topics(["pose=/pose", "pose=/pose2"])
    set_topics(parse_topics(["pose=/pose"]))
    try:
        with pytest.raises(InputError, match="this dataset is not a bag"):
            load_dataset(scene_dir)
    finally:
        set_topics(BagTopics())
    load_dataset(scene_dir)


def test_colmap_export_refuses_names_its_text_model_cannot_carry(small_map, tmp_path):
    """Round 7, finding 9: frame names with a blank, or repeated, were written into a COLMAP
    model that slamreloc's own reader (and COLMAP's) then refused."""
    root = tmp_path / "m"
    shutil.copytree(small_map.root, root)
    doc = json.loads((root / META).read_text())
    doc["frame_names"][0] = "My Photos/IMG 1.jpg"
    (root / META).write_text(json.dumps(doc))
    out = tmp_path / "cm"
    one_line_exit_2(["export", str(root), "--colmap", str(out)], "holds a blank")
    assert not out.exists()
    code, err = run_cli(["export", str(root), "--tum", str(tmp_path / "t.tum")])
    assert code == 0, err


def test_a_map_file_larger_than_any_map_is_refused_before_it_is_read(small_map, tmp_path):
    """Round 7 (service), finding 1: a 30 GB sparse regressor.npz was hashed whole before its
    checksum was compared; ReloadMap answered after a minute and a stop waited for it."""
    root = tmp_path / "m"
    shutil.copytree(small_map.root, root)
    with open(root / WEIGHTS, "r+b") as f:
        f.truncate(17 << 30)  # sparse: no disk used
    t0 = time.monotonic()
    with pytest.raises(InputError, match="more than a map's"):
        SceneMap.load(root)
    assert time.monotonic() - t0 < 10


def test_a_pem_file_with_a_byte_order_mark_is_refused_naming_the_option(tmp_path):
    """Round 7 (service), finding 3: a certificate starting with a byte-order mark passed
    the check and was refused by gRPC in three log lines blaming the port."""
    from slamreloc.io.pem import pem_problem

    assert "byte-order mark" in pem_problem(b"\xef\xbb\xbf-----BEGIN CERTIFICATE-----\n",
                                            "certificate")


@pytest.mark.parametrize("args", [None, 5, {"maps": {1: "/m"}}])
def test_a_ray_config_that_is_no_mapping_is_refused(args):
    """Round 7 (service), finding 6: `build_app(None)` was a bare TypeError; a map name 1 was
    served as "1"."""
    pytest.importorskip("ray.serve")
    from slamreloc.service.ray_app import build_app

    with pytest.raises(InputError, match="args"):
        build_app(args)
