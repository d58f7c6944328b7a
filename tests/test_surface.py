"""The map's depth surface and ICP refinement: built with the map, checked on load, and pulling
perturbed poses of the synthetic scene onto the truth."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slamreloc.datasets import load_dataset, read_depth
from slamreloc.errors import InputError
from slamreloc.geometry import Rigid3, axis_angle_to_matrix, pose_error, read_named_trajectory
from slamreloc.map.format import SURFACE
from slamreloc.map.scene_map import SceneMap
from slamreloc.map.surface import (IcpConfig, Surface, depth_cloud, frame_cloud, refine_pose,
                                   refine_with_depth)


@pytest.fixture(scope="module")
def query(scene_dir):
    ds = load_dataset(scene_dir)
    frames = ds.frames("query")
    return [(f.world_from_cam, depth_cloud(read_depth(f.depth_path, ds.depth_units_per_metre),
                                            f.camera, f.depth_camera))
            for f in frames[::4]]


def test_a_map_of_a_depth_dataset_carries_its_surface(small_map):
    surface = small_map.surface
    assert surface is not None and len(surface.points) == small_map.meta["surface"]["n_points"]
    assert len(surface.points) > 1000
    np.testing.assert_allclose(np.linalg.norm(surface.normals, axis=1), 1, atol=1e-2)
    # every training camera sees the surface in front of it
    db = small_map.database
    cam_from_world = Rigid3.from_matrix(db.world_from_cam[0]).inverse()
    assert np.mean(cam_from_world.transform(surface.points)[:, 2] > 0) > 0.2


def _scene_points(rng) -> np.ndarray:
    """A 4 x 4 x 2.5 m room (floor, ceiling, four walls) with three balls in it."""
    g = np.linspace(0, 1, 60)
    u, v = (a.ravel() for a in np.meshgrid(g, g))
    planes = [np.stack([4 * u, 4 * v, 0 * u], 1), np.stack([4 * u, 4 * v, 0 * u + 2.5], 1),
              np.stack([0 * u, 4 * u, 2.5 * v], 1), np.stack([0 * u + 4, 4 * u, 2.5 * v], 1),
              np.stack([4 * u, 0 * u, 2.5 * v], 1), np.stack([4 * u, 0 * u + 4, 2.5 * v], 1)]
    k = np.arange(3000) + 0.5
    phi, theta = np.arccos(1 - 2 * k / 3000), np.pi * (1 + 5 ** 0.5) * k
    ball = np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], 1)
    balls = [c + r * ball for c, r in (((1.2, 1.5, 0.5), 0.4), ((2.8, 2.2, 1.2), 0.3),
                                       ((2.0, 3.0, 0.3), 0.3))]
    return np.concatenate([*planes, *balls]) + rng.normal(0, 0.002, (1, 3))


@pytest.fixture(scope="module")
def room():
    from slamreloc.map.surface import build_surface

    points = _scene_points(np.random.default_rng(0))
    return build_surface([(Rigid3.identity(), points)]), points


small = st.lists(st.floats(-1, 1), min_size=3, max_size=3).map(np.array)


@settings(max_examples=25, deadline=None)
@given(small, small)
def test_icp_pulls_a_perturbed_pose_onto_the_truth(room, shift, turn):
    """Guesses up to 8 cm / 3 deg off (a relocalization's error) end within 5 mm / 0.3 deg."""
    surface, points = room
    truth = Rigid3(axis_angle_to_matrix(np.array([1.9, 0.3, -0.2])), np.array([2.0, 2.0, 1.3]))
    cam = truth.inverse().transform(points)
    cam = cam[(cam[:, 2] > 0.3) & (np.abs(cam[:, 0]) < cam[:, 2]) & (np.abs(cam[:, 1]) < cam[:, 2])]
    guess = Rigid3(truth.rotation @ axis_angle_to_matrix(np.radians(3) * turn / np.sqrt(3)),
                   truth.translation + 0.08 * shift / np.sqrt(3))
    fit = refine_pose(surface, cam, guess)
    assert fit.accepted and fit.fitness > 0.9
    dt, dr = pose_error(fit.world_from_cam, truth)
    assert dt < 0.005 and dr < 0.3, (dt, dr, pose_error(guess, truth))


def test_icp_keeps_a_good_pose_of_the_synthetic_scene(small_map, query):
    """On the rendered room (flat walls: directions the view leaves free are not moved), a pose
    at the truth stays within 1 cm / 0.2 deg of it."""
    for world_from_cam, points in query:
        fit = refine_pose(small_map.surface, points, world_from_cam)
        assert fit.accepted and fit.fitness > 0.8
        dt, dr = pose_error(fit.world_from_cam, world_from_cam)
        assert dt < 0.01 and dr < 0.2, (dt, dr)


def test_one_depth_refinement_for_a_depth_map_and_its_camera(small_map, scene_dir):
    """`refine_with_depth` (evaluate --depth, the SLAM plugin, the service): ICP of the depth
    map's points in its camera's frame; depth of its own camera, given at another pixel size,
    is scaled to the depth map; a depth map without a valid pixel leaves the guess."""
    ds = load_dataset(scene_dir)
    f = ds.frames("query")[0]
    depth = read_depth(f.depth_path, ds.depth_units_per_metre)
    truth = f.world_from_cam
    guess = Rigid3(truth.rotation, truth.translation + np.array([0.03, -0.02, 0.01]))
    fit = refine_with_depth(small_map.surface, depth, f.camera, None, guess)
    same = refine_pose(small_map.surface, depth_cloud(depth, f.camera, None), guess)
    assert fit.accepted and pose_error(fit.chosen(), truth)[0] < 0.01
    np.testing.assert_array_equal(fit.world_from_cam.matrix(), same.world_from_cam.matrix())
    cam = f.camera  # the depth as if from a camera of its own, described at twice the size
    own = refine_with_depth(small_map.surface, depth, cam, cam.scaled_to(2 * cam.width,
                                                                         2 * cam.height), guess)
    np.testing.assert_array_equal(own.world_from_cam.matrix(), fit.world_from_cam.matrix())
    empty = refine_with_depth(small_map.surface, np.zeros_like(depth), f.camera, None, guess)
    assert not empty.accepted and empty.chosen() is guess


def test_a_view_that_is_not_on_the_surface_is_not_accepted(small_map, query):
    world_from_cam, points = query[0]
    rng = np.random.default_rng(0)
    noise = rng.uniform(-3, 3, size=(2000, 3)) + [0, 0, 4]  # a cloud of nothing in particular
    fit = refine_pose(small_map.surface, noise, world_from_cam)
    assert not fit.accepted
    far = Rigid3(world_from_cam.rotation, world_from_cam.translation + [0, 0, 20])
    assert not refine_pose(small_map.surface, points, far, IcpConfig()).accepted


def test_a_damaged_surface_is_refused_naming_the_file(small_map, tmp_path):
    import shutil

    copy = tmp_path / "map"
    shutil.copytree(small_map.root, copy)
    data = bytearray((copy / SURFACE).read_bytes())
    data[len(data) // 2] ^= 0xFF
    (copy / SURFACE).write_bytes(bytes(data))
    with pytest.raises(InputError, match=f"{SURFACE}: contents do not match"):
        SceneMap.load(copy).surface
    (copy / SURFACE).unlink()
    with pytest.raises(InputError, match="surface but the file is missing"):
        SceneMap.load(copy).surface


@pytest.mark.parametrize("arrays, message", [
    ({"points": np.zeros((5, 3), np.float32)}, "needs 'points' and 'normals'"),
    ({"points": np.zeros((5, 2), np.float32), "normals": np.zeros((5, 2), np.float32)},
     "must both be"),
    ({"points": np.full((5, 3), np.nan, np.float32), "normals": np.zeros((5, 3), np.float32)},
     "non-finite"),
    ({"points": np.zeros((5, 3), np.float32), "normals": np.zeros((5, 3), np.float16)},
     r"'normals' must be unit vectors .*5 of 5 are not, row 0 has length 0"),
    ({"points": np.zeros((2, 3), np.float32),
      "normals": np.array([[0, 0, 1], [0, 0, 1.01]], np.float32)},
     "1 of 2 are not, row 1 has length 1.01"),
])
def test_malformed_surface_arrays_are_named(arrays, message):
    with pytest.raises(InputError, match=message):
        Surface.from_arrays(arrays, "m/surface.npz")


def test_stored_normals_within_float16_rounding_are_taken():
    rng = np.random.default_rng(0)
    nrm = rng.normal(size=(10000, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    surface = Surface.from_arrays({"points": np.zeros((10000, 3), np.float32),
                                   "normals": nrm.astype(np.float16)}, "m/surface.npz")
    assert len(surface.normals) == 10000


def test_zero_normals_in_a_relisted_surface_are_refused(small_map, scene_dir, tmp_path):
    """surface.npz with every normal 0 and its checksum updated in the metadata: `evaluate
    --depth` refuses the map in one line naming the file, before any ICP."""
    import json
    import shutil

    from slamreloc.map.format import META, sha256_file

    copy = tmp_path / "map"
    shutil.copytree(small_map.root, copy)
    with np.load(copy / SURFACE) as npz:
        arrays = {k: npz[k] for k in npz.files}
    arrays["normals"] = np.zeros_like(arrays["normals"])
    (copy / SURFACE).unlink()
    np.savez(copy / SURFACE, **arrays)
    meta = json.loads((copy / META).read_text())
    meta["files"][SURFACE] = sha256_file(copy / SURFACE)
    (copy / META).write_text(json.dumps(meta))
    with pytest.raises(InputError, match=f"{SURFACE}: surface 'normals' must be unit vectors"):
        SceneMap.load(copy).surface
    res = _cli("evaluate", copy, scene_dir, "--split", "query", "--depth", "--report",
               tmp_path / "r.json")
    assert res.returncode == 2, res.stderr
    assert res.stderr.strip().splitlines() == [
        f"error: {copy / SURFACE}: surface 'normals' must be unit vectors (length 1 within "
        f"0.001); {len(arrays['normals'])} of {len(arrays['normals'])} are not, row 0 has "
        "length 0"]
    assert not (tmp_path / "r.json").exists()


def _cli(*args):
    import subprocess
    import sys

    return subprocess.run([sys.executable, "-m", "slamreloc.cli", *map(str, args)],
                          capture_output=True, text=True)


# What ICP makes of a PnP pose on the rendered room, whose depth is exact: the rotation is
# pinned to the truth (a pose at the truth stays within 0.2 deg of it, the test above), and so
# is the translation except along a direction the view leaves free (a flat wall slides), where
# the PnP pose's value is kept; most views leave none free.
ICP_MAX_ROTATION_DEG = 0.2
ICP_MEDIAN_TRANSLATION_M = 0.005


def test_evaluate_with_depth_refines_every_query(small_map, scene_dir, tmp_path):
    """`evaluate --depth`: each query's PnP pose (the run without `--depth`) is replaced by the
    accepted ICP fit of its depth against the map's surface. On the synthetic room every fit is
    accepted and lands on the exact geometry, whatever the training run made of the PnP poses:
    bounds from the scene, not from the other run's recall."""
    import json

    runs, poses = {}, {}
    for name, extra in (("rgb", []), ("depth", ["--depth"])):
        res = _cli("evaluate", small_map.root, scene_dir, "--split", "query", "--report",
                   tmp_path / f"{name}.json", "--trajectory", tmp_path / f"{name}.txt", *extra)
        assert res.returncode == 0, res.stderr
        runs[name] = json.loads((tmp_path / f"{name}.json").read_text())
        traj = read_named_trajectory(tmp_path / f"{name}.txt")
        poses[name] = dict(zip(traj.names, traj.poses))
    assert runs["depth"]["refine"] == "depth" and runs["rgb"]["refine"] is None
    assert runs["depth"]["timing_ms"]["icp"] > 0
    dataset = load_dataset(scene_dir)
    frames = dataset.frames("query")
    assert runs["depth"]["n_localized"] == runs["rgb"]["n_localized"] == len(frames)

    fits = [refine_pose(small_map.surface, frame_cloud(f, dataset), poses["rgb"][f.name])
            for f in frames]
    assert sum(fit.accepted for fit in fits) == len(frames)
    translation_m = []
    for f, fit, reported in zip(frames, fits, runs["depth"]["per_query"]):
        assert reported["name"] == f.name
        # the CLI's pose is the fit (TUM files round to 1e-6)
        dt, dr = pose_error(poses["depth"][f.name], fit.world_from_cam)
        assert dt < 1e-4 and dr < 0.01, (f.name, dt, dr)
        assert fit.fitness > 0.8 and fit.rmse_m < 0.003, (f.name, fit.fitness, fit.rmse_m)
        dt, dr = pose_error(fit.world_from_cam, f.world_from_cam)
        assert dr < ICP_MAX_ROTATION_DEG, (f.name, dt, dr)
        assert abs(reported["translation_error_m"] - dt) < 1e-4
        translation_m.append(dt)
    assert np.median(translation_m) < ICP_MEDIAN_TRANSLATION_M, translation_m


def test_evaluate_with_depth_needs_a_surface(small_map, scene_dir, tmp_path):
    import json
    import shutil

    copy = tmp_path / "map"
    shutil.copytree(small_map.root, copy)
    meta = json.loads((copy / "slamreloc_map.json").read_text())
    del meta["files"][SURFACE], meta["surface"]
    (copy / "slamreloc_map.json").write_text(json.dumps(meta))
    (copy / SURFACE).unlink()
    assert SceneMap.load(copy).surface is None
    res = _cli("evaluate", copy, scene_dir, "--split", "query", "--report", tmp_path / "r.json",
               "--depth")
    assert res.returncode != 0 and "no surface" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1
