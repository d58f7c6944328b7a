"""ATE, Umeyama alignment, TUM files: against evo, and round trips (hypothesis)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slamreloc.datasets.poses import FrameKey
from slamreloc.errors import InputError
from slamreloc.geometry import Rigid3, axis_angle_to_matrix, read_tum_trajectory
from slamreloc.geometry import write_tum_trajectory as write_tum
from slamreloc.slam.external import TrajectoryOdometry
from slamreloc.slam.metrics import ate_rmse, umeyama_se3
from slamreloc.slam.run import kidnap_schedule

vec3 = st.tuples(*[st.floats(-3, 3, allow_nan=False)] * 3).map(np.array)


def random_trajectory(rng, n):
    return [Rigid3(axis_angle_to_matrix(rng.normal(size=3)), rng.normal(size=3))
            for _ in range(n)]


@settings(max_examples=50, deadline=None)
@given(rotvec=vec3, shift=vec3, seed=st.integers(0, 2**16))
def test_umeyama_recovers_a_rigid_transform(rotvec, shift, seed):
    points = np.random.default_rng(seed).normal(size=(20, 3))
    target_from_source = Rigid3(axis_angle_to_matrix(rotvec), shift)
    got = umeyama_se3(points, target_from_source.transform(points))
    assert np.allclose(got.rotation, target_from_source.rotation, atol=1e-6)
    assert np.allclose(got.translation, target_from_source.translation, atol=1e-6)


@settings(max_examples=30, deadline=None)
@given(rotvec=vec3, shift=vec3, seed=st.integers(0, 2**16))
def test_aligned_ate_ignores_a_rigid_offset(rotvec, shift, seed):
    truth = random_trajectory(np.random.default_rng(seed), 15)
    offset = Rigid3(axis_angle_to_matrix(rotvec), shift)
    moved = [offset @ p for p in truth]
    assert ate_rmse(moved, truth, align=True) < 1e-6
    expected = np.sqrt(np.mean([np.sum((m.translation - t.translation) ** 2)
                                for m, t in zip(moved, truth)]))
    assert ate_rmse(moved, truth) == pytest.approx(expected)


@pytest.mark.parametrize("align", [False, True])
def test_ate_agrees_with_evo(tmp_path, align):
    from evo.core import metrics, sync
    from evo.tools import file_interface

    rng = np.random.default_rng(3)
    truth = random_trajectory(rng, 40)
    est = [Rigid3(p.rotation, p.translation + rng.normal(scale=0.1, size=3) + [0.3, 0, 0])
           for p in truth]
    stamps = [i / 30 for i in range(40)]
    write_tum(tmp_path / "ref.txt", stamps, truth, ["reference"])
    write_tum(tmp_path / "est.txt", stamps, est)
    ref = file_interface.read_tum_trajectory_file(str(tmp_path / "ref.txt"))
    evo_est = file_interface.read_tum_trajectory_file(str(tmp_path / "est.txt"))
    ref, evo_est = sync.associate_trajectories(ref, evo_est, max_diff=0.01)
    if align:
        evo_est.align(ref)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, evo_est))
    ours = ate_rmse(_poses(tmp_path / "est.txt"), _poses(tmp_path / "ref.txt"), align)
    assert ours == pytest.approx(ape.get_statistic(metrics.StatisticsType.rmse), rel=1e-5)


def _poses(path):
    """The camera-to-world poses of a TUM trajectory file, in file order."""
    return [pose for _, pose in read_tum_trajectory(path, numeric_stamps=True)]


@pytest.mark.parametrize("text, problem", [
    ("0.0 1 2 3 0 0 0\n", "expected 8 fields"),
    ("frame-1 1 2 3 0 0 0 1\n", "not a number"),
    ("0.0 1 2 x 0 0 0 1\n", "non-numeric"),
])
def test_malformed_tum_is_an_input_error(tmp_path, text, problem):
    path = tmp_path / "odo.txt"
    path.write_text(text)
    with pytest.raises(InputError, match=problem):
        read_tum_trajectory(path, numeric_stamps=True)


def test_odometry_file_without_poses_is_an_input_error(tmp_path):
    path = tmp_path / "odo.txt"
    path.write_text("# only a comment\n")
    with pytest.raises(InputError, match="no poses"):
        TrajectoryOdometry.from_file(path, [FrameKey("f0", None, 0.0)])


def test_kidnap_schedule():
    kept, jumps = kidnap_schedule(200, 40, 20)
    assert kept[:41] == [*range(40), 60] and jumps == [40, 80, 120] and len(kept) == 140
    assert kidnap_schedule(10, 0, 20) == (list(range(10)), [])
