"""Scene-coordinate labels on the synthetic scene, checked against its exact depth."""

import numpy as np
import pytest

from slamreloc.datasets import load_dataset, read_depth
from slamreloc.extract import extract_frames
from slamreloc.features import make_extractor
from slamreloc.labels import LabelConfig, build_labels, depth_points


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
