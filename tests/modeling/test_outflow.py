"""The outflow tract the bridge opening took off the heart, given back up to its valve (``modeling.outflow``)."""

from __future__ import annotations

import numpy as np
import pytest

from modeling.outflow import outflow_beyond_opening

SPACING = np.array([2.0, 2.0, 2.0])  # the segmentation's coarse grid


def _tube(sleeve_mm, *, lumen_mm=8.0, length_mm=90.0):
    """A chamber (z < 20 mm, kept by the opening) and a tube leaving it along z.

    Its first ``sleeve_mm`` past the chamber in 4 mm of muscle (an infundibulum), then a vessel's 1.5 mm wall
    in fat (the trunk above its valve).  Returns (core, blood, hu, z of each voxel).
    """
    n = int((20.0 + length_mm) / SPACING[0]) + 4
    k, j, i = np.indices((n, 40, 40)) * SPACING[:, None, None, None]
    z, r = k, np.hypot(j - 40.0, i - 40.0)
    hu = np.full(k.shape, -100.0)
    chamber = (z < 20.0) & (r < 34.0)
    hu[chamber] = 100.0
    hu[chamber & (r < 28.0) & (z > 2.0)] = 300.0
    past = z >= 20.0
    wall = np.where(z < 20.0 + sleeve_mm, 4.0, 1.5)
    hu[past & (r < lumen_mm + wall)] = np.where(z < 20.0 + sleeve_mm, 100.0, 40.0)[past & (r < lumen_mm + wall)]
    hu[past & (r < lumen_mm) & (z < 20.0 + length_mm)] = 300.0
    return chamber, hu > 200.0, hu, z


def test_the_infundibulum_is_kept_up_to_its_valve():
    core, blood, hu, z = _tube(12.0)
    kept, lengths = outflow_beyond_opening(core, blood, hu, SPACING, up_kji=(2.0, 0.0, 0.0))
    assert len(lengths) == 1 and 9.0 <= lengths[0] <= 15.0, lengths
    assert kept[blood & (z >= 20.0) & (z < 28.0)].all()
    assert not kept[z > 36.0].any()


def test_a_vessel_running_down_from_its_mouth_is_no_trunk():
    """The same tube with the patient's head the other way: the trunk rises from its valve, this runs down."""
    core, blood, hu, _ = _tube(12.0)
    kept, lengths = outflow_beyond_opening(core, blood, hu, SPACING, up_kji=(-2.0, 0.0, 0.0))
    assert not kept.any() and lengths == [], lengths


@pytest.mark.parametrize("case", ["vein in fat", "thin coronary", "short blind pouch"])
def test_no_sleeve_or_no_vessel_gives_nothing_back(case):
    """A vessel leaving in fat from its mouth, a coronary-sized tube, a pouch with nothing beyond its 'valve'."""
    sleeve, lumen, length = {"vein in fat": (0.0, 8.0, 90.0), "thin coronary": (12.0, 2.0, 90.0),
                             "short blind pouch": (12.0, 8.0, 20.0)}[case]
    core, blood, hu, _ = _tube(sleeve, lumen_mm=lumen, length_mm=length)
    kept, lengths = outflow_beyond_opening(core, blood, hu, SPACING)
    assert not kept.any() and lengths == [], lengths
