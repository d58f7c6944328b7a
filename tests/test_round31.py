"""Attack round 31 and the leftovers of round 30: the C++ client's error lines follow the CLI's
line rule (`slamreloc.errors.terminal_line`)."""

from __future__ import annotations

import os
import subprocess

import pytest

from slamreloc.errors import terminal_line
from tests.test_cpp_client import MISSING

needs_cpp = pytest.mark.skipif(bool(MISSING), reason=f"the C++ client needs {', '.join(MISSING)}")


@needs_cpp
@pytest.mark.parametrize("name", [
    b"a\x1b[31mred\nline", b"tab\there\rcr", b"bad\xfe\xffbytes", "zero\u200bwidth".encode(),
    "private\U000f0000use".encode(), b"x" * 2000, "caf\u00e9 \u4e2d\u6587".encode()])
def test_the_cpp_client_s_error_lines_follow_the_cli_s_rule(client_binary, tmp_path, name):
    """A sequence folder whose name holds control characters, bytes that are not UTF-8,
    characters Python does not print, or a 2000-character run: the C++ client's one error
    line is the Python CLI's `terminal_line` of the same message, byte for byte."""
    missing = os.fsencode(tmp_path) + b"/" + name
    done = subprocess.run([str(client_binary), "--server", "127.0.0.1:1", missing],
                          capture_output=True, timeout=60, check=False)
    assert done.returncode == 2
    message = os.fsdecode(missing) + ": no such folder"
    assert done.stderr == f"error: {terminal_line(message)}\n".encode(), done.stderr


# ---- round 31 (A): the service ------------------------------------------------------------
import shutil  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import grpc  # noqa: E402
import numpy as np  # noqa: E402

from slamreloc.client import Client, RemoteError, image_msg  # noqa: E402
from slamreloc.proto import relocalizer_pb2 as pb  # noqa: E402
from slamreloc.proto import relocalizer_pb2_grpc as pb_grpc  # noqa: E402
from slamreloc.service.server import ServeConfig, start_server  # noqa: E402
from tests.fuzzing import run_cli  # noqa: E402
from tests.test_fuzz_inputs import _tiny_map  # noqa: E402


@pytest.fixture(scope="module")
def tiny_map(tmp_path_factory) -> Path:
    return _tiny_map(tmp_path_factory.mktemp("round31") / "map")


def _tree(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file()}


@pytest.mark.parametrize("leftover", [".a.tmp-3999999", ".a.old-3999999"])
def test_a_map_named_as_a_writer_s_temporary_is_refused_before_any_map_is_read(
        tiny_map, tmp_path, leftover):
    """N1: `serve A .A.tmp-PID`: reading A cleaned its killed writer's leftovers, deleting the
    second map the command was given; with --learned-maps DIR the start-up clean-up of DIR
    deleted (or renamed) a map served from it. Both are refused before anything is read."""
    maps = tmp_path / "maps"
    shutil.copytree(tiny_map, maps / "a")
    shutil.copytree(tiny_map, maps / leftover)
    before = _tree(maps)
    for args in ([str(maps / "a"), str(maps / leftover), "--name", "a", "--name", "b"],
                 [str(maps / leftover), "--name", "q", "--learned-maps", str(maps)]):
        code, err = run_cli(["serve", *args, "--port", "0"])
        assert code == 2 and "named as a writer's temporary" in err and leftover in err, err
        assert _tree(maps) == before


def test_one_folder_is_served_under_one_name(tiny_map, tmp_path):
    """N3: one folder under two names (the same path, another spelling, a link) is refused at
    start-up, by the reload's rule: otherwise neither name could be saved by a session."""
    folder = tmp_path / "m"
    shutil.copytree(tiny_map, folder)
    (tmp_path / "link").symlink_to(folder)
    for second in (folder, tmp_path / "m" / ".." / "m", tmp_path / "link"):
        code, err = run_cli(["serve", str(folder), str(second), "--name", "a", "--name", "b",
                             "--port", "0"])
        assert code == 2 and "serve a folder under one name" in err, err


def _png(width: int, height: int, seed: int = 0) -> bytes:
    rng = np.random.default_rng(seed)
    return cv2.imencode(".png", rng.integers(0, 255, (height, width, 3), np.uint8))[1].tobytes()


def _session_updates(tiny_map: Path, open_units: float,
                     depths: list[tuple[int, bytes, float]]) -> list:
    """The updates of one session on a server of `tiny_map`, opened with `open_units` depth
    units a metre, sent one 64x48 frame per (encoding, data, units_per_metre) of `depths`."""
    running = start_server({"m": tiny_map}, ServeConfig(port=0, watch_s=0))
    try:
        channel = grpc.insecure_channel(running.address)
        frames = []
        for encoding, data, units in depths:
            frame = pb.SessionFrame(image=image_msg(_png(64, 48)), timestamp=len(frames))
            frame.depth.CopyFrom(pb.Depth(encoding=encoding, width=64, height=48, data=data,
                                          units_per_metre=units))
            frames.append(pb.SessionRequest(frame=frame))
        opening = pb.SessionRequest(open=pb.SessionOpen(map="m", odometry="auto",
                                                        depth_units_per_metre=open_units))
        updates = list(pb_grpc.RelocalizerStub(channel).Session(iter([opening, *frames]),
                                                                timeout=120))
        channel.close()
    finally:
        running.stop()
    return updates


def test_a_frame_s_depth_units_must_match_the_session_s(tiny_map):
    """N2: a frame's Depth.units_per_metre silently overrode SessionOpen's: a session opened at
    5000 units a metre ran as one at 1000. A frame's own value must now equal the session's."""
    depth = np.full((48, 64), 5000, "<u2").tobytes()
    updates = _session_updates(tiny_map, 5000, [(pb.Depth.UINT16, depth, units)
                                                for units in (1000.0, 5000.0, 0.0)])
    errors = [u.error for u in updates if u.HasField("error")]
    assert len(errors) == 1 and errors[0].kind == pb.BAD_DEPTH, updates
    assert "units_per_metre 1000 differs from SessionOpen.depth_units_per_metre 5000" in \
        errors[0].message
    assert sum(u.HasField("frame") for u in updates) == 2  # the same units, or none: taken


def test_large_requests_held_at_once_are_bounded(tiny_map):
    """N4: many large requests at once, each within --max-request-mb, took the server past its
    memory. The bytes of the large requests it holds are bounded (`max_held_bytes`): with one
    large Localize waiting for the worker, a second is refused OVERLOADED at once, a small call
    is still answered, and the first is answered when the worker is free."""
    # at most one request of up to 1 MiB held at once (the bound is at least one request)
    config = ServeConfig(port=0, watch_s=0, max_request_bytes=1 << 20, max_held_bytes=1 << 16)
    running = start_server({"m": tiny_map}, config)
    big = [_png(640, 480, seed) for seed in (1, 2)]  # each ~0.9 MiB, over 64 KiB
    assert all((1 << 19) < len(b) < (1 << 20) - 4096 for b in big)
    first: dict = {}
    try:
        client = Client(running.address)
        running.service.compute.acquire()  # the one worker busy: the first call waits for it
        try:
            waiting = threading.Thread(target=lambda: first.update(
                r=client.localize(big[0], camera="PINHOLE 640 480 500 500 320 240", map="m")))
            waiting.start()
            deadline = time.monotonic() + 60
            while running.service.held_bytes == 0 and time.monotonic() < deadline:
                time.sleep(0.01)
            assert running.service.held_bytes >= len(big[0])
            with pytest.raises(RemoteError) as refused:
                client.localize(big[1], camera="PINHOLE 640 480 500 500 320 240", map="m")
            assert refused.value.kind == "OVERLOADED" and "MiB of requests" in str(refused.value)
            assert client.health().serving
        finally:
            running.service.compute.release()
        waiting.join(120)
        assert "r" in first and running.service.held_bytes == 0
        client.close()
    finally:
        running.stop()


# ---- round 31 (B): what a map records stays an input ----------------------------------------
from slamreloc.datasets.poses import read_poses  # noqa: E402
from slamreloc.errors import InputError  # noqa: E402
from slamreloc.map.scene_map import SceneMap  # noqa: E402


@pytest.fixture(scope="module")
def tiny_scene(scene_dir, tmp_path_factory) -> Path:
    return six_frames(scene_dir, tmp_path_factory.mktemp("round31_scene") / "ds")


def six_frames(scene_dir: Path, out: Path) -> Path:
    """The first 6 frames of the small scene's map sequence, copied into the dataset `out`:
    a dataset mapped in seconds."""
    (out / "seq-01").mkdir(parents=True)
    for name in ("TrainSplit.txt", "intrinsics.txt", "scene.json"):
        shutil.copy(scene_dir / name, out / name)
    for i in range(6):
        for f in (scene_dir / "seq-01").glob(f"frame-{i:06d}.*"):
            shutil.copy(f, out / "seq-01" / f.name)
    return out


def _digest(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file()}


def _tiny_map_of(dataset: Path, out: Path, *extra: str) -> Path:
    code, err = run_cli(["map", str(dataset), "--out", str(out), "--arch", "tiny",
                         "--epochs", "1", *extra])
    assert code == 0, err
    return out


def test_a_pose_file_stays_an_input_of_the_maps_that_extend_its_map(tiny_scene, tmp_path):
    """P1: a map posed from `--poses F`, extended by a SLAM session (`slam --map MP --out S1`),
    handed S1 a record without F: `export S1 --tum F` overwrote MP's pose file. The extended
    map records the pose files of the frames it took over, and every command on it reads
    them only."""
    from slamreloc.slam.live_map import LiveMap

    ds = tiny_scene
    first = _tiny_map_of(ds, tmp_path / "m0")
    poses = tmp_path / "poses" / "poses.txt"
    poses.parent.mkdir()
    assert run_cli(["export", str(first), "--tum", str(poses)])[0] == 0
    mp = _tiny_map_of(ds, tmp_path / "mp", "--poses", str(poses))
    s1 = LiveMap(prior=SceneMap.load(mp)).save(tmp_path / "s1")  # slam --map MP --out S1's save
    assert SceneMap.load(s1).info.earlier_pose_files == [str(poses.resolve())]
    before = _digest(poses.parent)
    code, err = run_cli(["export", str(s1), "--tum", str(poses)])
    assert code == 2 and "a pose file of the map's earlier sessions" in err, err
    assert _digest(poses.parent) == before


def test_outputs_named_through_a_linked_sequence_folder_are_refused(tiny_scene, tmp_path):
    """P3: a dataset whose sequence folder is a symbolic link (kept on another disk): outputs
    named inside the dataset through it, or inside the folder it links to, were written among
    its frames. Both are refused as for a plain folder."""
    real = tmp_path / "real"
    shutil.copytree(tiny_scene, real)
    ds = tmp_path / "ds"
    ds.mkdir()
    for entry in real.iterdir():  # the sequences linked in, the rest copied
        if entry.is_dir():
            (ds / entry.name).symlink_to(entry)
        else:
            shutil.copy(entry, ds / entry.name)
    m = _tiny_map_of(ds, tmp_path / "m")
    before = _digest(real)
    for argv in (["map", str(ds), "--out", str(ds / "seq-01" / "mapin"), "--arch", "tiny",
                  "--epochs", "1"],
                 ["export", str(m), "--tum", str(ds / "seq-01" / "x.txt")],
                 ["export", str(m), "--colmap", str(real / "seq-01" / "model")]):
        code, err = run_cli(argv)
        assert code == 2 and "which this command only reads" in err, (argv, err)
    assert _digest(real) == before


@pytest.mark.parametrize("gap", ["0.000000000", "0.000000001", "0.0000005"])
def test_two_poses_of_one_instant_are_refused_whatever_their_stamps(tmp_path, gap):
    """P4: two different poses at one stamp were refused, at stamps 1 ns apart taken (the
    frame got the nearer, by nanoseconds). Stamps within a microsecond are one instant."""
    path = tmp_path / "poses.txt"
    path.write_text("0 0 0 0 0 0 0 1\n0.033333333 0.01 0 0 0 0 0 1\n"
                    f"{gap} 1 0 0 0 0 0 1\n")
    with pytest.raises(InputError, match=r"poses.txt:3: timestamp .* line 1 with a different "
                                         r"pose"):
        read_poses(path)
    path.write_text(f"0 0 0 0 0 0 0 1\n{gap} 0 0 0 0 0 0 1\n0.033333333 0.01 0 0 0 0 0 1\n")
    assert len(read_poses(path)) == 2  # the same pose twice: read once


# ---- round 32: around round 31's fixes ------------------------------------------------------
import dataclasses  # noqa: E402

from slamreloc.datasets.rosbag import load_rosbag  # noqa: E402
from slamreloc.geometry import Rigid3  # noqa: E402
from tests.rosbag_support import (  # noqa: E402,F401 - automatic_topics: a fixture
    INFO_TOPIC,
    Messages,
    automatic_topics,
    first_test_frames,
    frame_stamp,
    write_bag,
)


def test_outputs_into_a_folder_a_deeper_link_of_an_input_leads_to_are_refused(tiny_scene,
                                                                              tmp_path):
    """Q1: round 31 looked at links directly inside an input only: a dataset whose frame
    files are links into a store of images took a map written into that store."""
    store, ds = tmp_path / "store", tmp_path / "ds"
    shutil.copytree(tiny_scene, ds)
    store.mkdir()
    for f in sorted((ds / "seq-01").glob("*.color.png")):
        f.rename(store / f.name)
        f.symlink_to(store / f.name)
    before = _digest(store)
    code, err = run_cli(["map", str(ds), "--out", str(store / "mapin"), "--arch", "tiny",
                         "--epochs", "1"])
    assert code == 2 and "linked folder" in err and "which this command only reads" in err, err
    assert _digest(store) == before


@pytest.fixture(scope="module")
def bag_scene(scene_dir):
    return first_test_frames(scene_dir, 4)


def test_an_uncalibrated_camera_info_is_said_to_be_one(bag_scene, tmp_path):
    """Q2: ROS's uncalibrated CameraInfo (K all zero) was refused as "(no skew)"."""
    dataset, frames = bag_scene
    msgs = Messages(2)
    info = [dataclasses.replace(msgs.camera_info(frame_stamp(f), f.camera), k=np.zeros(9))
            for f in frames]
    bag = write_bag(dataset, frames, tmp_path / "bag", camera_info=False,
                    extra={INFO_TOPIC: info})
    with pytest.raises(InputError, match="K is all zero, which says the camera is not "
                                         "calibrated"):
        load_rosbag(bag)


def test_a_bag_folder_s_metadata_that_is_no_file_is_named(bag_scene, tmp_path):
    """Q3: a ROS 2 bag folder whose metadata.yaml is a named pipe was "not a dataset"."""
    dataset, frames = bag_scene
    bag = write_bag(dataset, frames, tmp_path / "bag")
    (bag / "metadata.yaml").unlink()
    os.mkfifo(bag / "metadata.yaml")
    code, err = run_cli(["sfm", str(bag), "--out", str(tmp_path / "out")])
    assert code == 2 and "metadata.yaml: ROS bag metadata is not a regular file (a named " \
        "pipe)" in err, err


def test_two_poses_of_one_instant_in_a_bag_are_refused(bag_scene, tmp_path):
    """Q4: a pose topic giving frame 0 two poses 1 m apart, 0.8 microseconds apart, was read
    as their midpoint; a TUM file with the same rows is refused. One rule: refused."""
    dataset, frames = bag_scene
    msgs = Messages(2)
    t0 = frame_stamp(frames[0])
    moved = Rigid3(np.eye(3), np.array([1.0, 0, 0])) @ frames[0].world_from_cam
    poses = [msgs.pose_stamped(t0 - 4e-7, "map", frames[0].world_from_cam),
             msgs.pose_stamped(t0 + 4e-7, "map", moved)]
    poses += [msgs.pose_stamped(frame_stamp(f), "map", f.world_from_cam) for f in frames[1:]]
    bag = write_bag(dataset, frames, tmp_path / "bag", poses=None, extra={"/pose": poses})
    with pytest.raises(InputError, match="one instant .*carry different poses"):
        load_rosbag(bag)


def test_a_session_s_depth_units_are_compared_as_numbers_and_not_for_metres(tiny_map):
    """Q5: 1 / float32(0.001) units (a RealSense depth scale) were refused against 1000 as
    "1000 differs from 1000"; FLOAT32_METRES depth with units given was refused or taken by
    the session's units. Units equal to within a millionth are the same; metres take none."""
    mm = np.full((48, 64), 2000, "<u2").tobytes()
    metres = np.full((48, 64), 2.0, "<f4").tobytes()
    updates = _session_updates(tiny_map, 1000, [
        (pb.Depth.UINT16, mm, 1 / float(np.float32(0.001))),
        (pb.Depth.FLOAT32_METRES, metres, 1000.0), (pb.Depth.FLOAT32_METRES, metres, 0)])
    answers = [u for u in updates if u.HasField("frame") or u.HasField("error")]
    assert [u.HasField("frame") for u in answers] == [True, False, True], updates
    assert "given with FLOAT32_METRES depth, which is in metres" in answers[1].error.message


def test_learned_maps_on_a_second_name_of_a_served_map_s_folder_are_refused(tiny_map,
                                                                          tmp_path):
    """Q7: --learned-maps given as a bind mount of the served map's folder was taken (the
    plain path is refused), and a save wrote into the served map."""
    folder, mount = tmp_path / "lm", tmp_path / "mnt"
    shutil.copytree(tiny_map, folder / "q")
    mount.mkdir()
    if subprocess.run(["mount", "--bind", str(folder), str(mount)], capture_output=True,
                      check=False).returncode != 0:
        pytest.skip("bind mounts need root (mount --bind)")
    try:
        code, err = run_cli(["serve", str(folder / "q"), "--learned-maps", str(mount / "q"),
                             "--port", "0"])
    finally:
        subprocess.run(["umount", str(mount)], check=False)
    assert code == 2 and "--learned-maps is the folder of the served map" in err, err
