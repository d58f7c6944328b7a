"""`slamreloc serve` and `slamreloc.client`: the same answers as the in-process code, typed
refusals, tokens, sessions equal to `slamreloc slam`, map reload under load."""

from __future__ import annotations

import json
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

import cv2
import grpc
import pytest
import torch

from slamreloc.client import Client, RemoteError, confirmed_frames, frame_poses
from slamreloc.datasets import load_dataset
from slamreloc.geometry import Rigid3, write_tum_trajectory
from slamreloc.io.images import decode_rgb, read_image
from slamreloc.localize.localizer import RegressorLocalizer
from slamreloc.map.format import SURFACE
from slamreloc.map.write import save_map
from slamreloc.proto.messages import transform_msg
from slamreloc.map.scene_map import SceneMap
from slamreloc.service.server import ServeConfig, start_server
from slamreloc.slam.feed import read_frames
from slamreloc.slam.report import kidnap_stats
from slamreloc.slam.run import kidnap_schedule
from tests.fuzzing import run_cli, run_cli_output

TOKEN = "a-token-of-sixteen-chars"


@pytest.fixture(scope="module")
def server(small_map):
    running = start_server({"small": small_map.root}, ServeConfig(port=0, watch_s=0))
    yield running
    running.stop()


@pytest.fixture(scope="module")
def queries(scene_dir):
    """seq-02's first frames as JPEG bytes (what a phone or a robot would send)."""
    frames = load_dataset(scene_dir).frames("seq-02")[:6]
    return [cv2.imencode(".jpg", cv2.imread(str(f.image_path)))[1].tobytes() for f in frames]


def _in_process(scene_map: SceneMap, data: bytes):
    image = decode_rgb(data, "query")
    h, w = image.shape[:2]
    return RegressorLocalizer(scene_map).localize(image, scene_map.camera.scaled_to(w, h))


def test_localize_answers_as_the_in_process_localizer(server, small_map, queries):
    with Client(server.address) as client:
        for data in queries:
            answer = client.localize(data, map="small")
            local = _in_process(small_map, data).estimate
            assert answer.localized and answer.reason == "LOCALIZED"
            # bit for bit: the same computation on the same bytes
            assert answer.response.world_from_cam == transform_msg(local.world_from_cam)
            r = answer.response
            assert (r.num_inliers, r.num_correspondences) == (local.num_inliers,
                                                              local.num_correspondences)
            assert r.timings.total_ms >= r.timings.features_ms > 0 and r.map_version
        # a raw RGB array answers as its PNG does; "" names the only map
        image = decode_rgb(queries[0], "q")
        png = cv2.imencode(".png", cv2.cvtColor(image, cv2.COLOR_RGB2BGR))[1].tobytes()
        raw, encoded = client.localize(image), client.localize(png)
        assert raw.response.world_from_cam == encoded.response.world_from_cam


def test_query_camera_and_prior(server, small_map, queries):
    cam = small_map.camera
    with Client(server.address) as client:
        plain = client.localize(queries[1])
        # the map's camera given explicitly, as a pinhole and as a COLMAP string
        assert client.localize(queries[1], camera=cam).response.world_from_cam == \
            plain.response.world_from_cam
        assert client.localize(queries[1], camera=cam.colmap_string()).localized
        truth = plain.world_from_cam
        near = client.localize(queries[1], world_from_cam_prior=truth)
        assert near.localized
        far = client.localize(queries[1], world_from_cam_prior=Rigid3(
            truth.rotation, truth.translation + [2.0, 0, 0]))
        assert not far.localized and far.reason == "FAR_FROM_PRIOR" and far.world_from_cam


@pytest.mark.parametrize("case, kind, code", [
    ("unknown map", "UNKNOWN_MAP", grpc.StatusCode.NOT_FOUND),
    ("corrupt image", "BAD_IMAGE", grpc.StatusCode.INVALID_ARGUMENT),
    ("camera of another size", "BAD_CAMERA", grpc.StatusCode.INVALID_ARGUMENT),
])
def test_refusals_are_typed_and_the_server_carries_on(server, small_map, queries, case, kind,
                                                      code):
    cam = small_map.camera
    with Client(server.address) as client:
        request = {
            "unknown map": {"image": queries[0], "map": "kitchen"},
            "corrupt image": {"image": queries[0][: len(queries[0]) // 2]},
            "camera of another size": {"image": queries[0], "camera": cam.scaled_to(64, 48)},
        }[case]
        with pytest.raises(RemoteError) as err:
            client.localize(**request)
        assert (err.value.kind, err.value.code) == (kind, code)
        assert client.localize(queries[0]).localized


def test_request_size_and_token(small_map, queries, tmp_path):
    running = start_server({"small": small_map.root},
                           ServeConfig(port=0, watch_s=0, token=TOKEN,
                                       max_request_bytes=1 << 20))
    try:
        with Client(running.address) as anonymous:
            with pytest.raises(RemoteError) as err:
                anonymous.localize(queries[0])
            assert err.value.kind == "UNAUTHENTICATED"
        with Client(running.address, token=TOKEN) as client:
            assert client.localize(queries[0]).localized
            with pytest.raises(RemoteError) as err:  # refused by gRPC before it is read
                client.localize(b"\xff" * (2 << 20))
            assert err.value.code == grpc.StatusCode.RESOURCE_EXHAUSTED
            assert client.health().serving
    finally:
        running.stop()
    # a non-loopback address without a token does not start
    status, err = run_cli(["serve", str(small_map.root), "--host", "0.0.0.0"])
    assert status == 2 and err.count("\n") == 1 and "token" in err


def test_serve_command_answers_and_stops(small_map, queries):
    proc = subprocess.Popen([sys.executable, "-m", "slamreloc.cli", "serve",
                             str(small_map.root), "--name", "kitchen", "--port", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        assert "listening on 127.0.0.1:" in line, proc.stderr.read()
        address = line.split()[2]
        with Client(address) as client:
            assert [m.name for m in client.list_maps()] == ["kitchen"]
            assert client.localize(queries[0], map="kitchen").localized
    finally:
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 0


def _kidnap_frames(kidnap_scene, every=30, skip=10):
    dataset = load_dataset(kidnap_scene)
    frames = dataset.frames("seq-03")
    kept, jumps = kidnap_schedule(len(frames), every, skip)
    return dataset, [frames[i] for i in kept], jumps


def _stream(client, dataset, frames, **opening):
    """Stream frames through a session; (per-frame results, the closing message)."""
    results = []
    with client.session(**opening) as session:
        for frame, inp in zip(frames, read_frames(dataset, frames,
                                                  depth=opening["odometry"] != "client")):
            odom = frame.world_from_cam if opening["odometry"] == "client" else None
            results.append(session.send(inp.image, camera=inp.camera, depth=inp.depth,
                                        odometry_world_from_cam=odom,
                                        timestamp=inp.timestamp))
        closed = session.close()
    return results, closed


def _session_kidnap_stats(results, frames, jumps):
    return kidnap_stats(confirmed_frames(results), frame_poses(results),
                        [f.world_from_cam for f in frames], jumps)


@pytest.mark.parametrize("odometry", ["auto", "client"])
def test_session_recovers_as_slam_does(server, small_map, kidnap_scene, tmp_path, odometry):
    """The session's events give the recovery numbers `slamreloc slam` reports on the same
    frames: with the server's odometry on streamed depth, and with the client's own odometry
    (here: the frames' poses, given to `slam` as a trajectory file)."""
    dataset, frames, jumps = _kidnap_frames(kidnap_scene)
    args = ["slam", str(kidnap_scene), "--map", str(small_map.root), "--split", "seq-03",
            "--kidnap-every", "30", "--kidnap-skip", "10", "--report", str(tmp_path / "r.json")]
    if odometry == "client":
        traj = tmp_path / "odometry.txt"
        all_frames = dataset.frames("seq-03")
        write_tum_trajectory(traj, [f.timestamp for f in all_frames],
                             [f.world_from_cam for f in all_frames])
        args += ["--odometry", str(traj)]
    status, err = run_cli(args)
    assert status == 0, err
    report = json.loads((tmp_path / "r.json").read_text())
    with Client(server.address) as client:
        results, closed = _stream(client, dataset, frames, odometry=odometry)
    ours = _session_kidnap_stats(results, frames, jumps)
    assert [r.index for r in results] == list(range(len(frames)))
    assert report["n_recovered"] >= 1  # the comparison covers a recovery
    for key in ("n_kidnaps", "n_recovered", "frames_to_recover"):
        assert ours[key] == report[key], key
    for key in ("recovered_median_error_m", "recovered_median_error_deg"):
        assert ours[key] == pytest.approx(report[key], abs=2e-3)  # the report rounds
    stats = json.loads(closed.stats_json)
    assert stats["n_anchors"] == report["relocalization"]["n_anchors"]
    assert len(closed.world_from_cam) == len(frames)


def test_sessions_are_freed_and_bounded(small_map, scene_dir):
    running = start_server({"small": small_map.root},
                           ServeConfig(port=0, watch_s=0, max_sessions=1))
    image = read_image(load_dataset(scene_dir).frames("seq-02")[0].image_path)
    try:
        with Client(running.address) as client:
            session = client.session(odometry="client")
            session.send(image, odometry_world_from_cam=Rigid3.identity())
            with pytest.raises(RemoteError) as err:  # a bad frame: refused, session goes on
                session.send(image)
            assert err.value.kind == "BAD_POSE"
            assert session.send(image, odometry_world_from_cam=Rigid3.identity()).index == 1
            with pytest.raises(RemoteError) as err:
                client.session(odometry="client")
            assert err.value.kind == "OVERLOADED"
            session._updates.cancel()  # the client goes away without closing
            deadline = time.time() + 10
            while client.health().num_sessions and time.time() < deadline:
                time.sleep(0.05)
            assert client.health().num_sessions == 0
            with client.session(odometry="client") as again:
                assert again.opened.session_id != session.opened.session_id
    finally:
        running.stop()


def test_map_replaced_under_load_fails_no_request(small_map, queries, tmp_path):
    served = tmp_path / "served"
    shutil.copytree(small_map.root, served)
    threads_before = (torch.get_num_threads(), cv2.getNumThreads())
    running = start_server({"live": served}, ServeConfig(port=0, watch_s=0.1, workers=2))
    assert cv2.getNumThreads() == 1  # each worker's OpenCV runs on its own core
    answers, failures, stop = [], [], threading.Event()

    def hammer():
        with Client(running.address) as client:
            while not stop.is_set():
                try:
                    answers.append(client.localize(queries[0]).response.map_version)
                except RemoteError as err:
                    failures.append(err)

    threads = [threading.Thread(target=hammer) for _ in range(3)]
    for t in threads:
        t.start()
    try:
        versions = []
        with Client(running.address) as client:
            versions.append(client.list_maps()[0].version)
            scene_map = SceneMap.load(served)
            for i in range(2):  # the map-update path: a new map written over the served one
                meta = replace(scene_map.info, timings_s={"update": float(i)})
                save_map(served, meta, scene_map.regressor, scene_map.database,
                         extra={SURFACE: scene_map.surface.to_arrays()})
                deadline = time.time() + 20
                while client.list_maps()[0].version == versions[-1] and time.time() < deadline:
                    time.sleep(0.05)
                versions.append(client.list_maps()[0].version)
            reloaded = client.reload_map("live")  # by request: same content, no change
            assert not reloaded.changed and reloaded.map.version == versions[-1]
        time.sleep(0.5)
    finally:
        stop.set()
        for t in threads:
            t.join()
        running.stop()
    # the thread counts are process-wide: stopping gives the embedding process its own back
    assert (torch.get_num_threads(), cv2.getNumThreads()) == threads_before
    assert len(set(versions)) == 3, versions  # each replacement was picked up
    assert not failures and len(answers) > 10
    assert set(answers) <= set(versions) and answers[-1] == versions[-1]


def test_generated_code_matches_the_proto(tmp_path):
    protoc = pytest.importorskip("grpc_tools.protoc")
    root = Path(__file__).resolve().parents[1]
    rel = "slamreloc/proto/relocalizer.proto"
    (tmp_path / "slamreloc/proto").mkdir(parents=True)
    shutil.copy(root / rel, tmp_path / rel)
    assert protoc.main(["protoc", f"-I{tmp_path}", f"--python_out={tmp_path}",
                        f"--pyi_out={tmp_path}", f"--grpc_python_out={tmp_path}",
                        str(tmp_path / rel)]) == 0
    def code(path: Path) -> str:  # the generator's own version aside: grpcio-tools >= 1.85.1
        return re.sub(r"GRPC_GENERATED_VERSION = '[^']*'", "GRPC_GENERATED_VERSION = ''",
                      path.read_text())

    for name in ("relocalizer_pb2.py", "relocalizer_pb2.pyi", "relocalizer_pb2_grpc.py"):
        assert code(tmp_path / "slamreloc/proto" / name) == \
            code(root / "slamreloc/proto" / name), f"regenerate {name} (proto/__init__)"


def test_localize_cli_lines_match_the_service(server, small_map, scene_dir):
    """`slamreloc localize` and the service agree on files (what the C++ client sends)."""
    paths = [str(f.image_path) for f in load_dataset(scene_dir).frames("seq-02")[:3]]
    status, out, err = run_cli_output(["localize", str(small_map.root), *paths])
    assert status == 0, err
    with Client(server.address) as client:
        for line, path in zip(out.splitlines(), paths):
            values = [float(v) for v in line.split()[1:8]]
            pose = client.localize(path).world_from_cam
            assert values == pytest.approx([*pose.translation, *pose.quat_xyzw()], abs=1e-6)


def test_ros2_node_path_below_rclpy(server, small_map, scene_dir):
    """What clients/ros2/slamreloc_node.py does with a message, without ROS: sensor_msgs/Image
    (raw and compressed) + CameraInfo -> colour_file / camera_from_info -> Client.localize;
    the pose equals the image file's."""
    pytest.importorskip("rosbags")
    from slamreloc.datasets.rosbag import camera_from_info, colour_file
    from tests.rosbag_support import Messages

    msgs = Messages(2)
    frame = load_dataset(scene_dir).frames("seq-02")[2]
    info = msgs.camera_info(0.0, small_map.camera)
    with Client(server.address) as client:
        expected = client.localize(frame.image_path).response.world_from_cam
        for msg in (msgs.raw(0.0, read_image(frame.image_path), "rgb8"),
                    msgs.compressed(0.0, frame.image_path.read_bytes(), "png")):
            data, _, size = colour_file(msg, "image")
            answer = client.localize(data, camera=camera_from_info(info, size, "camera_info"))
            assert answer.localized and answer.response.world_from_cam == expected
