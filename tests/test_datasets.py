"""Dataset loaders: 7-Scenes (real samples), TUM RGB-D, the synthetic scene; bad inputs."""

import shutil

import cv2
import numpy as np
import pytest

from slamreloc.datasets import load_dataset, read_depth, read_image, read_pose
from slamreloc.datasets.sevenscenes import SEVENSCENES_RGB_FROM_DEPTH
from slamreloc.errors import InputError
from slamreloc.types import Camera
from tests.conftest import REDKITCHEN, SMALL_SCENE, STAIRS, needs


@needs(STAIRS)
def test_sevenscenes_splits_and_jpg_colour():
    ds = load_dataset(STAIRS)
    assert ds.kind == "7scenes" and not ds.depth_registered
    assert ds.resolve_split("train") == ["seq-02", "seq-03"]
    assert ds.resolve_split("test") == ["seq-01", "seq-04"]
    assert len(ds.frames("all")) == 12 and len(ds.frames("train")) == 6
    frame = ds.frames("test")[0]
    assert frame.image_path.suffix == ".jpg" and read_image(frame.image_path).shape == (480, 640, 3)
    assert (frame.camera.fx, frame.camera.cx) == (525.0, 320.0)
    # the depth is the Kinect's depth camera's, at the depth maps' 640x480, with its rig pose
    assert frame.depth_camera == Camera(640, 480, 585.0, 585.0, 320.0, 240.0)
    assert read_depth(frame.depth_path).shape == (480, 640)
    np.testing.assert_allclose(frame.rgb_from_depth.matrix(), np.array(SEVENSCENES_RGB_FROM_DEPTH),
                               atol=1e-9)
    assert all(f.depth_camera == frame.depth_camera for f in ds.frames("all"))


@needs(REDKITCHEN)
def test_redkitchen_layout():
    ds = load_dataset(REDKITCHEN)
    assert len(ds.frames("train")) == 400 and len(ds.frames("test")) == 200
    f = ds.frames("test")[0]
    assert f.name == "seq-02/frame-000000"
    rot = f.world_from_cam.rotation
    np.testing.assert_allclose(rot.T @ rot, np.eye(3), atol=1e-6)
    depth = read_depth(f.depth_path)
    assert depth.dtype == np.float32 and 0.3 < np.median(depth[depth > 0]) < 5


def test_invalid_depth_values_read_as_zero(tmp_path):
    raw = np.tile(np.array([[0, 1000], [65535, 2500]], np.uint16), (8, 8))  # 16 x 16 pixels
    cv2.imwrite(str(tmp_path / "d.png"), raw)
    np.testing.assert_allclose(read_depth(tmp_path / "d.png"),
                               np.tile([[0, 1.0], [0, 2.5]], (8, 8)))


def test_synthetic_scene_is_detected(scene_dir):
    ds = load_dataset(scene_dir)
    assert ds.kind == "synthetic" and ds.depth_registered
    assert [len(ds.frames(r)) for r in ("map", "query", "kidnap", "unlabelled")] == [
        SMALL_SCENE.n_map, SMALL_SCENE.n_query, SMALL_SCENE.n_kidnap, SMALL_SCENE.n_unlabelled]
    assert ds.resolve_split("train") == ["seq-01"] and ds.resolve_split("test") == ["seq-02"]
    assert ds.frames("test")[0].camera.fx == SMALL_SCENE.fx  # from intrinsics.txt
    assert all(f.depth_camera is None and f.rgb_from_depth is None  # registered depth
               for f in ds.frames("all"))


def _copy_scene(scene_dir, tmp_path, n=3):
    """A 7-Scenes copy of the first n frames of seq-01."""
    root = tmp_path / "ds"
    (root / "seq-01").mkdir(parents=True)
    for f in sorted((scene_dir / "seq-01").iterdir())[: 3 * n]:
        shutil.copy(f, root / "seq-01" / f.name)
    return root


def test_intrinsics_override_and_validation(scene_dir, tmp_path):
    root = _copy_scene(scene_dir, tmp_path)
    np.savetxt(root / "intrinsics.txt", [[300, 0, 160], [0, 310, 120], [0, 0, 1]])
    assert load_dataset(root).frames()[0].camera.fy == 310
    np.savetxt(root / "intrinsics.txt", [[-300, 0, 160], [0, 310, 120], [0, 0, 1]])
    with pytest.raises(InputError, match="intrinsics.txt.*positive"):
        load_dataset(root)
    np.savetxt(root / "intrinsics.txt", [[300, 0, 160], [0, 310, 120]])
    with pytest.raises(InputError, match="3x3"):
        load_dataset(root)


def test_tum_layout(scene_dir, tmp_path):
    """A TUM RGB-D folder made from synthetic frames: timestamps associate poses and depth."""
    from slamreloc.geometry import tum_line

    src = load_dataset(scene_dir).frames("train")[:4]
    root = tmp_path / "tum"
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rgb, depth, gt = [], [], []
    for i, f in enumerate(src):
        t = 100.0 + i / 30
        shutil.copy(f.image_path, root / "rgb" / f"{t:.6f}.png")
        d = (read_depth(f.depth_path) * 5000).astype(np.uint16)
        cv2.imwrite(str(root / "depth" / f"{t + 0.004:.6f}.png"), d)
        rgb.append(f"{t:.6f} rgb/{t:.6f}.png")
        depth.append(f"{t + 0.004:.6f} depth/{t + 0.004:.6f}.png")
        gt.append(tum_line(f"{t + 0.001:.6f}", f.world_from_cam))
    for name, lines in (("rgb.txt", rgb), ("depth.txt", depth), ("groundtruth.txt", gt)):
        (root / name).write_text("# header\n" + "\n".join(lines) + "\n")
    ds = load_dataset(root)
    assert ds.kind == "tum" and len(ds.frames()) == 4 and ds.depth_registered
    for got, want in zip(ds.frames(), src):
        np.testing.assert_allclose(got.world_from_cam.matrix(), want.world_from_cam.matrix(),
                                   atol=1e-5)
        d_got = read_depth(got.depth_path, ds.depth_units_per_metre)
        assert np.abs(d_got - read_depth(want.depth_path)).max() < 1e-3


@pytest.mark.parametrize("content, message", [
    ("1 0 0 0\n0 1 0 0\n0 0 1 0\n", "4x4"),
    ("1 0 0 0\n0 2 0 0\n0 0 1 0\n0 0 0 1\n", "not orthonormal"),
    ("a b c d\n", "not a numeric matrix"),
])
def test_malformed_pose_names_the_file(tmp_path, content, message):
    path = tmp_path / "frame-000000.pose.txt"
    path.write_text(content)
    with pytest.raises(InputError, match=message) as err:
        read_pose(path)
    assert str(path) in str(err.value)


def test_unknown_layout_and_missing_folder(tmp_path):
    with pytest.raises(InputError, match="not found"):
        load_dataset(tmp_path / "nope")
    (tmp_path / "x.txt").write_text("hi")
    with pytest.raises(InputError, match="not a known dataset layout"):
        load_dataset(tmp_path)


def test_unreadable_and_empty_images(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_image(tmp_path / "missing.png")
    (tmp_path / "empty.png").write_bytes(b"")
    with pytest.raises(InputError, match="empty.png.*not a readable image"):
        read_image(tmp_path / "empty.png")
