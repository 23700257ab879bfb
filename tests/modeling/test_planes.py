"""Fat planes blurred above the tissue threshold (modeling/planes.py), on synthetic CTs with known planes."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from modeling.planes import fat_planes

SPACING = (1.5, 1.5, 1.5)


def _two_blocks(gap_hu: float, blur_voxels: float = 1.0):
    """Muscle (100 HU) in two blocks pressed together across a one-voxel fat plane (at i = 20) of
    ``gap_hu`` after partial volume, in fat (-100 HU), blurred as a CT's point spread blurs it."""
    ct = np.full((40, 40, 41), -100.0)
    ct[8:32, 8:32, 6:35] = 100.0
    ct[8:32, 8:32, 20] = gap_hu
    return ndimage.gaussian_filter(ct, blur_voxels)


def test_a_blurred_plane_between_two_blocks_is_found():
    ct = _two_blocks(gap_hu=-100.0)
    assert ct[20, 20, 20] > 0.0  # the threshold no longer sees it: the blur lifts it into the tissue range
    planes = fat_planes(ct, SPACING, hu_low=0.0)
    inner = planes[12:28, 12:28, :]  # the plane away from the blocks' edges
    assert inner[:, :, 20].mean() > 0.9  # the plane's floor, across its whole extent
    assert not inner[:, :, :19].any() and not inner[:, :, 22:].any()  # nothing else inside the blocks
    assert set(np.flatnonzero(planes.any(axis=(0, 1)))) <= {19, 20, 21}  # one sheet, at the plane


def test_muscle_against_fat_and_noise_specks_are_no_planes():
    ct = _two_blocks(gap_hu=100.0)  # one block of muscle: its edges step from 100 to -100 HU
    rng = np.random.default_rng(3)
    specks = rng.integers(12, 28, size=(25, 3))
    ct[tuple(specks.T)] = 25.0  # single dim voxels inside the muscle (noise)
    assert not fat_planes(ct, SPACING, hu_low=0.0).any()


def test_only_the_box_is_searched():
    ct = _two_blocks(gap_hu=-100.0)
    box = (slice(0, 40), slice(0, 40), slice(25, 41))  # beside the plane
    assert not fat_planes(ct, SPACING, hu_low=0.0, box=box).any()
    assert fat_planes(ct, SPACING, hu_low=0.0, box=(slice(0, 40),) * 2 + (slice(10, 31),)).any()
