"""Simulated views (`slamreloc.map.augment`, `map --augment-views`): the warps, where their
keypoints land, and a map trained with them."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from slamreloc.map.augment import AugmentConfig, augmented_rows, random_affine


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), width=st.integers(16, 4000), height=st.integers(16, 4000),
       tilt=st.floats(1.0, 4.0), zoom=st.floats(0.5, 1.0))
def test_a_warp_keeps_the_centre_and_stays_within_its_bounds(seed, width, height, tilt, zoom):
    """The warp turns about the image centre; it squeezes by at most 1/max_tilt and zooms
    within `scale`; it never mirrors."""
    config = AugmentConfig(views=1, max_tilt=tilt, scale=(zoom, 1 / zoom))
    affine = random_affine(np.random.default_rng(seed), width, height, config)
    centre = np.array([width / 2, height / 2])
    np.testing.assert_allclose(affine[:, :2] @ centre + affine[:, 2], centre, atol=1e-6 * width)
    singular = np.linalg.svd(affine[:, :2], compute_uv=False)
    assert singular.max() <= 1 / zoom * (1 + 1e-9)
    assert singular.min() >= zoom / tilt * (1 - 1e-9)
    assert np.linalg.det(affine[:, :2]) > 0


def test_simulated_views_take_the_points_of_the_same_features(scene_dir):
    """Each simulated row's descriptor describes the feature whose point it takes: the frame's
    keypoint nearest it in descriptor space is that keypoint, or one at the same pixel (SIFT
    gives a blob one keypoint per dominant orientation; they share the blob's point) for most
    rows (88 % here; a wrong warp back gives ~0 %); the rest are descriptors the warp moved past
    another keypoint's, the change a new viewpoint makes, which is what the rows teach."""
    from slamreloc.datasets import load_dataset
    from slamreloc.features import make_extractor
    from slamreloc.features.extract import extract_frames

    frames = load_dataset(scene_dir).frames("train")[:6]
    extractor = make_extractor("sift")
    feats = extract_frames(frames, extractor, progress=False)
    # stand-in labels that name each keypoint: its frame, its index, 0
    points = [np.stack([np.full(len(f), i), np.arange(len(f)), np.zeros(len(f))], 1)
              .astype(np.float32) for i, f in enumerate(feats)]
    for p in points:
        p[::3] = np.nan  # unlabelled keypoints give no rows
    desc, pts = augmented_rows(frames, feats, points, extractor, AugmentConfig(views=2),
                               progress=False)
    assert len(desc) > 100 and desc.shape[1] == extractor.dim and pts.shape == (len(desc), 3)
    frame, index = pts[:, 0].astype(int), pts[:, 1].astype(int)
    assert not np.any(index % 3 == 0)
    apart = []
    for d, i, k in zip(desc, frame, index):
        best = np.argmin(np.linalg.norm(feats[i].descriptors - d, axis=1))
        apart.append(np.linalg.norm(feats[i].keypoints[best] - feats[i].keypoints[k]))
    assert np.mean(np.array(apart) <= 1.0) > 0.75, np.mean(np.array(apart) <= 1.0)


def test_map_with_simulated_views_records_them(scene_dir, tmp_path):
    """`map --augment-views 2` trains on more rows than its database holds, says so in the
    map's metadata, and the map localizes."""
    out = tmp_path / "map"
    run = subprocess.run([sys.executable, "-m", "slamreloc.cli", "map", str(scene_dir), "--out",
                          str(out), "--epochs", "3", "--augment-views", "2"],
                         capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    meta = json.loads((out / "slamreloc_map.json").read_text())
    train = meta["train"]
    assert train["augment"]["views"] == 2 and train["n_augmented_rows"] > 0
    assert "augment_s" in meta["timings_s"]
    res = subprocess.run([sys.executable, "-m", "slamreloc.cli", "evaluate", str(out),
                          str(scene_dir), "--report", str(tmp_path / "r.json")],
                         capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert json.loads((tmp_path / "r.json").read_text())["n_localized"] > 0


def test_augment_views_out_of_range_is_one_line(scene_dir, tmp_path):
    for value in ("17", "-1"):
        res = subprocess.run([sys.executable, "-m", "slamreloc.cli", "map", str(scene_dir),
                              "--out", str(tmp_path / "m"), "--augment-views", value],
                             capture_output=True, text=True)
        assert res.returncode == 2 and res.stderr.count("\n") == 1, res.stderr
        assert "--augment-views must be in 0..16" in res.stderr
        assert not (tmp_path / "m").exists()
