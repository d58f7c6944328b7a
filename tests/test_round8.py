"""Issue 43, the eighth attack round (CLI side): what it found, each as a regression test.
The service side's are in test_service_hardening.py, test_hardening.py, test_round6.py,
test_ray_serve.py and test_cpp_client.py."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from slamreloc.datasets import load_dataset
from slamreloc.datasets.rosbag import BagTopics, set_topics
from slamreloc.map.format import META
from slamreloc.map.scene_map import SceneMap
from tests.fuzzing import run_cli
from tests.rosbag_support import write_bag
from tests.test_cli_round5 import one_line_exit_2
from tests.test_fuzz_inputs import _tiny_map


@pytest.fixture(autouse=True)
def no_topics():
    set_topics(BagTopics())
    yield
    set_topics(BagTopics())


@pytest.fixture(scope="module")
def tiny_map(tmp_path_factory) -> Path:
    return _tiny_map(tmp_path_factory.mktemp("round8") / "map")


def _digests(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def test_a_bag_whose_name_cannot_name_frames_is_refused_and_the_old_map_kept(scene_dir,
                                                                             tiny_map,
                                                                             tmp_path):
    """F1: `...bag` (frames `../000000`) ran the whole job, then replaced a good map at --out
    by one its own check refuses. Now the bag is refused as it loads, naming it."""
    dataset = load_dataset(scene_dir)
    bag = write_bag(dataset, dataset.frames("seq-01")[:3], tmp_path / "...bag", version=1)
    old = shutil.copytree(tiny_map, tmp_path / "old")
    before = _digests(old)
    code, err = run_cli(["map", str(bag), "--out", str(old), "--epochs", "1"])
    last = err.strip().splitlines()[-1]  # after the bag's listing lines
    assert code == 2 and last.startswith(f"error: {bag}: frame name '../000000' is not a path "
                                         "inside the dataset"), err
    assert _digests(old) == before


def test_save_map_checks_the_metadata_before_the_swap(tiny_map, tmp_path):
    """F1, the safety net: metadata a reader would refuse never replaces a map that loads."""
    from slamreloc.map.write import save_map
    from slamreloc.errors import InputError

    old = shutil.copytree(tiny_map, tmp_path / "old")
    before = _digests(old)
    m = SceneMap.load(old)
    db = m.database
    db.frame_names[0] = "../escape"
    with pytest.raises(InputError, match="not written .what was there is kept.*'..'"):
        save_map(old, m.info, m.regressor, db)
    assert _digests(old) == before and not list(tmp_path.glob(".old.tmp-*"))


def test_an_empty_frame_names_list_is_refused(tiny_map, tmp_path):
    """F1b: `"frame_names": []` passed the count check (1 name for 2 poses did not), then export
    wrote a COLMAP model pycolmap cannot read and pseudo-label ended in IndexError."""
    bad = shutil.copytree(tiny_map, tmp_path / "m")
    doc = json.loads((bad / META).read_text())
    doc["frame_names"] = []
    (bad / META).write_text(json.dumps(doc))
    one_line_exit_2(["export", str(bad), "--tum", str(tmp_path / "t.txt")],
                    "2 training poses but 0 frame names")
    assert not (tmp_path / "t.txt").exists()


def test_intrinsics_txt_takes_every_cameras_principal_point_rule(scene_dir, tmp_path):
    """F2: intrinsics.txt refused any negative cx; --camera, --intrinsics and camera.txt take
    cx in [-width, 2 width]. Now one rule, and the file is named where it breaks it."""
    folder = shutil.copytree(scene_dir, tmp_path / "scene")
    w = load_dataset(folder).frames("seq-02")[0].camera.width
    (folder / "intrinsics.txt").write_text("262.5 0 -10\n0 262.5 119.5\n0 0 1\n")
    assert load_dataset(folder).frames("seq-02")[0].camera.cx == -10
    (folder / "intrinsics.txt").write_text(f"262.5 0 {-w - 5}\n0 262.5 119.5\n0 0 1\n")
    with pytest.raises(Exception, match=r"intrinsics.txt: .*cx must lie within one image"):
        load_dataset(folder)


def test_a_colmap_quaternion_within_the_tolerance_is_normalised(tiny_map, tmp_path):
    """F3: a COLMAP images.txt quaternion of norm 1.0005 (inside the 1e-3 rule every pose file
    follows) failed as "not orthonormal"; now it is normalised as in the other readers."""
    from slamreloc.datasets.poses import read_poses

    model = tmp_path / "model"
    code, err = run_cli(["export", str(tiny_map), "--colmap", str(model)])
    assert code == 0, err
    lines = (model / "images.txt").read_text().splitlines()
    i = next(k for k, line in enumerate(lines) if line and not line.startswith("#"))
    fields = lines[i].split()
    fields[1:5] = [repr(float(v) * 1.0005) for v in fields[1:5]]
    lines[i] = " ".join(fields)
    (model / "images.txt").write_text("\n".join(lines) + "\n")
    poses = read_poses(model).world_from_cam
    rotation = next(iter(poses.values())).rotation
    np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-9)


def test_topic_is_refused_where_no_bag_is_read(tiny_map, scene_dir, tmp_path):
    """F4: the global --topic was taken silently by commands that read no bag, and sfm took
    pose= although it reads no poses."""
    image = str(load_dataset(scene_dir).frames("seq-02")[0].image_path)
    one_line_exit_2(["--topic", "image=/x", "localize", str(tiny_map), image],
                    "slamreloc --topic chooses a ROS bag DATASET's topics", "'localize'")
    one_line_exit_2(["--topic", "pose=/pose", "sfm", str(scene_dir), "--out",
                     str(tmp_path / "s")], "sfm makes the poses from the images")
    assert not (tmp_path / "s").exists()


def test_a_timestamp_no_float_holds_is_named_as_one(scene_dir, tmp_path):
    """F6: `1e400` or `nan` stamps were read as frame names and reported as "frame '1e400' has
    more than one pose"; a name with a space, as a repeated name instead of its field count."""
    line = "0 0 0 0 0 0 1\n"
    for stamp, words in (("1e400", "timestamp '1e400'"), ("nan", "timestamp 'nan'")):
        (tmp_path / "p.txt").write_text(f"{stamp} {line}{stamp} {line}")
        one_line_exit_2(["map", str(scene_dir), "--out", str(tmp_path / "m"), "--poses",
                         str(tmp_path / "p.txt")], words)
    (tmp_path / "p.txt").write_text(f"seq-01/frame 000000 {line}" * 2)
    one_line_exit_2(["map", str(scene_dir), "--out", str(tmp_path / "m"), "--poses",
                     str(tmp_path / "p.txt")], "expected 8 fields")


def test_a_camera_error_quotes_the_number_given(tiny_map, scene_dir):
    """F7: `--camera "PINHOLE 320 240 262.5 262.5 -400 119.5"` said "got -400.5", the value
    after COLMAP's half-pixel shift, not the one typed."""
    image = str(load_dataset(scene_dir).frames("seq-02")[0].image_path)
    line = one_line_exit_2(["localize", str(tiny_map), image, "--camera",
                            "PINHOLE 320 240 262.5 262.5 -400 119.5"], "cx must lie within")
    assert line.endswith("got -400")


@pytest.mark.parametrize("kind", ["fifo", "folder", "dev_zero"])
def test_sfm_refuses_a_photo_name_that_is_no_file(scene_dir, tmp_path, kind):
    """F8: a pipe, a link to a device or a folder named like a photo was skipped unsaid."""
    photos = tmp_path / "photos"
    photos.mkdir()
    for frame in load_dataset(scene_dir).frames("seq-01")[:3]:
        shutil.copy(frame.image_path, photos / frame.image_path.name)
    odd = photos / "zz.jpg"
    {"fifo": lambda: os.mkfifo(odd), "folder": odd.mkdir,
     "dev_zero": lambda: odd.symlink_to("/dev/zero")}[kind]()
    one_line_exit_2(["sfm", str(photos), "--out", str(tmp_path / "out")], str(odd),
                    "named as a photo but not a file")
    assert not (tmp_path / "out").exists()
