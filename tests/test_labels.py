"""Scene-coordinate labels on the synthetic scene, checked against its exact depth."""

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slamreloc.datasets import load_dataset, read_depth
from slamreloc.features.extract import extract_frames
from slamreloc.features import make_extractor
from slamreloc.geometry import project
from slamreloc.map.labels import LabelConfig, build_labels, depth_points


@pytest.fixture(scope="module")
def map_frames(scene_dir):
    ds = load_dataset(scene_dir)
    frames = ds.frames("train")[:30]
    feats = extract_frames(frames, make_extractor("sift"), progress=False)
    depths = [read_depth(f.depth_path) for f in frames]
    return frames, feats, depths


def test_triangulated_labels_agree_with_true_depth(map_frames):
    """Without depth, multi-view triangulation alone must put points within a few cm."""
    frames, feats, depths = map_frames
    labels = build_labels(frames, feats, None, LabelConfig(), progress=False)
    truth = np.concatenate([depth_points(f, ft.keypoints, d)
                            for f, ft, d in zip(frames, feats, depths)])
    got = np.concatenate(labels.points)
    both = ~np.isnan(got[:, 0]) & ~np.isnan(truth[:, 0])
    err = np.linalg.norm(got[both] - truth[both], axis=1)
    assert labels.stats["n_labelled"] > 0.25 * labels.stats["n_keypoints"]
    assert labels.stats["mean_track_length"] > 2.5
    assert labels.stats["median_reproj_error_px"] < 1.0
    assert np.median(err) < 0.01 and np.percentile(err, 90) < 0.05


def test_registered_depth_refines_track_labels(map_frames):
    """Depth replaces triangulated points of tracked keypoints; single-view keypoints stay
    unlabelled, and tracks that disagree with depth are rare."""
    frames, feats, depths = map_frames
    tri = build_labels(frames, feats, None, LabelConfig(), progress=False)
    dep = build_labels(frames, feats, depths, LabelConfig(), progress=False)
    assert 0.9 * tri.stats["n_labelled"] <= dep.stats["n_labelled"] <= tri.stats["n_labelled"]
    assert dep.stats["n_track_depth_disagreements"] < 0.05 * tri.stats["n_labelled"]
    for pts, tracks in zip(dep.points, dep.track_ids):
        assert np.all(tracks[~np.isnan(pts[:, 0])] >= 0)


def test_labels_reproject_into_their_frames(map_frames):
    frames, feats, depths = map_frames
    labels = build_labels(frames, feats, depths, LabelConfig(), progress=False)
    for f, ft, pts in list(zip(frames, feats, labels.points))[::7]:
        ok = ~np.isnan(pts[:, 0])
        cam = f.world_from_cam.inverse().transform(pts[ok].astype(np.float64))
        uv = cam[:, :2] / cam[:, 2:] * [f.camera.fx, f.camera.fy] + [f.camera.cx, f.camera.cy]
        assert np.median(np.linalg.norm(uv - ft.keypoints[ok], axis=1)) < 1.0


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2 ** 31 - 1), n_views=st.integers(2, 8),
       noise_px=st.floats(0.0, 0.3), start_offset_m=st.floats(0.0, 0.05))
def test_refined_track_points_are_the_least_squares_points(seed, n_views, noise_px,
                                                          start_offset_m):
    """`refine_track_points` (structure-only bundle adjustment, poses fixed) moves each track's
    point, from a start a few cm off, to the point of least squared reprojection error over
    its observations (scipy's least_squares on the same residuals), two tracks at once. With
    residuals under the Huber threshold (1 px) the two objectives are the same."""
    from scipy.optimize import least_squares

    from slamreloc.geometry import look_at
    from slamreloc.map.labels import refine_track_points
    from slamreloc.types import Camera, Frame

    rng = np.random.default_rng(seed)
    camera = Camera(640, 480, 525.0, 520.0, 320.0, 240.0)
    targets = rng.uniform(-0.3, 0.3, (2, 3)) + [0.0, 2.0, 1.0]
    eyes = rng.uniform([-0.5, -0.2, 0.7], [0.5, 0.3, 1.3], (n_views, 3))
    frames = [Frame(f"f{i}", Path("none"), camera, world_from_cam=look_at(eye, [0.0, 2.0, 1.0]))
              for i, eye in enumerate(eyes)]

    def pixels(point, frame):
        cam = frame.world_from_cam.inverse().transform(point[None])
        return project(cam, *camera.params())[0]

    kp, frame_of, track_of, start = [], [], [], []
    for t, target in enumerate(targets):
        for k, frame in enumerate(frames):
            kp.append(pixels(target, frame) + rng.uniform(-noise_px, noise_px, 2))
            frame_of.append(k)
            track_of.append(t)
        start += [target + start_offset_m * rng.standard_normal(3) / np.sqrt(3)] * n_views
    kp, frame_of, track_of = np.array(kp), np.array(frame_of), np.array(track_of)
    refined = refine_track_points(np.array(start), kp, frame_of, track_of, frames)
    for t in range(2):
        rows = np.flatnonzero(track_of == t)
        assert np.ptp(refined[rows], axis=0).max() == 0  # one point per track
        best = least_squares(lambda p: np.concatenate(
            [pixels(p, frames[frame_of[r]]) - kp[r] for r in rows]), targets[t],
            xtol=1e-14, ftol=1e-14, gtol=1e-14).x
        assert np.linalg.norm(refined[rows[0]] - best) < 1e-6, (refined[rows[0]], best)
