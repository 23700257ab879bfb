"""Tests of hrcore/geometry.py: checks, Kabsch and frozen arrays (the algebra of
apply/invert/compose is tested, property-based, in tests/registration/test_transforms.py)."""


import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from hrcore.geometry import (
    TransformError,
    apply_to_points,
    check_transform,
    frozen,
    invert,
    is_rigid,
    kabsch,
)

SETTINGS = settings(max_examples=40, deadline=None)
seeds = st.integers(min_value=0, max_value=2**32 - 1)


def random_rigid(rng, n=None):
    shape = () if n is None else (n,)
    T = np.zeros(shape + (4, 4))
    T[..., :3, :3] = Rotation.random(n, random_state=rng).as_matrix()
    T[..., :3, 3] = rng.uniform(-200, 200, shape + (3,))
    T[..., 3, 3] = 1.0
    return T


@SETTINGS
@given(seeds)
def test_kabsch_recovers_a_rigid_transform_exactly(seed):
    rng = np.random.default_rng(seed)
    T = random_rigid(rng)
    source = rng.normal(0, 40, (6, 3))
    np.testing.assert_allclose(kabsch(source, apply_to_points(T, source)), T, atol=1e-9)


@SETTINGS
@given(seeds)
def test_weights_select_the_points_that_count(seed):
    """Zero weight on corrupted points: the fit is the one on the others alone."""
    rng = np.random.default_rng(seed)
    T = random_rigid(rng)
    source = rng.normal(0, 40, (8, 3))
    target = apply_to_points(T, source)
    target[5:] += rng.normal(0, 30, (3, 3))
    w = np.r_[rng.uniform(0.5, 2.0, 5), np.zeros(3)]
    np.testing.assert_allclose(kabsch(source, target, weights=w), T, atol=1e-9)
    np.testing.assert_allclose(kabsch(source, target, weights=w), kabsch(source[:5], target[:5]), atol=1e-9)


def test_batch_equals_one_fit_at_a_time():
    rng = np.random.default_rng(3)
    source = rng.normal(0, 30, (5, 7, 3))
    target = rng.normal(0, 30, (5, 7, 3))
    batch = kabsch(source, target)
    assert batch.shape == (5, 4, 4)
    for b in range(5):
        np.testing.assert_allclose(batch[b], kabsch(source[b], target[b]), atol=1e-12)


def test_reflected_target_still_gives_a_rotation():
    """Coplanar points mirrored: the SVD's best orthogonal map is a reflection;
    Kabsch returns the best proper rotation instead (det +1)."""
    rng = np.random.default_rng(4)
    source = np.c_[rng.normal(0, 20, (6, 2)), np.zeros(6)]
    target = source * [1.0, 1.0, -1.0] + [0.0, 0.0, 0.5] * rng.normal(size=(6, 1))
    T = kabsch(source, target)
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0)
    check_transform(T, rigid=True)


def test_kabsch_refuses_mismatched_points():
    with pytest.raises(ValueError, match=r"same shape .*\(4, 3\) and \(5, 3\)"):
        kabsch(np.zeros((4, 3)), np.zeros((5, 3)))


@pytest.mark.parametrize(
    "bad, kwargs, match",
    [
        (np.eye(3), {}, r"T_init must have shape \(4, 4\), got \(3, 3\)"),
        (np.eye(4)[None], {}, r"T_init must have shape \(4, 4\)"),
        (np.full((4, 4), np.nan), {}, "T_init has non-finite entries"),
        (np.ones((4, 4)), {}, r"T_init last row must be \(0, 0, 0, 1\)"),
        (np.diag([2.0, 1, 1, 1]), {"rigid": True}, "T_init is not a rigid transform: .*orthonormal"),
        (np.diag([1.0, 1, -1, 1]), {"rigid": True}, "T_init is not a rigid transform: .*reflection"),
    ],
)
def test_check_names_the_argument_and_the_fault(bad, kwargs, match):
    with pytest.raises(TransformError, match=match):
        check_transform(bad, name="T_init", **kwargs)


def test_check_passes_affines_and_nan_frames_when_asked():
    affine = np.diag([0.5, 0.5, 0.625, 1.0])  # voxel to patient: not rigid, still a 4x4 transform
    assert check_transform(affine) is not None
    stack = random_rigid(np.random.default_rng(5), 3)
    stack[1] = np.nan  # an invalid tracker frame
    check_transform(stack, stack=True, rigid=True, finite=False)
    with pytest.raises(TransformError, match="non-finite"):
        check_transform(stack, stack=True)


def test_is_rigid_says_which_frame_is_bad():
    stack = random_rigid(np.random.default_rng(6), 4)
    stack[1, :3, :3] *= 1.01
    stack[2, 3, 0] = 0.5
    stack[3, :3, 0] *= -1  # reflection
    np.testing.assert_array_equal(is_rigid(stack), [True, False, False, False])


def test_invert_of_a_stack():
    stack = random_rigid(np.random.default_rng(7), 5)
    np.testing.assert_allclose(stack @ invert(stack), np.broadcast_to(np.eye(4), stack.shape), atol=1e-12)


def test_frozen_is_a_read_only_copy():
    a = np.array([1.0, 1.9999999, 3.0])
    f = frozen(a)
    assert not f.flags.writeable and f.flags.c_contiguous
    a[0] = 5.0
    assert f[0] == 1.0 and a.flags.writeable
    i = frozen(a, np.int64)
    assert i.dtype == np.int64 and i.tolist() == [5, 2, 3]
    assert frozen(np.arange(3)).dtype == np.arange(3).dtype
