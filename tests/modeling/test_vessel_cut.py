"""The great-vessel cut of the automatic segmentation, on shapes whose answer is known.

``modeling.segment._cut_great_vessels`` walks each branch of the heart body out
in 5 mm shells: thick (deeper than a chamber's 17 mm) it is an atrium; what
reaches on beyond for more than 25 mm is a vessel, cut where the thick stretch
ends; a branch that rounds off sooner is kept.  Here: a ventricle (ball of
38 mm), an atrium beside it (ball of 18.5 mm, its centre 50 mm away), a vessel
(tube of 11 mm radius) leaving the atrium upwards, and a second atrium with no
vessel.
"""

from __future__ import annotations

import numpy as np

from modeling.segment import _cut_great_vessels, _heart_body

SPACING = np.array([2.0, 2.0, 2.0])  # k, j, i (mm): the segmentation's coarse grid
SHAPE = (110, 90, 110)


def _grid():
    k, j, i = np.indices(SHAPE, dtype=float)
    return np.stack([i, j, k], axis=-1) * SPACING[::-1] - np.array([110.0, 90.0, 90.0])  # x, y, z (mm)


def _ball(p, centre, radius):
    return np.sum((p - np.asarray(centre, float)) ** 2, axis=-1) <= radius**2


def _cut(body):
    heart = _heart_body(body, np.zeros_like(body), SPACING, 20.0)
    return _cut_great_vessels(body, heart, SPACING, heart_radius_mm=20.0, vessel_length_mm=25.0, root_mm=10.0,
                              chamber_radius_mm=17.0)


def test_an_atrium_is_kept_its_vessel_cut():
    p = _grid()
    ventricle = _ball(p, (0, 0, 0), 38)
    atrium = _ball(p, (-50, 0, 0), 18.5)
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    vessel = ((x + 50) ** 2 + y**2 <= 11.0**2) & (z >= 0) & (z <= 125)
    other_atrium = _ball(p, (38, 0, 38), 18.5)
    body = ventricle | atrium | vessel | other_atrium
    kept, note = _cut(body)
    # the lone atrium stays whole: it rounds off within 25 mm of its thick part (cut at its first thin shell,
    # 10 mm out, as before, it lost its far half)
    assert np.all(kept[other_atrium]), note
    # the vessel goes, cut where its atrium's thick stretch ends (15 mm out): the atrium's near half stays,
    # its far wall goes with the vessel (thickness tells no more)
    assert not kept[vessel & (z > 35)].any(), note
    assert np.all(kept[atrium & (x >= -40)]) and kept[atrium].mean() > 0.5, note
    assert "cut 15 mm from it" in note, note
    assert "1 branch(es)" in note


def test_an_organ_pressed_to_the_heart_is_cut_at_its_neck():
    """A thick slab (a liver) touching the ventricle over a narrow neck: thick for longer than an atrium."""
    p = _grid()
    ventricle = _ball(p, (0, 0, 0), 38)
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    neck = (x**2 + y**2 <= 12.0**2) & (z <= -30) & (z >= -52)
    organ = (np.abs(x) <= 100) & (np.abs(y) <= 40) & (z <= -50) & (z >= -88)
    body = ventricle | neck | organ
    kept, note = _cut(body)
    assert np.all(kept[ventricle]) and kept[organ].mean() < 0.005, note


def test_a_lobe_beyond_a_vessel_goes_with_it():
    """Atrium, then a thin tube for 40 mm, then a ball as thick as a chamber: the atrium's stretch ends at the tube.

    Counting the stretch to its last thick shell (the ball) kept the tube and the ball whole.
    """
    p = _grid()
    ventricle = _ball(p, (0, 0, 0), 38)
    atrium = _ball(p, (-50, 0, 0), 18.5)
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    tube = ((x + 50) ** 2 + y**2 <= 9.0**2) & (z >= 0) & (z <= 70)
    lobe = _ball(p, (-50, 0, 80), 19.0)
    body = ventricle | atrium | tube | lobe
    kept, note = _cut(body)
    assert not kept[lobe].any() and not kept[tube & (z > 35)].any(), note
    assert np.all(kept[atrium & (x >= -40)]), note


def test_an_organ_pressed_broadly_is_cut_two_heart_radii_out():
    """A thick slab against the ventricle with no neck: thick all the way, cut 2 x 20 mm from the heart body."""
    p = _grid()
    ventricle = _ball(p, (0, 0, 0), 38)
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    organ = (np.abs(x) <= 100) & (np.abs(y) <= 40) & (z <= -20) & (z >= -56)  # 36 mm: no 20 mm ball fits
    body = ventricle | organ
    kept, note = _cut(body)
    assert "cut 40 mm from it" in note, note
    assert np.all(kept[ventricle]) and not kept[organ & (np.abs(x) > 90)].any(), note
