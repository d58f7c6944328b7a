"""Issue 43, attack round 23 (interruption and files changing while read): a symbolic link put
at a map writer's OUT after its checks is never written, deleted or moved through (A1, A2); a
map saved over a folder while it is read never mixes into the map being read (A3); a dataset
frame's image or depth replaced by one of another size after the dataset's load is refused
where it is read, as at the load (A4, A5)."""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import cv2
import pytest

from slamreloc.errors import InputError
from tests.test_fuzz_inputs import _tiny_map


def _digests(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


# ---- A1, A2: OUT becomes a link while the map is written ------------------------------------
@pytest.mark.parametrize("victim_kind", ["map", "dataset"])
@pytest.mark.parametrize("exchange", [True, False], ids=["rename-exchange", "two-renames"])
def test_a_link_put_at_out_while_the_map_is_written_is_never_followed(
        tmp_path, monkeypatch, victim_kind, exchange):
    import slamreloc.map.write as write

    if not exchange:
        monkeypatch.setenv("SLAMRELOC_NO_RENAME_EXCHANGE", "1")
    victim = tmp_path / "victim"
    if victim_kind == "map":
        _tiny_map(victim)
    else:  # a dataset's files: images, poses, a split file, a sub-folder
        (victim / "seq-01").mkdir(parents=True)
        (victim / "seq-01" / "frame-000000.pose.txt").write_text("1 0 0 0\n" * 4)
        (victim / "TrainSplit.txt").write_text("sequence1\n")
    before = _digests(victim)
    out = tmp_path / "out"
    _tiny_map(out)  # an earlier map at OUT, replaced by a link while the new one is written
    real_write = write._write_map_files

    def write_then_link(tmp, target, *args):
        real_write(tmp, target, *args)
        target.rename(tmp_path / "moved-away")
        target.symlink_to(victim)

    monkeypatch.setattr(write, "_write_map_files", write_then_link)
    with pytest.raises(InputError, match=r"out: became a symbolic link \(to .*victim\) while "
                                         r"the map was written; not written"):
        _tiny_map(out, n=80)
    assert _digests(victim) == before
    assert out.is_symlink() and out.resolve() == victim.resolve()
    assert not [p.name for p in tmp_path.iterdir() if p.name.startswith(".out.")]


def test_a_map_writer_refuses_a_link_at_out_whatever_it_points_to(tmp_path):
    from slamreloc.map.write import check_map_target

    _tiny_map(tmp_path / "victim")
    (tmp_path / "out").symlink_to(tmp_path / "victim")
    with pytest.raises(InputError, match="out: is a symbolic link .* never writes through a link"):
        check_map_target(tmp_path / "out")


# ---- A3: a map saved over the folder while it is read -----------------------------------------
def test_a_map_saved_over_a_loaded_one_does_not_mix_into_it(tmp_path):
    from slamreloc.map.scene_map import SceneMap

    root = _tiny_map(tmp_path / "map", n=64)
    loaded = SceneMap.load(root)
    _tiny_map(root, n=200)  # another process saves a new map there
    assert len(loaded.database.points) == 64  # the files opened with its metadata
    assert len(SceneMap.load(root).database.points) == 200


def test_a_map_swapped_in_during_the_load_is_read_whole(tmp_path, monkeypatch):
    import slamreloc.map.scene_map as scene_map

    root = _tiny_map(tmp_path / "map", n=64)
    real_read = scene_map.read_regressor
    saves = []

    def save_first(*args):  # the metadata read, a new map saved before the weights are
        if not saves:
            saves.append(_tiny_map(root, n=200))
        return real_read(*args)

    monkeypatch.setattr(scene_map, "read_regressor", save_first)
    loaded = scene_map.SceneMap.load(root)
    assert saves and len(loaded.database.points) == loaded.info.labels["n_labelled"] == 200


def test_a_damaged_file_is_still_reported_as_damaged(tmp_path):
    from slamreloc.map.format import DATABASE
    from slamreloc.map.scene_map import SceneMap

    root = _tiny_map(tmp_path / "map")
    loaded = SceneMap.load(root)
    data = bytearray((root / DATABASE).read_bytes())
    data[-30] ^= 0xFF
    (root / DATABASE).write_bytes(bytes(data))
    for scene_map in (loaded, SceneMap.load(root)):
        with pytest.raises(InputError, match="contents do not match the checksum"):
            scene_map.database  # noqa: B018


# ---- A4, A5: a frame's file replaced by one of another size after the dataset's load ---------
def test_a_frame_file_of_another_size_since_the_load_is_refused_where_read(scene_dir, tmp_path):
    from slamreloc.datasets import load_dataset, read_frame_depth, read_frame_image
    from slamreloc.features import make_extractor
    from slamreloc.features.extract import extract_frames
    from slamreloc.slam.feed import read_frames

    root = shutil.copytree(scene_dir, tmp_path / "scene")
    dataset = load_dataset(root)
    frame = dataset.frames("train")[3]
    assert frame.depth_path is not None and frame.depth_camera is None  # registered depth
    image = cv2.imread(str(frame.image_path))
    depth = cv2.imread(str(frame.depth_path), cv2.IMREAD_ANYDEPTH)
    cv2.imwrite(str(frame.depth_path), cv2.resize(depth, (160, 120),
                                                  interpolation=cv2.INTER_NEAREST))
    depth_message = rf"{frame.depth_path}: depth is 160x120, its image is 320x240"
    with pytest.raises(InputError, match=depth_message):
        read_frame_depth(frame, dataset.depth_units_per_metre)
    with pytest.raises(InputError, match=depth_message):
        next(read_frames(dataset, [frame]))  # slam's feed
    cv2.imwrite(str(frame.image_path), cv2.resize(image, (640, 480)))
    image_message = (rf"{frame.image_path}: image is 640x480, the dataset's images are "
                     "320x240")
    with pytest.raises(InputError, match=image_message):
        read_frame_image(frame)
    with pytest.raises(InputError, match=image_message):  # map's feature extraction
        extract_frames([frame], make_extractor("sift"), progress=False)
    with pytest.raises(InputError, match=image_message):  # the same rule at the load
        load_dataset(root)
