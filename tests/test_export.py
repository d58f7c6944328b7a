"""`slamreloc export`: the map's points and training cameras read back by pycolmap, open3d and
the TUM reader, equal to the map's own."""

from __future__ import annotations

import numpy as np
import pytest

from slamreloc.geometry import names_sidecar, read_tum_trajectory
from slamreloc.io.images import read_image
from tests.fuzzing import run_cli


@pytest.fixture(scope="module")
def exported(small_map, tmp_path_factory):
    out = tmp_path_factory.mktemp("export")
    code, err = run_cli(["export", str(small_map.root), "--colmap", str(out / "colmap"),
                         "--ply", str(out / "map.ply"), "--tum", str(out / "train.txt")], 300)
    assert code == 0, err
    return out


def test_colmap_model_round_trip(small_map, scene_dir, exported):
    """pycolmap reads the model: its 3D points are the map's distinct points, its images the
    training cameras (cam_from_world = the inverse of the map's world_from_cam), each
    observation a database keypoint (COLMAP's +0.5 pixel convention) of that point."""
    import pycolmap

    rec = pycolmap.Reconstruction(str(exported / "colmap"))
    db = small_map.database
    points = {pid: p for pid, p in rec.points3D.items()}
    xyz = np.array([p.xyz for p in points.values()])
    unique = np.unique(db.points.astype(np.float64), axis=0)
    assert len(xyz) == len(unique)
    np.testing.assert_array_equal(np.unique(xyz, axis=0), unique)
    assert sum(p.track.length() for p in points.values()) == len(db.points)
    cam = rec.cameras[1]
    assert cam.model.name == "PINHOLE" and (cam.width, cam.height) == (
        small_map.camera.width, small_map.camera.height)
    assert cam.principal_point_x == pytest.approx(small_map.camera.cx + 0.5)
    assert len(rec.images) == len(db.frame_names)
    for image_id, image in rec.images.items():
        i = image_id - 1
        pose = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
        np.testing.assert_allclose(pose.matrix(), np.linalg.inv(db.world_from_cam[i])[:3],
                                   atol=1e-6)
        assert image.name.startswith(db.frame_names[i])  # the image file, relative to the dataset
        rows = np.flatnonzero(db.frame_index == i)
        p2d = np.array([p.xy for p in image.points2D])
        np.testing.assert_allclose(p2d, db.keypoints[rows] + 0.5, atol=1e-4)
        ids = [p.point3D_id for p in image.points2D]
        np.testing.assert_allclose([points[k].xyz for k in ids], db.points[rows], atol=1e-6)


def test_ply_has_the_points_with_their_image_colours(small_map, scene_dir, exported):
    import open3d as o3d

    cloud = o3d.io.read_point_cloud(str(exported / "map.ply"))
    xyz = np.asarray(cloud.points)
    db = small_map.database
    assert len(xyz) == len(np.unique(db.points, axis=0))
    # the first database row's point has the colour of its keypoint's pixel
    row = 0
    hit = np.flatnonzero(np.all(np.abs(xyz - db.points[row]) < 1e-6, axis=1))
    assert len(hit) == 1
    name = db.frame_names[db.frame_index[row]]
    frame = next(f for f in small_map_frames(scene_dir) if f.name == name)
    x, y = np.round(db.keypoints[row]).astype(int)
    colour = read_image(frame.image_path)[y, x]
    np.testing.assert_allclose(np.asarray(cloud.colors)[hit[0]] * 255, colour, atol=0.5)


def small_map_frames(scene_dir):
    from slamreloc.datasets import load_dataset

    return load_dataset(scene_dir).frames("all")


def test_tum_training_poses(small_map, exported):
    rows = read_tum_trajectory(exported / "train.txt", numeric_stamps=True)
    db = small_map.database
    assert len(rows) == len(db.frame_names)
    for (_, pose), m in zip(rows, db.world_from_cam):
        np.testing.assert_allclose(pose.matrix(), m, atol=1e-5)
    names = [ln.split()[1] for ln in names_sidecar(exported / "train.txt").read_text()
             .splitlines()]
    assert names == list(db.frame_names)


def test_export_refuses_bad_requests(small_map, tmp_path):
    code, err = run_cli(["export", str(small_map.root)])
    assert code == 2 and "nothing to write" in err
    code, err = run_cli(["export", str(small_map.root), "--colmap", str(small_map.root / "c")])
    assert code == 2 and "inside the map" in err
    (tmp_path / "keep").mkdir()
    (tmp_path / "keep" / "precious.txt").write_text("x")
    code, err = run_cli(["export", str(small_map.root), "--colmap", str(tmp_path / "keep")])
    assert code == 2 and "not empty" in err and "--colmap" in err
    assert (tmp_path / "keep" / "precious.txt").read_text() == "x"
