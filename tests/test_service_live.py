"""`slamreloc serve` sessions that learn their map (SessionOpen.learn, as `slam --out`):
saved on request under a name into `--learned-maps`, then served like any other map while
the session carries on; the refusals of a save."""

from __future__ import annotations

import grpc
import pytest

from slamreloc.client import Client, RemoteError
from slamreloc.errors import InputError
from slamreloc.datasets import load_dataset
from slamreloc.map.scene_map import SceneMap
from slamreloc.proto import relocalizer_pb2 as pb
from slamreloc.service.server import ServeConfig, start_server
from slamreloc.slam.feed import read_frames
from slamreloc.slam.live_map import LiveMapConfig

# the synthetic scene's small images need upsampled SIFT (as its maps: tests/conftest.py)
LIVE = LiveMapConfig(feature_options={"upsample": True})
N_FRAMES = 60


@pytest.fixture(scope="module")
def learning_server(tmp_path_factory):
    folder = tmp_path_factory.mktemp("learned")
    running = start_server({}, ServeConfig(port=0, watch_s=0, learned_maps=folder, live=LIVE))
    yield running, folder
    running.stop()


@pytest.fixture(scope="module")
def frames(kidnap_scene):
    dataset = load_dataset(kidnap_scene)
    frames = dataset.frames("kidnap")[:N_FRAMES + 6]
    return list(read_frames(dataset, frames, depth=True))


def test_a_session_learns_saves_and_serves_its_map(learning_server, frames):
    running, folder = learning_server
    with Client(running.address) as client:
        # an empty map on a server that serves none: the session learns one
        with client.session(odometry="auto") as session:
            assert session.opened.map_version == ""
            with pytest.raises(RemoteError) as err:  # nothing learned yet
                session.save("learned")
            assert (err.value.kind, err.value.code) == ("FAILED_PRECONDITION",
                                                        grpc.StatusCode.FAILED_PRECONDITION)
            results = [session.send(f.image, camera=f.camera, depth=f.depth,
                                    timestamp=f.timestamp) for f in frames[:N_FRAMES]]
            assert [r.index for r in results] == list(range(N_FRAMES))
            assert sum(r.has_pose for r in results) >= N_FRAMES - 2
            # a frame without depth: refused, typed, naming the field; the session carries on
            with pytest.raises(RemoteError) as err:
                session.send(frames[N_FRAMES].image, camera=frames[N_FRAMES].camera)
            assert err.value.kind == "BAD_DEPTH" and "frame.depth" in str(err.value)
            # a client never names a server path
            for bad in ("../escape", "a/b", ".hidden", "", "two words"):
                with pytest.raises(InputError, match="`name`"):  # refused before it is sent
                    session.save(bad)
                with pytest.raises(RemoteError) as err:  # and by the server, if sent anyway
                    session._answer(pb.SessionRequest(save=pb.SessionSave(name=bad)))
                assert err.value.kind == "BAD_REQUEST", bad
            saved = session.save("learned")
            assert saved.name == "learned" and saved.map_version and saved.num_points > 500
            assert (folder / "learned").is_dir()
            m = SceneMap.load(folder / "learned")
            assert m.info.train["learned_live"]
            listed = {i.name: i for i in client.list_maps()}
            assert listed["learned"].version == saved.map_version
            # the saved map answers Localize while the session goes on
            f = frames[10]
            answer = client.localize(f.image, camera=f.camera, map="learned")
            assert answer.localized, answer.response.detail
            assert answer.response.map_version == saved.map_version
            more = [session.send(f.image, camera=f.camera, depth=f.depth,
                                 timestamp=f.timestamp) for f in frames[N_FRAMES:]]
            assert [r.index for r in more] == list(range(N_FRAMES, len(frames)))
            # saving again replaces the map, and the server serves the new one
            again = session.save("learned")
            listed = {i.name: i for i in client.list_maps()}
            assert listed["learned"].version == again.map_version
            assert client.localize(f.image, camera=f.camera, map="learned").localized
            # a name whose folder holds something other than a map is not overwritten
            (folder / "notamap").mkdir()
            (folder / "notamap" / "keep.txt").write_text("mine")
            with pytest.raises(RemoteError) as err:
                session.save("notamap")
            assert err.value.kind == "FAILED_PRECONDITION"
            assert (folder / "notamap" / "keep.txt").read_text() == "mine"
            closed = session.close()
        assert len(closed.world_from_cam) == len(frames)
        assert "learned" in {i.name for i in client.list_maps()}


def test_save_without_learned_maps_is_refused(frames):
    running = start_server({}, ServeConfig(port=0, watch_s=0, live=LIVE))
    try:
        with Client(running.address) as client, client.session(odometry="auto",
                                                                learn=True) as session:
            f = frames[0]
            session.send(f.image, camera=f.camera, depth=f.depth, timestamp=f.timestamp)
            with pytest.raises(RemoteError) as err:
                session.save("learned")
            assert (err.value.kind, err.value.code) == ("FAILED_PRECONDITION",
                                                        grpc.StatusCode.FAILED_PRECONDITION)
            assert "--learned-maps" in str(err.value)
            f = frames[1]  # the session carries on
            assert session.send(f.image, camera=f.camera, depth=f.depth,
                                timestamp=f.timestamp).index == 1
    finally:
        running.stop()
