"""modeling.coarse: block statistics kept for a read-only CT, per-label maxima without a sort."""

import gc

import numpy as np
from scipy import ndimage

from modeling import coarse
from modeling.coarse import block_mean_max, block_transform, label_maximum


def test_label_maximum_is_ndimage_maximum():
    rng = np.random.default_rng(3)
    labels, n = ndimage.label(rng.random((20, 21, 22)) > 0.6)
    values = (rng.random(labels.shape) * 50 - 10).astype(np.float32)
    expected = ndimage.maximum(values, labels, np.arange(1, n + 1))
    got = label_maximum(values, labels, n)
    assert got.dtype == np.float32
    assert np.array_equal(got, expected)
    # a label with no voxel gives 0, as ndimage's
    assert label_maximum(np.array([-5.0, -3.0, 2.0]), np.array([1, 1, 3]), 3).tolist() == [-3.0, 0.0, 2.0]


def test_block_means_of_a_read_only_volume_are_kept_until_it_is_freed():
    rng = np.random.default_rng(4)
    hu = rng.integers(-1000, 1500, (12, 16, 16)).astype(np.int16)
    fresh = block_mean_max(hu, (3, 4, 4))
    assert block_mean_max(hu, (3, 4, 4))[0] is not fresh[0]  # writeable: computed each time
    hu.flags.writeable = False
    first = block_mean_max(hu, (3, 4, 4))
    again = block_mean_max(hu, (3, 4, 4))
    assert again[0] is first[0] and again[1] is first[1]
    assert not first[0].flags.writeable  # nobody changes what the next caller gets
    assert np.array_equal(first[0], fresh[0]) and np.array_equal(first[1], fresh[1])
    assert block_mean_max(hu, (2, 2, 2))[0].shape == (6, 8, 8)  # another step: its own blocks
    view = hu[:, :8]
    assert block_mean_max(view, (3, 4, 4))[0].shape == (4, 2, 4)  # a view is never taken for its base
    del hu, view, first, again
    gc.collect()
    assert not coarse._LAST  # freed with the volume


def test_centroid_is_ndimage_center_of_mass():
    from modeling.coarse import centroid

    rng = np.random.default_rng(5)
    mask = rng.random((13, 17, 19)) > 0.8
    np.testing.assert_allclose(centroid(mask), ndimage.center_of_mass(mask), rtol=0, atol=1e-12)
    one = np.zeros((4, 5, 6), bool)
    one[3, 0, 5] = True
    assert centroid(one).tolist() == [3.0, 0.0, 5.0]


def test_block_transform_puts_each_block_at_its_voxels_centre():
    """The coarse grid's voxel -> patient transform (the traced lumen's, ``HeartSegmentation.vessel_lumen``):
    each block's index maps to the mean of its voxels' centres, on an oblique, mirrored grid with blocks of
    2 x 3 x 4 voxels (k, j, i)."""
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [20, -10, 35], degrees=True).as_matrix() @ np.diag([0.5, -0.6, 1.25])
    T[:3, 3] = (-40.0, 12.0, 300.0)
    step = np.array([2, 3, 4])
    shape = (8, 9, 12)  # whole blocks
    k, j, i = np.indices(shape)
    centres = np.stack([i, j, k, np.ones_like(i)], axis=-1) @ T.T
    means = np.stack([block_mean_max(np.ascontiguousarray(centres[..., a]), step)[0] for a in range(3)], axis=-1)
    ck, cj, ci = np.indices(means.shape[:3])
    mapped = np.stack([ci, cj, ck, np.ones_like(ci)], axis=-1) @ block_transform(T, step).T
    np.testing.assert_allclose(mapped[..., :3], means, atol=1e-9)
