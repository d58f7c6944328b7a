"""COLMAP projects (sparse model + images/): loading, camera models, splits, damaged models,
and `slamreloc map` on one."""

from __future__ import annotations

import struct
import subprocess
import sys
import time

import numpy as np
import pytest

from slamreloc.datasets import load_dataset
from slamreloc.errors import InputError
from slamreloc.map.scene_map import SceneMap
from tests.colmap_project import write_colmap_project


@pytest.fixture(scope="module")
def source(scene_dir):
    """Three frames of each of the synthetic scene's first two sequences (7-Scenes layout)."""
    ds = load_dataset(scene_dir)
    return ds.frames("seq-01")[:3] + ds.frames("seq-02")[:3]


@pytest.mark.parametrize("ext, legacy", [("bin", False), ("bin", True), ("txt", False),
                                         ("txt", True)])
def test_colmap_model_loads_with_the_source_poses_and_camera(source, tmp_path, ext, legacy):
    root = write_colmap_project(source, tmp_path / "project", ext, legacy)
    ds = load_dataset(root)
    assert ds.kind == "colmap" and not ds.depth_registered
    assert list(ds.sequences) == ["seq-01", "seq-02"]
    assert ds.resolve_split("train") == ["seq-01", "seq-02"]  # no split files: all for mapping
    frames = ds.frames("all")
    assert [f.name for f in frames] == [f"{f.sequence}/{f.image_path.name}" for f in source]
    for got, want in zip(frames, source):
        assert got.camera == want.camera  # COLMAP's +0.5 principal point converted back
        np.testing.assert_allclose(got.world_from_cam.matrix(), want.world_from_cam.matrix(),
                                   atol=1e-9)
        assert got.image_path.read_bytes() == want.image_path.read_bytes()
        assert got.depth_path is None


def test_colmap_model_in_sparse_and_split_files(source, tmp_path):
    root = write_colmap_project(source, tmp_path / "project", model_dir="sparse")
    (root / "TrainSplit.txt").write_text("seq-02\n")
    (root / "TestSplit.txt").write_text("# queries\nseq-01\n")
    ds = load_dataset(root)
    assert ds.resolve_split("train") == ["seq-02"] and ds.resolve_split("test") == ["seq-01"]
    (root / "TestSplit.txt").write_text("seq-09\n")
    with pytest.raises(InputError, match="TestSplit.txt: split 'test' names sequence 'seq-09'"):
        load_dataset(root).frames("test")


def test_distortion_models_are_read_and_others_refused(source, tmp_path):
    ok = write_colmap_project(source, tmp_path / "zero", model="OPENCV",
                              distortion=(0.0, 0.0, 0.0, 0.0))
    assert load_dataset(ok).frames("all")[0].camera == source[0].camera
    for name, model, distortion in (("radial", "OPENCV", (0.1, 0.0, 0.0, 0.0)),
                                    ("fisheye", "OPENCV_FISHEYE", (0.0, 0.0, 0.0, 0.0))):
        root = write_colmap_project(source, tmp_path / name, model=model,
                                    distortion=distortion)
        camera = load_dataset(root).frames("all")[0].camera
        assert (camera.model, camera.distortion) == (model, distortion)
        assert camera.pinhole == source[0].camera
    root = write_colmap_project(source, tmp_path / "fov", model="FOV", distortion=(0.1,))
    with pytest.raises(InputError) as err:
        load_dataset(root)
    assert str(err.value).startswith(f"{root}/sparse/0/cameras.bin: camera 1 is FOV")
    assert "undistort the images" in str(err.value) and "\n" not in str(err.value)


def test_missing_image_and_damaged_models_name_the_file(source, tmp_path):
    root = write_colmap_project(source, tmp_path / "project", legacy=True)
    model = root / "sparse" / "0"
    missing = root / "images" / "seq-02" / source[4].image_path.name
    missing.rename(tmp_path / "aside.png")
    with pytest.raises(InputError, match=f"{missing}: image file not found"):
        load_dataset(root)
    (tmp_path / "aside.png").rename(missing)
    data = (model / "images.bin").read_bytes()
    (model / "images.bin").write_bytes(data[:-30])
    with pytest.raises(InputError, match=f"{model}/images.bin: truncated"):
        load_dataset(root)
    # a count that pycolmap's reader would trust (allocate, or loop on for ever): refused at once
    (model / "images.bin").write_bytes(struct.pack("<Q", 1 << 40) + data[8:])
    t0 = time.monotonic()
    with pytest.raises(InputError, match=f"{model}/images.bin: damaged or truncated"):
        load_dataset(root)
    assert time.monotonic() - t0 < 5
    (model / "images.bin").write_bytes(data)
    cams = bytearray((model / "cameras.bin").read_bytes())
    cams[12:16] = struct.pack("<i", 99)  # the first camera's model id
    (model / "cameras.bin").write_bytes(bytes(cams))
    with pytest.raises(InputError, match="cameras.bin: camera 1 has unknown camera model id 99"):
        load_dataset(root)


def test_images_txt_garbage_names_file_and_line(source, tmp_path):
    root = write_colmap_project(source, tmp_path / "project", ext="txt", legacy=True)
    path = root / "sparse" / "0" / "images.txt"
    lines = path.read_text().splitlines()
    first = next(i for i, line in enumerate(lines) if line and not line.startswith("#"))
    lines[first] = lines[first].replace(" 1 seq-01", " one seq-01")
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match=f"{path}:{first + 1}: CAMERA_ID is not a whole number"):
        load_dataset(root)


def test_map_command_on_a_colmap_project(source, tmp_path):
    """`slamreloc map COLMAP_PROJECT --out M` makes a map whose training poses and camera are
    the project's."""
    root = write_colmap_project(source, tmp_path / "project", legacy=True)
    out = tmp_path / "map"
    proc = subprocess.run([sys.executable, "-m", "slamreloc.cli", "map", str(root), "--out",
                           str(out), "--arch", "tiny", "--epochs", "1", "--device", "cpu"],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    m = SceneMap.load(out)
    assert m.meta["dataset"]["kind"] == "colmap" and m.camera == source[0].camera
    db = m.database
    assert db.frame_names == [f"{f.sequence}/{f.image_path.name}" for f in source]
    np.testing.assert_allclose(db.world_from_cam,
                               np.stack([f.world_from_cam.matrix() for f in source]), atol=1e-9)
    assert m.meta["labels"]["n_labelled"] >= 500
