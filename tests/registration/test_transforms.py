"""Tests of registration/transforms.py: the rigid-transform algebra, property-based."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from registration.transforms import (
    TransformError,
    apply_to_points,
    apply_to_vectors,
    check_rigid,
    compose,
    euler_xyz_deg_from_matrix,
    invert,
    make_transform,
    matrix_from_euler_xyz_deg,
    mean_rotation,
    rotation_distance_deg,
    rotation_exp,
    rotation_log,
    se3_exp,
    se3_log,
    translation_distance_mm,
)

SETTINGS = settings(max_examples=60, deadline=None)
seeds = st.integers(min_value=0, max_value=2**32 - 1)


def random_transform(seed, *, translation_mm=200.0):
    rng = np.random.default_rng(seed)
    R = Rotation.random(random_state=rng).as_matrix()
    return make_transform(R, rng.uniform(-translation_mm, translation_mm, 3))


@SETTINGS
@given(seeds)
def test_inverse_is_two_sided(seed):
    T = random_transform(seed)
    np.testing.assert_allclose(T @ invert(T), np.eye(4), atol=1e-12)
    np.testing.assert_allclose(invert(T) @ T, np.eye(4), atol=1e-12)
    check_rigid(invert(T))


@SETTINGS
@given(seeds, seeds, seeds)
def test_composition_is_associative_and_inverts_in_reverse(a, b, c):
    A, B, C = random_transform(a), random_transform(b), random_transform(c)
    np.testing.assert_allclose(compose(compose(A, B), C), compose(A, compose(B, C)), atol=1e-9)
    np.testing.assert_allclose(invert(compose(A, B)), compose(invert(B), invert(A)), atol=1e-9)


@SETTINGS
@given(seeds)
def test_points_and_vectors_follow_the_transform(seed):
    T = random_transform(seed)
    rng = np.random.default_rng(seed + 1)
    p = rng.normal(0, 50, (7, 3))
    q = apply_to_points(T, p)
    # distances are preserved, the homogeneous product agrees
    np.testing.assert_allclose(np.linalg.norm(q[1:] - q[0], axis=1), np.linalg.norm(p[1:] - p[0], axis=1))
    np.testing.assert_allclose(q, (T @ np.c_[p, np.ones(7)].T).T[:, :3], atol=1e-9)
    # vectors ignore translation
    np.testing.assert_allclose(apply_to_vectors(T, p[1:] - p[0]), q[1:] - q[0], atol=1e-9)


@SETTINGS
@given(seeds, st.floats(min_value=1e-9, max_value=np.pi - 1e-6))
def test_exp_log_round_trip(seed, angle):
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    rv = axis * angle
    np.testing.assert_allclose(rotation_log(rotation_exp(rv)), rv, atol=1e-9)
    R = rotation_exp(rv)
    np.testing.assert_allclose(rotation_exp(rotation_log(R)), R, atol=1e-9)


@SETTINGS
@given(seeds, st.floats(min_value=0.0, max_value=3.0))
def test_se3_exp_log_round_trip(seed, angle):
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    twist = np.r_[rng.uniform(-100, 100, 3), axis / np.linalg.norm(axis) * angle]
    T = se3_exp(twist)
    check_rigid(T)
    np.testing.assert_allclose(se3_log(T), twist, atol=1e-7)
    np.testing.assert_allclose(se3_exp(se3_log(T)), T, atol=1e-9)


def test_se3_exp_of_pure_rotation_about_a_point():
    # rotation of pi/2 about z through (10, 0, 0): the origin goes to (10, -10, 0)
    T = make_transform(rotation_exp([0, 0, np.pi / 2]))
    T[:3, 3] = np.array([10.0, 0, 0]) - T[:3, :3] @ [10.0, 0, 0]
    np.testing.assert_allclose(se3_exp(se3_log(T)), T, atol=1e-12)
    np.testing.assert_allclose(apply_to_points(T, [0.0, 0, 0]), [10.0, -10.0, 0.0], atol=1e-12)


@SETTINGS
@given(
    st.floats(-179, 179),
    st.floats(-85, 85),  # away from gimbal lock at beta = +-90
    st.floats(-179, 179),
)
def test_euler_xyz_round_trip(alpha, beta, gamma):
    T = matrix_from_euler_xyz_deg([alpha, beta, gamma], [1.0, 2.0, 3.0])
    np.testing.assert_allclose(euler_xyz_deg_from_matrix(T), [alpha, beta, gamma], atol=1e-7)
    np.testing.assert_allclose(T[:3, 3], [1.0, 2.0, 3.0])


def test_euler_xyz_is_intrinsic_rx_ry_rz():
    a, b, g = np.radians([-22.9, 2.2, -43.8])  # Table 1, trial 1
    Rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    Ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    Rz = np.array([[np.cos(g), -np.sin(g), 0], [np.sin(g), np.cos(g), 0], [0, 0, 1]])
    T = matrix_from_euler_xyz_deg([-22.9, 2.2, -43.8])
    np.testing.assert_allclose(T[:3, :3], Rx @ Ry @ Rz, atol=1e-12)


@SETTINGS
@given(seeds, st.floats(min_value=0.0, max_value=179.0))
def test_rotation_distance_is_the_relative_angle(seed, angle_deg):
    T = random_transform(seed)
    rng = np.random.default_rng(seed + 7)
    axis = rng.normal(size=3)
    step = make_transform(rotation_exp(axis / np.linalg.norm(axis) * np.radians(angle_deg)))
    # the geodesic angle is invariant to which side the rotation acts on
    assert rotation_distance_deg(T, T @ step) == pytest.approx(angle_deg, abs=1e-6)
    assert rotation_distance_deg(T, step @ T) == pytest.approx(angle_deg, abs=1e-6)
    assert rotation_distance_deg(T, T) == pytest.approx(0.0, abs=1e-6)


def test_translation_distance_at_a_point():
    A = make_transform(rotation_exp([0, 0, np.pi / 2]), [0, 0, 0])
    B = np.eye(4)
    assert translation_distance_mm(A, B) == 0.0
    # the point (10, 0, 0) goes to (0, 10, 0) under A and stays under B
    assert translation_distance_mm(A, B, [10.0, 0, 0]) == pytest.approx(np.sqrt(200.0))


@SETTINGS
@given(seeds)
def test_mean_rotation_of_symmetric_spread_is_the_centre(seed):
    centre = Rotation.random(random_state=np.random.default_rng(seed))
    rng = np.random.default_rng(seed + 3)
    offsets = rng.normal(0, 0.1, (10, 3))
    offsets = np.concatenate([offsets, -offsets])  # symmetric about the centre
    R = (centre * Rotation.from_rotvec(offsets)).as_matrix()
    assert rotation_distance_deg(mean_rotation(R), centre.as_matrix()) < 0.05


def test_check_rigid_rejects_reflections_and_bad_shapes():
    with pytest.raises(TransformError, match="reflection"):
        check_rigid(np.diag([1.0, 1.0, -1.0, 1.0]))
    with pytest.raises(TransformError, match="orthonormal"):
        check_rigid(np.diag([2.0, 1.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match=r"shape \(\.\.\., 4, 4\)"):
        invert(np.eye(3))
    with pytest.raises(ValueError, match=r"points must have shape"):
        apply_to_points(np.eye(4), np.zeros((3, 2)))


def test_stacks_broadcast():
    Ts = np.stack([random_transform(s) for s in range(5)])
    np.testing.assert_allclose(compose(Ts, invert(Ts)), np.broadcast_to(np.eye(4), Ts.shape), atol=1e-9)
    assert rotation_distance_deg(Ts, Ts[0]).shape == (5,)
    assert euler_xyz_deg_from_matrix(Ts).shape == (5, 3)
