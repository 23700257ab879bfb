"""The right ventricle's outflow tract where it is thinner than the bridge opening's ball.

The segmentation cuts bridges and thin vessels off the heart's region with a
morphological opening (:func:`modeling.segment.segment_heart`'s
``vessel_radius_mm``, 14 mm).  An outflow tract thinner than that ball (the
infundibulum of a small heart, a child's: the anatomical phantom's is 12.5-13
mm in outer radius below its valve) goes with the pulmonary trunk, and the
model was closed inside it, 9.6 mm below the valve (12.0 at sample size).
What tells the outflow tract from the vessel is what step 7 of
:mod:`modeling.greatvessels` reads: the infundibulum rises from its ventricle
in a sleeve of muscle, the trunk above its valve lies in fat.  So, of the
contrast blood the opening took off the heart (every component: the phantom's
right-heart blood is apart from the seed's pool; less what a trace already
called a vessel's lumen or wall):

1. each connected part of it that opens into the blood kept in the heart (its
   *mouth*) and is a great vessel's (at least ``min_radius_mm`` in inscribed
   radius: no coronary artery; reaching ``vessel_mm`` on past its valve: no
   blind pouch, no partial-volume blob) is followed out from the mouth (the
   distance to it, up to ``reach_mm``);
2. the fraction of fat (below ``fat_hu``) ``ring_mm`` around its lumen, among
   the voxels outside the heart kept and nearer this tube than any other
   blood, is profiled in 1.5 mm bins from the mouth and fitted by one step
   (:func:`modeling.greatvessels._step_up`);
3. where it rises by at least ``min_rise`` from at most ``sleeve_fat`` within
   ``max_mm`` of the mouth, the sleeve ends at the first bin whose fraction
   rises by ``min_rise`` over the bins before it, seen in three bins at least
   and muscle (at most ``sleeve_fat``) up to it: a least-squares step sits
   halfway up a ramp, and on the phantom the fat rises over ~6 mm past the
   valve (cut at the step, the mesh ran 4.2 mm up the trunk);
4. the tube must rise from its mouth towards the head (10-30 mm from it;
   ``up_kji``, ``min_ascent``: the outflow tract and the trunk do; a vein
   running down from its atrium does not; checked first, it spares the
   profile's transforms);
5. the lumen before it and its wall (``ring_mm[1]`` around it, not fat) are the
   outflow tract, given back to the heart.

A vein's mouth (fat 1.5 mm out from its wall) and a noisy CT (no sleeve shows)
give nothing back.  On ``shared/realct``, whose outflow tract the opening
keeps, nothing is given back (before the calibre and length checks a coronary
artery and small blobs were, 41 ml, Dice 0.906 -> 0.896); resampled to 1 mm,
before the rise was asked for, a vein running down from its mouth (2.2 ml,
all outside the reference).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from modeling.distance import distance_mm
from modeling.greatvessels import PROFILE_BIN_MM, _step_up

__all__ = ["keep_outflow_tracts", "outflow_beyond_opening"]


def outflow_beyond_opening(core, blood, hu, spacing_kji, *, not_heart=None, ring_mm=(1.0, 4.0), fat_hu=-30.0,
                           sleeve_fat=0.25, min_rise=0.1, max_mm=25.0, vessel_mm=25.0, min_radius_mm=4.0,
                           up_kji=None, min_ascent=0.25, reach_mm=50.0):
    """The outflow tracts (lumen and muscle wall) the opening took off the heart.

    Parameters
    ----------
    core : bool array
        The heart kept by the opening (and the vessel cut).
    blood : bool array like ``core``
        Contrast blood (every component: the right heart's may be apart from the seed's pool).
    hu : float array like ``core``
        The CT on the same grid.
    spacing_kji : (3,) float, mm
    not_heart : bool array like ``core``, optional
        Blood already known to be vessel (a traced lumen and its wall): no tube.
    ring_mm, fat_hu, sleeve_fat, min_rise, max_mm
        As :func:`modeling.greatvessels.trace_great_vessels`' step 7: the shell whose fat is counted, the
        most fat a muscle sleeve holds, the least rise that marks the valve, the longest infundibulum.
    vessel_mm, min_radius_mm
        A tube is a great vessel's when it reaches this far on past the valve (within ``reach_mm`` of its
        mouth) and is at least this wide in inscribed radius.
    up_kji : (3,) float, optional
        The patient's height (LPS z, mm) gained per index step along each axis.  With it the tube
        10-30 mm from its mouth must lie above the mouth, by at least ``min_ascent`` of the way
        (0.25: 15 degrees above the axial plane).  The outflow tract and the trunk rise (the phantom's
        0.97; ``shared/realct``'s pulmonary valve faces 0.59 upwards); without it a vein running down
        from its mouth was given back on ``shared/realct`` resampled to 1 mm (2.2 ml outside the
        reference); the lost tubes there lie at -0.6 to 0.01.

    Returns
    -------
    kept : bool array like ``core``
        The lumen and wall to give back (empty when no outflow tract shows).
    lengths_mm : list of float
        How far each reaches past its mouth.
    """
    spacing = np.asarray(spacing_kji, dtype=float)
    kept = np.zeros(core.shape, bool)
    lost = blood & ~core
    if not_heart is not None:
        lost &= ~not_heart
    mouths = lost & ndimage.binary_dilation(blood & core)
    if not mouths.any():
        return kept, []
    labels, _ = ndimage.label(lost)
    lengths = []
    objects = ndimage.find_objects(labels)
    volume_mm3 = np.bincount(labels.ravel()) * float(np.prod(spacing))
    margin = [int(np.ceil(ring_mm[1] / s)) + 1 for s in spacing]
    for label in np.unique(labels[mouths]):
        found = objects[label - 1]
        if (np.linalg.norm([(f.stop - f.start) * s for f, s in zip(found, spacing)]) < vessel_mm
                or volume_mm3[label] < np.pi * min_radius_mm ** 2 * vessel_mm):
            continue  # a blob or a thin vessel, not a great vessel leaving through its valve
        box = tuple(slice(max(f.start - m, 0), min(f.stop + m, n)) for f, m, n in zip(found, margin, core.shape))
        mouth = (labels[box] == label) & mouths[box]
        along = distance_mm(~mouth, spacing)
        lumen = (labels[box] == label) & (along <= reach_mm)
        if up_kji is not None:  # the trunk rises from the outflow tract towards the head
            far = np.argwhere(lumen & (along >= 10.0) & (along < 30.0))
            if len(far) == 0:
                continue  # shorter than a vessel
            way = far.mean(axis=0) - np.argwhere(mouth).mean(axis=0)
            if not way @ np.asarray(up_kji, dtype=float) >= min_ascent * np.linalg.norm(way * spacing):
                continue
        if distance_mm(lumen, spacing).max() < min_radius_mm:
            continue  # thinner than a great vessel: a coronary artery on the heart, in its fat
        to_lumen = distance_mm(~lumen, spacing)
        ring = (to_lumen > ring_mm[0]) & (to_lumen <= ring_mm[1]) & ~blood[box] & ~core[box] & (along <= reach_mm)
        ring &= to_lumen < distance_mm(~(blood[box] & ~lumen), spacing)
        bins = (along[ring] // PROFILE_BIN_MM).astype(np.int64)
        count, fat = np.bincount(bins).astype(float), np.bincount(bins, weights=hu[box][ring] < fat_hu)
        step = _step_up(count, fat)
        if step is None:
            continue
        split, before, after = step
        if before > sleeve_fat or after - before < min_rise:
            continue
        # the sleeve ends at the first bin whose fat rises by min_rise over the bins before it (a least-squares
        # step sits halfway up a ramp: the trunk's fat rises over ~6 mm past its valve, the infundibulum thinning)
        level = np.cumsum(fat) / np.maximum(np.cumsum(count), 1.0)
        frac = fat / np.maximum(count, 1.0)
        seen = np.cumsum(count > 0)  # a sleeve is seen in three bins at least, and is muscle
        rises = [b for b in range(3, split + 1) if count[b] > 0 and seen[b - 1] >= 3 and level[b - 1] <= sleeve_fat
                 and (frac[b] - level[b - 1] >= min_rise or b == split)]
        if not rises:
            continue
        length_mm = rises[0] * PROFILE_BIN_MM
        if length_mm > max_mm or along[lumen].max() < length_mm + vessel_mm:
            continue  # no infundibulum's length, or no vessel going on past the valve
        tract = lumen & (along < length_mm)
        wall = (distance_mm(~tract, spacing) <= ring_mm[1]) & ~blood[box] & (hu[box] >= fat_hu)
        kept[box] |= tract | (wall & (along < length_mm))
        lengths.append(length_mm)
    return kept, lengths


def keep_outflow_tracts(near, core, blood, hu, spacing_kji, reach_mm, *, not_heart=None, up_kji=None):
    """``near`` (the heart's band on the coarse grid) with the outflow tracts within ``reach_mm``; and a note.

    ``not_heart`` (the traced vessels' lumen and walls) stays out of it.
    """
    tract, lengths = outflow_beyond_opening(core, blood, hu, spacing_kji, not_heart=not_heart, up_kji=up_kji)
    if not lengths:
        return near, None
    near = near | (distance_mm(~tract, spacing_kji) <= reach_mm)
    if not_heart is not None:
        near &= ~not_heart
    return near, (f"outflow tract(s) thinner than the bridge opening's ball kept "
                  f"{', '.join(f'{x:.0f}' for x in lengths)} mm past it, in muscle up to where fat surrounds the vessel")
