"""Pose conventions and conversions (property-based)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slamreloc.errors import InputError
from slamreloc.geometry import (Rigid3, axis_angle_to_matrix, look_at, matrix_to_quat,
                                names_sidecar, parse_tum_line, pose_error, quat_to_matrix,
                                read_named_trajectory, tum_line)

vec3 = st.lists(st.floats(-10, 10, allow_nan=False), min_size=3, max_size=3).map(np.array)
rotvec = st.lists(st.floats(-3.1, 3.1, allow_nan=False), min_size=3, max_size=3).map(np.array)
rigid = st.builds(lambda r, t: Rigid3(axis_angle_to_matrix(r), t), rotvec, vec3)


@given(rotvec)
def test_quaternion_round_trip(r):
    rot = axis_angle_to_matrix(r)
    q = matrix_to_quat(rot)
    assert q[3] >= 0 and np.isclose(np.linalg.norm(q), 1)
    np.testing.assert_allclose(quat_to_matrix(q), rot, atol=1e-9)


@given(rigid, rigid, vec3)
def test_compose_and_inverse(b_from_a, c_from_b, x):
    c_from_a = c_from_b @ b_from_a
    np.testing.assert_allclose(c_from_a.transform(x[None])[0],
                               c_from_b.transform(b_from_a.transform(x[None]))[0], atol=1e-9)
    ident = b_from_a.inverse() @ b_from_a
    np.testing.assert_allclose(ident.matrix(), np.eye(4), atol=1e-9)


@given(rigid)
def test_tum_line_round_trip(world_from_cam):
    name, back = parse_tum_line(tum_line("frame-1", world_from_cam))
    assert name == "frame-1"
    dt, dr = pose_error(back, world_from_cam)
    assert dt < 1e-5 and dr < 1e-3


@given(rigid)
@settings(max_examples=50)
def test_matrix_round_trip(pose):
    np.testing.assert_allclose(Rigid3.from_matrix(pose.matrix()).matrix(), pose.matrix(),
                               atol=1e-9)


def test_pose_error_known_values():
    a = Rigid3.identity()
    b = Rigid3(axis_angle_to_matrix([0, 0, np.radians(10)]), np.array([0.03, 0.04, 0]))
    dt, dr = pose_error(b, a)
    assert np.isclose(dt, 0.05) and np.isclose(dr, 10.0)


def test_look_at_points_the_camera_axis_at_the_target():
    world_from_cam = look_at([1, 2, 1.5], [3, 2, 1.5])
    target_in_cam = world_from_cam.inverse().transform(np.array([[3, 2, 1.5]]))[0]
    np.testing.assert_allclose(target_in_cam, [0, 0, 2], atol=1e-9)
    # OpenCV convention: image y points down, i.e. world -z for an upright camera
    np.testing.assert_allclose(world_from_cam.rotation[:, 1], [0, 0, -1], atol=1e-9)


@pytest.mark.parametrize("matrix, message", [
    (np.eye(3), "4x4"),
    (np.diag([1, 1, 2, 1.0]), "not orthonormal"),
    (np.diag([1, 1, -1, 1.0]), "not orthonormal"),
    (np.vstack([np.eye(4)[:3], [0, 0, 1, 1]]), "last row"),
    (np.full((4, 4), np.nan), "non-finite"),
])
def test_non_rigid_matrices_are_rejected(matrix, message):
    with pytest.raises(InputError, match=message):
        Rigid3.from_matrix(matrix, source="x.txt")


def test_bad_tum_lines_are_rejected():
    with pytest.raises(InputError, match="8 fields"):
        parse_tum_line("a 1 2 3")
    with pytest.raises(InputError, match="non-numeric"):
        parse_tum_line("a 1 2 3 x 0 0 1")


def _pose(i: int) -> Rigid3:
    return look_at(np.array([0.1 * i, 0, 1.0]), np.array([0, 2.0, 1]))


def test_named_trajectory_takes_names_from_the_first_column_or_the_sidecar(tmp_path):
    numeric = tmp_path / "poses.txt"  # what `evaluate --trajectory` writes
    numeric.write_text("# estimate\n" + "".join(tum_line(f"{t:.6f}", _pose(i)) + "\n"
                                                for i, t in enumerate([1.5, 2.5, 4.0])))
    tum = read_named_trajectory(numeric)
    np.testing.assert_array_equal(tum.stamps, [1.5, 2.5, 4.0])
    assert tum.names == [None, None, None]
    np.testing.assert_allclose(tum.poses[2].translation, [0.2, 0, 1.0], atol=1e-6)
    names_sidecar(numeric).write_text("1.500000 seq-02/frame-000001\n2.500000 b\n"
                                      "4.000000 frame 9\n")
    assert read_named_trajectory(numeric).names == ["seq-02/frame-000001", "b", "frame 9"]
    names_sidecar(numeric).write_text("1.500000 seq-02/frame-000001\n4.000000 frame 9\n")
    with pytest.raises(InputError, match=r"poses.names.txt: names no frame for the stamp "
                                         r"2.500000"):  # one name per pose, or it says so
        read_named_trajectory(numeric)

    named = tmp_path / "named.txt"  # older files: names first, stamps are the row index
    named.write_text(tum_line("a/1.png", _pose(0)) + "\n" + tum_line("7.0", _pose(1)) + "\n")
    names_sidecar(named).write_text("0.000000 ignored\n")
    tum = read_named_trajectory(named)
    assert tum.names == ["a/1.png", None] and list(tum.stamps) == [0.0, 7.0]


@pytest.mark.parametrize("sidecar, message", [
    (b"1.000000\n", "expected 'stamp name'"),
    (b"x1 frame\n", "timestamp 'x1' is not a number"),
    (b"\xff\xfe frame\n", "not UTF-8"),
])
def test_bad_names_sidecar_is_a_one_line_error(tmp_path, sidecar, message):
    path = tmp_path / "poses.txt"
    path.write_text(tum_line("1.000000", _pose(0)) + "\n")
    names_sidecar(path).write_bytes(sidecar)
    with pytest.raises(InputError, match=message) as err:
        read_named_trajectory(path)
    assert str(err.value).startswith(str(names_sidecar(path))) and "\n" not in str(err.value)


@settings(max_examples=50, deadline=None)
@given(st.lists(rigid, min_size=3, max_size=12), rigid, st.floats(0.05, 20))
def test_pose_and_point_alignment_recover_a_similarity(poses, b_from_a, scale):
    """align_poses and umeyama find the similarity that moved a set of cameras (and the
    cameras keep their orientation relative to it)."""
    from slamreloc.geometry import Sim3, align_poses, umeyama

    sim = Sim3(scale, b_from_a.rotation, b_from_a.translation)
    moved = [sim.apply_to_pose(p) for p in poses]
    got = align_poses(poses, moved)
    centres = np.array([p.translation for p in poses])
    size = max(1.0, float(np.abs(centres).max()))
    if np.sum((centres - centres.mean(0)) ** 2) > len(poses) * (1e-8 * size) ** 2:
        assert np.isclose(got.scale, scale, rtol=1e-6)  # else centres coincide: no scale
    for p, q in zip(poses, moved):
        dt, dr = pose_error(got.apply_to_pose(p), q)
        assert dt < 1e-6 * max(1.0, scale * 10) and dr < 1e-4  # arccos: ~1e-6 deg noise
    if np.linalg.matrix_rank(centres - centres.mean(0), tol=1e-3) == 3:  # not degenerate
        fit = umeyama(centres, sim.transform(centres))
        np.testing.assert_allclose(fit.transform(centres), sim.transform(centres), atol=1e-6)
