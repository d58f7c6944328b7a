"""Guided matching (`slamreloc.localize.guided`) and the regressor's guided refinement, on the
small synthetic scene (its database labels come from rendered depth, so they are exact)."""

import shutil

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slamreloc.datasets import load_dataset, read_depth, read_image
from slamreloc.geometry import Rigid3, axis_angle_to_matrix, look_at, pose_error
from slamreloc.localize.guided import GuidedConfig, GuidedMatcher
from slamreloc.map.labels import depth_points
from slamreloc.localize.localizer import make_localizer
from slamreloc.localize.pnp import refine_from
from slamreloc.map.scene_map import MapDatabase, SceneMap


def _queries(scene_dir, n=None):
    return load_dataset(scene_dir).frames("test")[:n]


def _nudged(cam_from_world: Rigid3, rng) -> Rigid3:
    """The pose moved by 1 cm and turned by 0.3 deg in random directions (a regressor's
    typical error is smaller)."""
    axis = rng.normal(size=3)
    turn = Rigid3(axis_angle_to_matrix(axis / np.linalg.norm(axis) * np.radians(0.3)),
                  np.zeros(3))
    shift = rng.normal(size=3)
    return Rigid3(np.eye(3), 0.01 * shift / np.linalg.norm(shift)) @ turn @ cam_from_world


def test_matches_from_a_nudged_pose_are_mostly_the_keypoints_own_points(small_map, scene_dir):
    """From a pose 1 cm / 0.3 deg off, most guided matches' database points are the query
    keypoint's true world point (from the query's rendered depth). Measured: median 2.6 mm,
    84 % within 2 cm; the rest are a neighbouring point 2-4 cm away, the only one within
    6 px, and reproject 3-6 px off where the true ones reproject within ~1 px. The refinement
    on them (robust loss) lands within 1.2-4.9 mm / 0.04-0.16 deg of the truth."""
    matcher = GuidedMatcher(small_map.database)
    loc = make_localizer(small_map, "regressor")
    rng = np.random.default_rng(0)
    errors, counts, refined = [], [], []
    for query in _queries(scene_dir, 8):
        feats = loc.extractor.extract(read_image(query.image_path), query.camera)
        start = _nudged(query.world_from_cam.inverse(), rng)
        p2d, p3d = matcher.correspondences(start, feats, query.camera)
        truth = depth_points(query, p2d, read_depth(query.depth_path))
        seen = np.isfinite(truth).all(1)
        errors.append(np.linalg.norm(p3d[seen] - truth[seen], axis=1))
        counts.append(len(p2d))
        pose = refine_from(start, p2d, p3d, query.camera.pinhole, loc.pnp,
                           max_error_px=matcher.config.radius_px)
        refined.append(pose_error(pose.inverse(), query.world_from_cam))
    errors, refined = np.concatenate(errors), np.array(refined)
    assert min(counts) >= 100, counts
    assert np.median(errors) < 0.005 and np.mean(errors < 0.02) > 0.75
    assert refined[:, 0].max() < 0.0075 and refined[:, 1].max() < 0.25  # from 1 cm, 0.3 deg
    assert np.median(refined[:, 0]) < 0.004


def test_guided_refinement_is_more_precise_than_the_regressed_points(small_map, scene_dir):
    """Measured on this scene: median 0.59 cm and 16 of 20 queries within 1 cm on the regressed
    points; 0.24 cm and 20 of 20 after the guided refinement."""
    errors = {}
    for name, guided in (("regressed", None), ("guided", GuidedConfig())):
        loc = make_localizer(small_map, "regressor", guided=guided)
        found = []
        for query in _queries(scene_dir):
            result = loc.localize(read_image(query.image_path), query.camera)
            assert result.estimate.success
            assert (result.n_guided > 0) == (guided is not None)
            found.append(pose_error(result.estimate.world_from_cam, query.world_from_cam))
        errors[name] = np.array(found)
    guided, regressed = errors["guided"], errors["regressed"]
    assert np.median(guided[:, 0]) < 0.7 * np.median(regressed[:, 0])
    assert np.mean(guided[:, 0] < 0.01) >= 0.9 and np.mean(guided[:, 1] < 1.0) == 1.0


def test_a_pose_no_training_camera_looks_along_matches_nothing(small_map, scene_dir):
    """A camera at a query's place looking where no training camera looked (more than 45 deg
    from every training camera's axis): no rows, no matches."""
    matcher = GuidedMatcher(small_map.database)
    axes = np.asarray(small_map.database.world_from_cam)[:, :3, 2]
    i = np.arange(500) + 0.5  # directions spread evenly over the sphere
    polar, azimuth = np.arccos(1 - 2 * i / 500), np.pi * (1 + 5 ** 0.5) * i
    directions = np.column_stack([np.sin(polar) * np.cos(azimuth),
                                  np.sin(polar) * np.sin(azimuth), np.cos(polar)])
    unseen = directions[np.argmin((directions @ axes.T).max(axis=1))]
    assert (axes @ unseen).max() < np.cos(np.radians(45))
    query = _queries(scene_dir, 1)[0]
    eye = query.world_from_cam.translation
    up = (1.0, 0.0, 0.0) if abs(unseen[0]) < 0.9 else (0.0, 1.0, 0.0)
    away = look_at(eye, eye + unseen, up).inverse()
    feats = make_localizer(small_map, "regressor").extractor.extract(
        read_image(query.image_path), query.camera)
    assert len(matcher.nearby_rows(away)) == 0
    p2d, p3d = matcher.correspondences(away, feats, query.camera)
    assert p2d.shape == (0, 2) and p3d.shape == (0, 3)


@settings(max_examples=10, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_matches_do_not_depend_on_the_world_frame(small_map, scene_dir, seed):
    """Moving the whole map (database points and training cameras) and the pose by one rigid
    motion gives the same keypoints matched to the moved points."""
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    motion = Rigid3(axis_angle_to_matrix(axis / np.linalg.norm(axis) * rng.uniform(0, np.pi)),
                    rng.uniform(-5, 5, 3))
    db = small_map.database
    moved_db = MapDatabase(db.descriptors, motion.transform(db.points.astype(np.float64))
                           .astype(np.float32), db.keypoints, db.frame_index, db.frame_names,
                           np.array([(motion @ Rigid3.from_matrix(w)).matrix() for w in
                                     db.world_from_cam]))
    query = _queries(scene_dir, 1)[0]
    feats = make_localizer(small_map, "regressor", guided=None).extractor.extract(
        read_image(query.image_path), query.camera)
    cam_from_world = _nudged(query.world_from_cam.inverse(), rng)
    a2d, a3d = GuidedMatcher(db).correspondences(cam_from_world, feats, query.camera)
    b2d, b3d = GuidedMatcher(moved_db).correspondences(cam_from_world @ motion.inverse(),
                                                       feats, query.camera)
    assert len(a2d) > 100 and np.array_equal(a2d, b2d)
    np.testing.assert_allclose(motion.transform(a3d), b3d, atol=1e-4)


def test_a_map_shipped_without_its_database_localizes_on_the_regressed_points(
        small_map, scene_dir, tmp_path):
    slim = tmp_path / "slim"
    shutil.copytree(small_map.root, slim)
    (slim / "database.npz").unlink()
    with pytest.warns(UserWarning, match="no training database"):
        loc = make_localizer(SceneMap.load(slim), "regressor")
    query = _queries(scene_dir, 1)[0]
    result = loc.localize(read_image(query.image_path), query.camera)
    unguided = make_localizer(small_map, "regressor", guided=None).localize(
        read_image(query.image_path), query.camera)
    assert result.estimate.success and result.n_guided == 0
    assert np.array_equal(result.estimate.cam_from_world.matrix(),
                          unguided.estimate.cam_from_world.matrix())


def test_one_rule_for_a_map_shipped_without_its_database(small_map, scene_dir, tmp_path):
    """database.npz deleted (the metadata still lists it): `localize` and `evaluate` localize on
    the regressed points with a warning (the report says the database has no size); the
    commands that need its rows refuse it in one line naming the file (attack round 4:
    `evaluate` ended in a bare "[Errno 2]" after the work)."""
    import json

    from tests.fuzzing import run_cli

    slim = tmp_path / "slim"
    shutil.copytree(small_map.root, slim)
    (slim / "database.npz").unlink()
    query = _queries(scene_dir, 1)[0]
    report = tmp_path / "r.json"
    for argv in (["localize", slim, query.image_path],
                 ["evaluate", slim, scene_dir, "--report", report]):
        with pytest.warns(UserWarning, match="no training database"):
            code, err = run_cli([str(a) for a in argv])
        assert code == 0, (argv, err)
    r = json.loads(report.read_text())
    assert r["map"]["database_bytes"] is None and not r["guided_refinement"]
    for argv in (["export", slim, "--tum", tmp_path / "t.txt"],
                 ["evaluate", slim, scene_dir, "--report", report, "--method", "matching"],
                 ["pseudo-label", slim, scene_dir, "--out", tmp_path / "m2",
                  "--report", tmp_path / "p.json"]):
        code, err = run_cli([str(a) for a in argv])
        lines = err.strip().splitlines()
        assert code == 2 and len(lines) == 1, (argv, err)
        assert str(slim / "database.npz") in lines[0] and "missing" in lines[0]


def test_the_step_is_left_out_on_maps_whose_labels_disagree_with_their_images(small_map,
                                                                               scene_dir):
    """The step refines onto the labels, so it runs only where they reproject within
    `max_label_error_px` (this scene's: ~0.14 px, so a limit of 0.05 px leaves it out)."""
    error = small_map.info.label_reproj_error_px
    assert error is not None and 0.05 < error < GuidedConfig().max_label_error_px
    strict = GuidedConfig(max_label_error_px=0.05)
    assert not strict.applies_to(error) and strict.applies_to(None)
    loc = make_localizer(small_map, "regressor", guided=strict)
    assert loc.guided is None
    query = _queries(scene_dir, 1)[0]
    image = read_image(query.image_path)
    result = loc.localize(image, query.camera)
    unguided = make_localizer(small_map, "regressor", guided=None).localize(image, query.camera)
    assert result.n_guided == 0 and np.array_equal(result.estimate.cam_from_world.matrix(),
                                                   unguided.estimate.cam_from_world.matrix())
    assert make_localizer(small_map, "regressor").guided is not None


class _Blurred:
    """A regressor whose world points are the map's regressor's moved by `sigma_m` (metres,
    Gaussian per axis, seeded): what a regressor looks like in a place it barely knows. With
    `scramble_confident`, the more confident half of the points is thrown anywhere in a 10 m
    box instead: the points RANSAC uses then agree on no pose."""

    def __init__(self, localizer, sigma_m: float, seed: int = 0, scramble_confident=False):
        self.localizer, self.sigma_m, self.scramble = localizer, sigma_m, scramble_confident
        self.rng = np.random.default_rng(seed)

    def __call__(self, descriptors):
        points, confidence = type(self.localizer).predict(self.localizer, descriptors)
        points = points + self.rng.normal(0, self.sigma_m, points.shape)
        if self.scramble:
            confident = np.argsort(-confidence)[:len(points) // 2]
            points[confident] = self.rng.uniform(-5, 5, (len(confident), 3))
        return points, confidence


def _near_point_errors(small_map, scene_dir, config, sigma_m):
    """World-point errors (metres) of `near_points`' matches on 6 queries whose regressed
    points are `sigma_m` off, against the keypoints' true points (rendered depth)."""
    matcher = GuidedMatcher(small_map.database, config)
    loc = make_localizer(small_map, "regressor")
    blurred = _Blurred(loc, sigma_m)
    errors = []
    for query in _queries(scene_dir, 6):
        feats = loc.extractor.extract(read_image(query.image_path), query.camera)
        index, rows = matcher.near_points(feats, blurred(feats.descriptors)[0])
        assert len(index) >= 500 and len(np.unique(index)) == len(index)
        truth = depth_points(query, feats.keypoints[index], read_depth(query.depth_path))
        seen = np.isfinite(truth).all(1)
        errors.append(np.linalg.norm(small_map.database.points[rows][seen] - truth[seen], axis=1))
    return np.concatenate(errors)


def test_the_point_gate_finds_each_keypoints_own_rows_without_a_pose(small_map, scene_dir):
    """Regressed points 1 cm off (per axis): the keypoint's own rows are among the 8 nearest
    and the descriptor picks them; no pose went in. Measured: median 3.8 mm, 65 % within
    2 cm (the rest: a neighbouring point of this dense scene, 48 726 rows). At 3 cm the 8
    nearest rows often miss the keypoint's own (median 2.5 cm); 32 neighbours still find them
    (3.3 mm, 70 %): the gate needs as many neighbours as a place holds rows within its
    regressor's scatter (RedKitchen: 8 and 16 scored the same, BENCHMARKS.md)."""
    errors = _near_point_errors(small_map, scene_dir, GuidedConfig(), 0.01)
    assert np.median(errors) < 0.005 and np.mean(errors < 0.02) > 0.55
    wide = _near_point_errors(small_map, scene_dir, GuidedConfig(point_neighbours=32), 0.03)
    assert np.median(wide) < 0.005 and np.mean(wide < 0.02) > 0.6
    off = GuidedMatcher(small_map.database, GuidedConfig(point_radius_m=0.0))
    query = _queries(scene_dir, 1)[0]
    feats = make_localizer(small_map, "regressor").extractor.extract(
        read_image(query.image_path), query.camera)
    assert len(off.near_points(feats, np.zeros((len(feats), 3)))[0]) == 0


def _within_1cm(small_map, scene_dir, guided, **blur) -> float:
    loc = make_localizer(small_map, "regressor", guided=guided)
    loc.predict = _Blurred(loc, **blur)
    errors = []
    for query in _queries(scene_dir, 8):
        est = loc.localize(read_image(query.image_path), query.camera).estimate
        errors.append(pose_error(est.world_from_cam, query.world_from_cam) if est.success
                      else (np.inf, np.inf))
    errors = np.array(errors)
    return float(np.mean((errors[:, 0] < 0.01) & (errors[:, 1] < 1.0)))


def test_the_guided_step_recovers_precision_from_scattered_regressed_points(small_map,
                                                                            scene_dir):
    """Regressed points 2 cm off (per axis): RANSAC on them puts 2 of 8 queries within 1 cm /
    1 deg; the guided refinement (both gates) all 8."""
    assert _within_1cm(small_map, scene_dir, None, sigma_m=0.02) <= 0.5
    assert _within_1cm(small_map, scene_dir, GuidedConfig(), sigma_m=0.02) == 1.0


def test_where_the_regressed_points_find_no_pose_the_rows_near_them_do(small_map, scene_dir):
    """The confident half of the regressed points scattered over 10 m (RANSAC uses that half,
    so it finds no pose), the rest 1 cm off: without the guided step no query is localized;
    with it RANSAC runs on the rows near all the regressed points (measured: 7 of 8 queries
    within 1 cm / 1 deg)."""
    blur = dict(sigma_m=0.01, scramble_confident=True)
    assert _within_1cm(small_map, scene_dir, None, **blur) == 0.0
    assert _within_1cm(small_map, scene_dir, GuidedConfig(), **blur) >= 0.75
