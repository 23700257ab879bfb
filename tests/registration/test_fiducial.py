"""Tests of registration/fiducial.py: SVD registration, reflection guard, re-ordering."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from heartreg.phantom import layout
from heartreg.phantom.config import PRESETS
from registration.fiducial import FiducialError, register_fiducials, rigid_fit
from registration.transforms import apply_to_points, invert, make_transform, rotation_distance_deg

SETTINGS = settings(max_examples=40, deadline=None)
seeds = st.integers(min_value=0, max_value=2**32 - 1)


def random_case(seed, n=9, noise_mm=0.0):
    rng = np.random.default_rng(seed)
    T = make_transform(Rotation.random(random_state=rng), rng.uniform(-300, 300, 3))
    source = rng.uniform(-60, 60, (n, 3))
    target = apply_to_points(T, source) + rng.normal(0, noise_mm, (n, 3))
    return T, source, target


@SETTINGS
@given(seeds)
def test_exact_points_give_the_exact_transform(seed):
    T, source, target = random_case(seed)
    result = register_fiducials(source, target)
    np.testing.assert_allclose(result.T_heart_from_probe, T, atol=1e-8)
    assert result.fre_rms_mm < 1e-8
    assert not result.reordered


@SETTINGS
@given(seeds)
def test_noisy_points_recover_the_transform_within_the_noise(seed):
    # 9 points in a 120 mm box with 1 mm noise: the target registration error at
    # the centroid is ~ sigma / sqrt(n) = 0.33 mm per axis.  The rotation about
    # the least constrained axis has standard deviation sigma / sqrt(s2^2 + s3^2)
    # (s the singular values of the centred points): tolerances ~5 sigma.
    T, source, target = random_case(seed, noise_mm=1.0)
    result = register_fiducials(source, target)
    centre = source.mean(axis=0)
    err = apply_to_points(result.T_heart_from_probe, centre) - apply_to_points(T, centre)
    assert np.linalg.norm(err) < 2.0
    s = np.linalg.svd(source - centre, compute_uv=False)
    rot_sigma_deg = np.degrees(1.0 / np.hypot(s[1], s[2]))
    assert rotation_distance_deg(result.T_heart_from_probe, T) < 5 * np.sqrt(3) * rot_sigma_deg
    # FRE of n points fitted with 6 dof: E[FRE^2] = 3 sigma^2 (n - 2) / n
    assert 0.3 < result.fre_rms_mm < 2.5
    assert result.residuals_mm.shape == (9,)


@SETTINGS
@given(seeds)
def test_reflections_are_never_returned(seed):
    rng = np.random.default_rng(seed)
    source = rng.uniform(-50, 50, (6, 3))
    target = source * np.array([1.0, 1.0, -1.0])  # a mirror image: best orthogonal fit is a reflection
    T = rigid_fit(source, target)
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0)
    # coplanar points with noise (the fiducial grid) as well
    grid = np.c_[rng.uniform(-40, 40, (9, 2)), np.zeros(9)]
    T = rigid_fit(grid, grid + rng.normal(0, 2.0, grid.shape))
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0)


@SETTINGS
@given(seeds)
def test_permuted_order_is_recovered(seed):
    T, source, target = random_case(seed, n=8, noise_mm=0.3)
    perm = np.random.default_rng(seed + 1).permutation(8)
    result = register_fiducials(source, target[perm])
    # target[perm][order[i]] must be target[i]
    np.testing.assert_array_equal(perm[result.order], np.arange(8))
    assert result.reordered != np.array_equal(perm, np.arange(8))
    assert rotation_distance_deg(result.T_heart_from_probe, T) < 2.0
    assert result.fre_rms_mm < 1.0


def test_phantom_fiducials_register_to_the_shifted_skin():
    config = PRESETS["wood2018-trial1"]
    ct = layout.fiducials_patient_mm()
    shift = layout.T_fiducial_shift(config)
    T_probe_from_patient = invert(layout.T_patient_from_probe())
    touched = apply_to_points(T_probe_from_patient @ shift, ct)  # probe frame
    result = register_fiducials(touched, ct)
    expected = invert(shift) @ layout.T_patient_from_probe()  # the fiducial T0
    np.testing.assert_allclose(result.T_heart_from_probe, expected, atol=1e-8)
    assert not result.reordered and not result.ambiguous


def test_symmetric_grid_permutation_is_flagged_ambiguous():
    # The 3 x 3 skin grid is symmetric under a 180 degree turn about the
    # anterior-posterior axis: a permuted listing cannot be resolved by geometry.
    ct = layout.fiducials_patient_mm()
    perm = np.array([8, 7, 6, 5, 4, 3, 2, 1, 0])  # exactly that half-turn
    rng = np.random.default_rng(3)
    result = register_fiducials(ct[rng.permutation(9)], ct)
    assert result.fre_rms_mm < 1e-6
    assert result.ambiguous
    result_turned = register_fiducials(ct[perm], ct)
    assert result_turned.fre_rms_mm < 1e-6  # the order is consistent with a rigid motion


def test_count_mismatch_and_degenerate_layouts_raise():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(5, 3))
    with pytest.raises(FiducialError, match="5 points but target has 4"):
        register_fiducials(pts, pts[:4])
    line = np.outer(np.arange(5.0), [1.0, 2.0, 3.0])
    with pytest.raises(FiducialError, match="collinear"):
        register_fiducials(line, line + 1.0)
    with pytest.raises(FiducialError, match="at least 3"):
        rigid_fit(pts[:2], pts[:2])
    with pytest.raises(ValueError, match=r"source must have shape \(n, 3\)"):
        rigid_fit(pts[:, :2], pts)


def test_given_order_is_kept_when_reordering_is_disabled():
    T, source, target = random_case(5, n=6)
    result = register_fiducials(source, target[::-1], allow_reorder=False)
    assert not result.reordered
    assert result.fre_rms_mm > 3.0
