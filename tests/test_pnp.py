"""PnP-RANSAC and its final refinement (`slamreloc.pnp`), on synthetic correspondences."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from slamreloc.geometry import look_at, pose_error
from slamreloc.localizer import REGRESSOR_PNP
from slamreloc.pnp import PnPConfig, estimate_pose
from slamreloc.types import Camera

CAMERA = Camera(640, 480, 525.0, 525.0, 320.0, 240.0)


def scene(rng: np.random.Generator, n: int = 400):
    """A camera ~2 m from a cloud of world points (metres) it sees, and their pixels."""
    eye = rng.uniform(-1, 1, 3) + np.array([0.0, 0.0, -2.0])
    world_from_cam = look_at(eye, rng.uniform(-0.2, 0.2, 3), up=(0, -1, 0))
    cam = np.column_stack([rng.uniform(-0.8, 0.8, n), rng.uniform(-0.6, 0.6, n),
                           rng.uniform(1.2, 3.5, n)])
    cam[:, :2] *= cam[:, 2:] / 2.0
    pixels = np.column_stack([CAMERA.fx * cam[:, 0] / cam[:, 2] + CAMERA.cx,
                              CAMERA.fy * cam[:, 1] / cam[:, 2] + CAMERA.cy])
    return world_from_cam, world_from_cam.transform(cam), pixels


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31 - 1), st.sampled_from([1.0, 4.0]))
def test_exact_correspondences_give_the_exact_pose(seed, loss_px):
    world_from_cam, points, pixels = scene(np.random.default_rng(seed))
    est = estimate_pose(pixels, points, CAMERA, PnPConfig(refine_loss_px=loss_px))
    dt, dr = pose_error(est.world_from_cam, world_from_cam)
    assert est.num_inliers == len(points) and dt < 1e-6 and dr < 1e-4


def test_a_loss_scaled_to_regression_noise_is_more_precise():
    """Regressed world points scatter by centimetres: with 3 px of noise on the inliers (and
    30 % outliers) the regressor's refinement (Cauchy scale 4 px) is more precise than
    pycolmap's 1 px over 40 seeded scenes (median translation error)."""
    errors = {1.0: [], REGRESSOR_PNP.refine_loss_px: []}
    for seed in range(40):
        rng = np.random.default_rng(seed)
        world_from_cam, points, pixels = scene(rng)
        noisy = pixels + rng.normal(0, 3.0, pixels.shape)
        out = rng.random(len(points)) < 0.3
        noisy[out] = rng.uniform([0, 0], [640, 480], (out.sum(), 2))
        for loss, found in errors.items():
            est = estimate_pose(noisy, points, CAMERA, PnPConfig(refine_loss_px=loss))
            found.append(pose_error(est.world_from_cam, world_from_cam)[0])
    assert np.median(errors[REGRESSOR_PNP.refine_loss_px]) < 0.9 * np.median(errors[1.0])


def test_too_few_inliers_is_a_failure_not_a_pose():
    rng = np.random.default_rng(0)
    _, points, _ = scene(rng, 60)
    est = estimate_pose(rng.uniform([0, 0], [640, 480], (60, 2)), points, CAMERA)
    assert not est.success and est.world_from_cam is None and est.confidence == 0.0

