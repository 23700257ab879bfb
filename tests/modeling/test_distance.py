"""modeling.distance: the segmentation's distance transforms equal scipy's, in mm."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from modeling import distance
from modeling.distance import distance_mm


@pytest.mark.parametrize("spacing", [(1.0, 1.0, 1.0), (2.5, 0.7, 0.7), (0.6, 1.95, 3.0)])
def test_equals_scipy_on_anisotropic_grids(spacing):
    rng = np.random.default_rng(7)
    mask = ndimage.gaussian_filter(rng.random((23, 31, 29)), 2.0) > 0.5
    before = mask.copy()
    got = distance_mm(mask, spacing)
    want = ndimage.distance_transform_edt(mask, sampling=spacing)
    assert got.dtype == np.float32 and got.shape == mask.shape
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-5)
    np.testing.assert_array_equal(mask, before)  # the input is not changed


def test_any_memory_order_and_integer_masks():
    rng = np.random.default_rng(3)
    mask = rng.random((9, 10, 11)) > 0.2
    want = ndimage.distance_transform_edt(mask, sampling=(1.0, 2.0, 3.0))
    np.testing.assert_allclose(distance_mm(np.asfortranarray(mask), (1.0, 2.0, 3.0)), want, rtol=1e-6)
    np.testing.assert_allclose(distance_mm(mask[:, ::-1].astype(np.uint8)[:, ::-1], (1.0, 2.0, 3.0)), want, rtol=1e-6)


def test_no_background_is_infinitely_far_and_all_background_is_zero():
    assert np.isinf(distance_mm(np.ones((3, 4, 5), bool), 1.0)).all()
    assert not distance_mm(np.zeros((3, 4, 5), bool), 1.0).any()


@pytest.mark.parametrize("spacing", [(1.0, 0.0, 1.0), (1.0, np.nan, 1.0), (-1.0, 1.0, 1.0)])
def test_bad_spacing_is_refused(spacing):
    with pytest.raises(ValueError, match="spacing_kji"):
        distance_mm(np.ones((2, 2, 2), bool), spacing)


def test_refuses_2d():
    with pytest.raises(ValueError, match="3-D"):
        distance_mm(np.ones((4, 4), bool), (1.0, 1.0))


def test_threads_give_the_same_bits(monkeypatch):
    """edt splits lines between threads: one thread (a batch worker, OMP_NUM_THREADS=1) and two agree exactly."""
    rng = np.random.default_rng(3)
    mask = rng.random((30, 40, 50)) < 0.95
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert distance._cores() == 1
    one = distance.distance_mm(mask, (2.5, 0.7, 0.7))
    monkeypatch.setenv("OMP_NUM_THREADS", "2")
    monkeypatch.setattr(distance.os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)
    assert distance._cores() == 2
    assert np.array_equal(one, distance.distance_mm(mask, (2.5, 0.7, 0.7)))
