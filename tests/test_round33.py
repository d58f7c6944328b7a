"""Attack round 33: around round 32's fixes. A trajectory's names sidecar follows the one
instant rule and TUM's line rule; a session's and the C++ client's stamps within a microsecond
are one instant; outputs into a bind-mounted or doubly linked folder of an input are refused;
export names a recorded dataset it cannot read; a frame image that is a pipe is named so."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import grpc
import numpy as np
import pytest

from slamreloc.client import image_msg
from slamreloc.errors import InputError
from slamreloc.geometry import Rigid3, read_named_trajectory
from slamreloc.proto import relocalizer_pb2 as pb
from slamreloc.proto import relocalizer_pb2_grpc as pb_grpc
from slamreloc.proto.messages import transform_msg
from slamreloc.service.server import ServeConfig, start_server
from tests.fuzzing import run_cli
from tests.test_cpp_client import MISSING
from tests.test_fuzz_inputs import _tiny_map
from tests.test_round31 import _digest, _png, _tiny_map_of, six_frames


@pytest.fixture(scope="module")
def tiny_map(tmp_path_factory) -> Path:
    return _tiny_map(tmp_path_factory.mktemp("round33") / "map")


@pytest.fixture(scope="module")
def tiny_scene(scene_dir, tmp_path_factory) -> Path:
    return six_frames(scene_dir, tmp_path_factory.mktemp("round33_scene") / "ds")

POSES = ["0.000000 0 0 0 0 0 0 1", "1.000000 0.1 0 0 0 0 0 1", "2.000000 0.2 0 0 0 0 0 1"]
NAMES = ["0.000000 seq-01/frame-000000", "1.000000 seq-01/frame-000001",
         "2.000000 seq-01/frame-000002"]


def _trajectory(tmp_path: Path, names: list[str], sep: str = "\n") -> Path:
    path = tmp_path / "p.txt"
    path.write_text("\n".join(POSES) + "\n")
    (tmp_path / "p.names.txt").write_text(sep.join(names) + "\n", encoding="utf-8")
    return path


@pytest.mark.parametrize("again", ["0.000000 seq-01/frame-000001", "0.0000004 seq-01/frame-9"])
def test_a_names_sidecar_naming_one_instant_twice_is_refused(tmp_path, again):
    """R1: the sidecar was a dict: a stamp named twice kept its last name, so frame 0 took
    frame 1's pose. Two names at one instant (stamps within a microsecond) are refused,
    naming both lines; the same name twice is read once."""
    path = _trajectory(tmp_path, [*NAMES, again])
    with pytest.raises(InputError, match=r"p.names.txt:4: stamp .* line 1 with another name"):
        read_named_trajectory(path)
    _trajectory(tmp_path, [*NAMES, NAMES[1]])
    assert read_named_trajectory(path).names == [n.split()[1] for n in NAMES]


@pytest.mark.parametrize("sep, blank", [("\u2028", " "), ("\n", "\u00a0"), ("\f\n", " ")])
def test_a_names_sidecar_is_read_by_tum_s_line_rule(tmp_path, sep, blank):
    """R9: the sidecar was split at any Unicode line break and blank, which its TUM file
    refuses."""
    path = _trajectory(tmp_path, [n.replace(" ", blank) for n in NAMES], sep)
    with pytest.raises(InputError, match="p.names.txt.*other than a space, a tab or a line "
                                         "feed"):
        read_named_trajectory(path)


def test_a_session_s_frames_within_a_microsecond_are_one_instant(tiny_map):
    """R3: a session took two frames 0.5 us apart, which a file's list refuses."""
    running = start_server({"m": tiny_map}, ServeConfig(port=0, watch_s=0))
    try:
        channel = grpc.insecure_channel(running.address)
        requests = [pb.SessionRequest(open=pb.SessionOpen(map="m", odometry="client"))]
        for stamp in (1.0, 1.0000005, 1.1):
            frame = pb.SessionFrame(image=image_msg(_png(64, 48)), timestamp=stamp)
            frame.odometry_world_from_cam.CopyFrom(transform_msg(Rigid3.identity()))
            requests.append(pb.SessionRequest(frame=frame))
        updates = list(pb_grpc.RelocalizerStub(channel).Session(iter(requests), timeout=120))
        channel.close()
    finally:
        running.stop()
    errors = [u.error for u in updates if u.HasField("error")]
    assert len(errors) == 1 and "within 1 microsecond" in errors[0].message, updates
    assert sum(u.HasField("frame") for u in updates) == 2


@pytest.mark.skipif(bool(MISSING), reason=f"the C++ client needs {', '.join(MISSING)}")
def test_the_cpp_client_reads_stamps_within_a_microsecond_as_one_instant(client_binary,
                                                                         tmp_path):
    """R4: the C++ client's rgb.txt took two files 0.5 us apart (only the same stamp was
    refused), which the Python reader refuses."""
    (tmp_path / "rgb").mkdir()
    for name in ("a", "b"):
        (tmp_path / "rgb" / f"{name}.png").write_bytes(_png(64, 48))
    (tmp_path / "rgb.txt").write_text("1.0 rgb/a.png\n1.0000005 rgb/b.png\n")
    done = subprocess.run([str(client_binary), "--server", "127.0.0.1:1", str(tmp_path)],
                          capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 2 and "rgb.txt:2: timestamp 1.0000005 is within 1 microsecond " \
        "of line 1 with another file" in done.stderr, done.stderr


def test_outputs_into_a_folder_linked_from_a_linked_folder_are_refused(tiny_scene, tmp_path):
    """R5: a dataset whose sequence is a link to a folder whose images are links into a
    store: the links inside the linked folder were not followed, and a map was written into
    the store."""
    ext, store, ds = tmp_path / "ext", tmp_path / "store", tmp_path / "ds"
    shutil.copytree(tiny_scene, ext)
    store.mkdir()
    for f in sorted((ext / "seq-01").glob("*.color.png")):
        f.rename(store / f.name)
        f.symlink_to(store / f.name)
    ds.mkdir()
    for entry in ext.iterdir():
        (ds / entry.name).symlink_to(entry) if entry.is_dir() else shutil.copy(entry, ds)
    before = _digest(store)
    code, err = run_cli(["map", str(ds), "--out", str(store / "mapin"), "--arch", "tiny",
                         "--epochs", "1"])
    assert code == 2 and "linked folder" in err and "which this command only reads" in err, err
    assert _digest(store) == before


def _bind_mounted_sequence(tiny_scene: Path, tmp_path: Path) -> tuple[Path, Path]:
    """(ext, ds): a copy of `tiny_scene` as `ds` whose seq-01 is a bind mount of ext/seq-01
    (the caller unmounts it); skipped where bind mounts are not allowed."""
    ext, ds = tmp_path / "ext", tmp_path / "ds"
    shutil.copytree(tiny_scene, ds)
    ext.mkdir()
    shutil.move(ds / "seq-01", ext / "seq-01")
    (ds / "seq-01").mkdir()
    if subprocess.run(["mount", "--bind", str(ext / "seq-01"), str(ds / "seq-01")],
                      capture_output=True, check=False).returncode != 0:
        pytest.skip("bind mounts need root (mount --bind)")
    return ext, ds


def test_outputs_into_a_bind_mounted_folder_of_an_input_are_refused(tiny_scene, tmp_path):
    """R2: a dataset whose sequence folder is a bind mount of another folder: outputs named
    in that folder were written among the frames (a bind mount is no link)."""
    ext, ds = _bind_mounted_sequence(tiny_scene, tmp_path)
    try:
        before = _digest(ext)
        code, err = run_cli(["map", str(ds), "--out", str(ext / "seq-01" / "mapin"),
                             "--arch", "tiny", "--epochs", "1"])
        after = _digest(ext)
    finally:
        subprocess.run(["umount", str(ds / "seq-01")], check=False)
    assert code == 2 and "the dataset's bind-mounted folder" in err, err
    assert after == before


def test_export_names_a_recorded_dataset_it_cannot_read(tiny_scene, tmp_path):
    """R7: a recorded dataset that lost one image gave every point grey, rc 0; it is now
    named. The TUM poses, which need no image, are still exported."""
    ds = tmp_path / "ds"
    shutil.copytree(tiny_scene, ds)
    m = _tiny_map_of(ds, tmp_path / "m")
    (ds / "seq-01" / "frame-000002.color.png").unlink()
    code, err = run_cli(["export", str(m), "--ply", str(tmp_path / "p.ply")])
    assert code == 2 and "a dataset the map records, read for the points' colours" in err, err
    assert not (tmp_path / "p.ply").exists()
    assert run_cli(["export", str(m), "--tum", str(tmp_path / "t.txt")])[0] == 0


def test_a_frame_image_that_is_a_named_pipe_is_named_so(tiny_scene, tmp_path):
    """R8: a 7-Scenes colour image that is a named pipe was called 'a folder or a broken
    link'."""
    ds = tmp_path / "ds"
    shutil.copytree(tiny_scene, ds)
    image = ds / "seq-01" / "frame-000001.color.png"
    image.unlink()
    os.mkfifo(image)
    code, err = run_cli(["map", str(ds), "--out", str(tmp_path / "m"), "--arch", "tiny",
                         "--epochs", "1"])
    assert code == 2 and "not a regular file (a named pipe)" in err, err


def test_the_names_reader_keeps_the_file_s_order(tmp_path):
    """The sidecar's names follow the TUM file's rows, whatever the sidecar's order."""
    path = _trajectory(tmp_path, list(reversed(NAMES)))
    assert read_named_trajectory(path).names == [n.split()[1] for n in NAMES]
    assert np.allclose(read_named_trajectory(path).stamps, [0, 1, 2])


@pytest.fixture(scope="module")
def uncalibrated_bag(scene_dir, tmp_path_factory) -> Path:
    """A ROS 2 bag of 4 query frames whose CameraInfo says 'not calibrated' (K all zero)."""
    import dataclasses

    from tests.rosbag_support import INFO_TOPIC, Messages, first_test_frames, frame_stamp, write_bag

    dataset, frames = first_test_frames(scene_dir, 4)
    info = [dataclasses.replace(Messages(2).camera_info(frame_stamp(f), f.camera), k=np.zeros(9))
            for f in frames]
    return write_bag(dataset, frames, tmp_path_factory.mktemp("round33_bag") / "bag",
                     camera_info=False, extra={INFO_TOPIC: info})


def test_camera_stands_in_for_an_uncalibrated_bag_s_camera_info(small_map, uncalibrated_bag):
    """R6: the refusal of an uncalibrated CameraInfo advised `--camera`, and `localize`
    refused the bag with `--camera` given. `--camera` now stands in for it; without it the
    bag is refused, saying which commands take one."""
    camera = "PINHOLE 320 240 262.5 262.5 159.5 119.5"
    code, err = run_cli(["localize", str(small_map.root), str(uncalibrated_bag)])
    assert code == 2 and "K is all zero" in err and "take `--camera` in its place" in err, err
    done = subprocess.run([sys.executable, "-m", "slamreloc.cli", "localize",
                           str(small_map.root), str(uncalibrated_bag), "--camera", camera],
                          capture_output=True, text=True, timeout=600, check=False)
    assert done.returncode == 0, done.stderr
    assert len(done.stdout.splitlines()) == 4, done.stdout


def test_a_live_map_leaves_its_prior_trainable(tiny_map):
    """A LiveMap froze its prior SceneMap's regressor in place, so a pseudo-label update of
    the same SceneMap object in the same process failed ('does not require grad'): the suite
    found it when its files ran in another order. The prior is left as it was, and training
    unfreezes what it trains."""
    from slamreloc.map.scene_map import SceneMap
    from slamreloc.regressor.train import TrainConfig, train_regressor
    from slamreloc.slam.live_map import LiveMap

    prior = SceneMap.load(tiny_map)
    LiveMap(prior=prior)
    assert all(p.requires_grad for p in prior.regressor.parameters())
    model = prior.regressor.requires_grad_(False)
    db = prior.database
    stats = train_regressor(model, db.descriptors, db.points, TrainConfig(epochs=1),
                            device="cpu", progress=False, fine_tune=True)
    assert np.isfinite(stats["final_loss_m"])


# ---- round 34: around round 33's fixes -------------------------------------------------------
def test_a_bind_mount_inside_an_input_is_found_whatever_the_walk_s_size(tiny_scene, tmp_path):
    """S1: the walk that found a bind-mounted sequence by its disk identity stopped after its
    entry limit, and a plain folder of 201 000 files listed after the sequence used it up. The
    bind mounts inside an input come from the mount table now, not from the walk."""
    from slamreloc.io.outputs import input_reach

    ext, ds = _bind_mounted_sequence(tiny_scene, tmp_path)
    try:
        reach = input_reach(ds, limit=1)  # the walk sees one entry only
    finally:
        subprocess.run(["umount", str(ds / "seq-01")], check=False)
    assert reach.mounted == [(ext / "seq-01").resolve()]


def test_a_bag_of_calibrated_and_uncalibrated_camera_infos_is_refused(scene_dir, tmp_path):
    """S2: a bag whose CameraInfo messages are first uncalibrated then calibrated took
    `--camera` and skipped the bag's own calibration; the other order advised `--camera`,
    which it then refused. Two cameras in one bag are refused either way, with or without
    `--camera`."""
    import dataclasses

    from slamreloc.datasets.rosbag import camera_in_place_of_info, load_rosbag
    from slamreloc.types import Camera
    from tests.rosbag_support import INFO_TOPIC, Messages, first_test_frames, frame_stamp
    from tests.rosbag_support import write_bag

    dataset, frames = first_test_frames(scene_dir, 2)
    for zero_first in (True, False):
        info = [Messages(2).camera_info(frame_stamp(f), f.camera) for f in frames]
        k = 0 if zero_first else 1
        info[k] = dataclasses.replace(info[k], k=np.zeros(9))
        bag = write_bag(dataset, frames, tmp_path / f"bag{k}", camera_info=False,
                        extra={INFO_TOPIC: info})
        for given in (None, Camera(320, 240, 262.5, 262.5, 159.5, 119.5)):
            with camera_in_place_of_info(given), pytest.raises(
                    InputError, match="message 1 is .* one camera per bag"):
                load_rosbag(bag)


def test_serve_on_ray_names_its_port_by_the_rule_of_every_server():
    """S3: `serve --engine ray --port 70000` said "ports 70000, 8000: 1 to 65535", naming no
    option and a port the user never gave."""
    pytest.importorskip("ray")
    from slamreloc.service.ray_serve import serve_forever

    with pytest.raises(InputError, match=r"^`port` 70000: not a TCP port \(0 for any free "):
        serve_forever({}, port=70000)
