"""Issue 43, what the twelfth round left (minor) and the thirteenth attack round found, as
regression tests."""

from __future__ import annotations

import numpy as np
import pytest

from slamreloc.datasets import load_dataset
from slamreloc.errors import InputError
from tests.test_input_leftovers import scene, tum_folder  # noqa: F401 (a fixture)


def test_a_tum_list_going_back_in_time_is_refused(scene, tmp_path):  # noqa: F811
    """Round 12 minor: rgb.txt whose stamps went backwards was taken in file order (tracking
    ran the sequence backwards there); it is refused naming the line, as the C++ client does."""
    _, frames = scene
    root = tum_folder(frames, tmp_path / "tum")
    lines = (root / "rgb.txt").read_text().splitlines()
    lines[2], lines[3] = lines[3], lines[2]  # the second and third frames swapped
    (root / "rgb.txt").write_text("\n".join(lines) + "\n")
    earlier = lines[3].split()[0]
    with pytest.raises(InputError, match=rf"rgb.txt:4: timestamp {earlier} is earlier than "
                                         r"line 3's; the frames must be listed in time order"):
        load_dataset(root)


# ---- service -----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tiny_map(tmp_path_factory):
    from tests.test_fuzz_inputs import _tiny_map

    return _tiny_map(tmp_path_factory.mktemp("round13") / "map")


def _health(address: str):
    from tests.test_round12 import _health

    return _health(address)


def test_a_session_that_never_reads_its_last_answer_is_cancelled(tiny_map, monkeypatch):
    """M1: a client that ended its stream and never read the closing answer (a long session's
    trajectory, megabytes) kept its session slot and a server thread: that answer was sent
    with the idle deadline off. It is now sent under the deadline as every other answer."""
    import time

    import grpc

    from slamreloc.proto import relocalizer_pb2 as pb
    from slamreloc.service import sessions
    from slamreloc.service.server import SERVICE_NAME, ServeConfig, start_server

    # the trajectory of a long session, larger than the client's receive window
    monkeypatch.setattr(sessions.Session, "close",
                        lambda self: pb.SessionClosed(stats_json="x" * (4 << 20)))
    running = start_server({"m": tiny_map}, ServeConfig(
        port=0, watch_s=0, max_sessions=1, session_idle_s=1.0, open_timeout_s=1.0))
    channel = grpc.insecure_channel(running.address, options=[("grpc.http2.bdp_probe", 0),
                                                              ("grpc.max_receive_message_length",
                                                               8 << 20)])
    try:
        call = channel.stream_stream(f"/{SERVICE_NAME}/Session")(iter([
            pb.SessionRequest(open=pb.SessionOpen(map="m")).SerializeToString()]), timeout=120)
        deadline = time.monotonic() + 60
        seen = False
        while time.monotonic() < deadline:  # opened, then its slot comes free unread
            n = _health(running.address).num_sessions
            seen = seen or n == 1
            if seen and n == 0:
                break
            time.sleep(0.1)
        assert seen and _health(running.address).num_sessions == 0
        call.cancel()
    finally:
        channel.close()
        running.stop()


@pytest.mark.parametrize("stamps, refused", [
    ([-2.0, -1.0, 0.0, 0.0], 3), ([0.0, 0.0, 5.0], 2), ([1e-300, 0.0], 1),
    ([0.0, 0.0, 0.0], None), ([0.0, 0.04, 0.08], None), ([-1.0, 0.0, 1.0], None)])
def test_a_sessions_timestamps_increase_or_are_none(tiny_map, stamps, refused):
    """M3: `[-2, -1, 0, 0]` and `[0, 0, 5]` were taken: the exemption for 0 ("none given")
    looked at one frame and the one before. A session's stamps increase, or are 0 in every
    frame (decided by its first two frames)."""
    from slamreloc.client import Client, RemoteError
    from slamreloc.geometry import Rigid3
    from slamreloc.service.server import ServeConfig, start_server

    running = start_server({"m": tiny_map}, ServeConfig(port=0, watch_s=0))
    image = np.zeros((48, 64), np.uint8)
    try:
        with Client(running.address) as client, client.session("m") as session:
            for i, stamp in enumerate(stamps):
                send = lambda: session.send(  # noqa: E731
                    image, odometry_world_from_cam=Rigid3.identity(), timestamp=stamp)
                if i == refused:
                    with pytest.raises(RemoteError, match="frame.timestamp"):
                        send()
                else:
                    send()
    finally:
        running.stop()


@pytest.mark.parametrize("encoding", ["float32", "uint16"])
@pytest.mark.parametrize("shape", [(5,), (), (48, 64, 1)])
def test_the_client_sends_depth_of_one_value_per_pixel(shape, encoding):
    """M4: a uint16 depth of 1 or 0 dimensions raised a bare IndexError, and (H, W, 1) was sent
    while the float path refused it: both refuse any shape but (H, W), naming it."""
    from slamreloc.client import ClientSession

    depth = np.ones(shape, np.uint16 if encoding == "uint16" else np.float32)
    with pytest.raises(InputError, match=r"depth is \(H, W\), one value per pixel; got shape"):
        ClientSession.send(_NoStream(), np.zeros((48, 64), np.uint8), depth=depth,
                           depth_encoding=encoding)


class _NoStream:
    """Stands for a session's stream: a frame that reaches it is a failure of the test."""

    def _answer(self, request):
        raise AssertionError("sent")
