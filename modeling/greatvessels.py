"""Great vessels in the contrast blood pool, traced from where they leave to their valve.

A chest CT cuts the aorta, the pulmonary arteries, the venae cavae and the
pulmonary veins where they leave its field of view; inside, each widens into a
chamber, through a valve (aortic, pulmonary) or a junction (caval, pulmonary
venous).  In the blood pool's distance map (the radius of the largest ball
centred at each voxel that stays in blood) a tube is a ridge of nearly constant
radius, a chamber a high peak, and a valve a *saddle*: the ridge narrows
between the vessel's sinus and the chamber.  So:

1. the blood pool is split into *lobes*, the watershed basins of its distance
   map around peaks at least ``peak_spacing_mm`` apart (one per chamber, per
   aortic sinus, per stretch of vessel);
2. lobes touching the volume's sides with a radius of at most
   ``max_vessel_radius_mm`` are vessels leaving the field of view;
3. a vessel lobe's neighbour is vessel too when the saddle between them is at
   least ``saddle_ratio`` times the narrower lobe's radius (the tube goes on,
   no valve between) and the neighbour is at most ``widen_ratio`` times as wide
   as the vessel's narrowest lobe so far (a sinus, not a chamber; measured
   from the narrowest lobe, a chain of small steps cannot creep into a
   chamber).

A valve or junction narrows the ridge, or the chamber is much wider than the
vessel feeding it: the trace stops there.  Lobes of a chamber cut by the field
of view's edge are wider than any vessel and are no start.

Given the heart's body (the tissue a ball of the ventricles' size fits in),
where a lobe lies tells vessels apart too:

4. a lobe mostly outside the body, with a vessel's radius, whose blood
   reaches farther than ``leave_mm`` from it is a vessel leaving the heart,
   at the edge or not (unless step 2 found it a chamber cut by the edge): on
   a whole-chest CT the pulmonary arteries end in the lungs, thinner than any
   lobe, long before the field of view's edge;
5. the trace also steps into a lobe wider than the vessel so far when that
   lobe lies mostly outside the body, with a vessel's radius, and at most
   ``branch_ratio`` times as wide as the vessel's narrowest lobe: a
   bifurcation's parent (Murray's law: 2^(1/3) = 1.26 times each of two equal
   branches), the pulmonary trunk; an atrium outside the body is wider than
   the vein feeding it by more (1.5 times and up);
6. a vessel lobe open to a chamber's lobe (a saddle as in step 3) runs on
   into that chamber with no valve between, and only its part outside the
   body is vessel: the pulmonary valve leaves no saddle in the blood, and the
   trunk's lobe reaches down into the right ventricle's outflow tract.  Such
   a lobe mostly inside the body is the chamber's, and the vessel lobe past
   it, outside the body, opens into it in turn (once: the lobes of the aortic
   root's well, inside the body, never do);
7. given the CT, the part of such a lobe past the body is vessel only where
   fat surrounds it: the outflow tract (the right ventricle's infundibulum)
   rises past the body in a sleeve of muscle, the pulmonary trunk above its
   valve lies in fat.  Along the lobe's axis (its core, the voxels deeper than
   0.8 of its widest: a tube's core is long and thin) the fraction of fat 1-4
   mm around the lumen, in 1.5 mm bins, is fitted by one step; where it
   rises by 0.1 or more from at most 0.25 (a muscle sleeve), within 25 mm of
   the body (an infundibulum's length), is the valve.  On ``shared/realct``,
   along the axis, 0.14-0.25 up to 12 mm past the body, 0.27 at 14 mm,
   0.31-0.41 beyond: the cut 2 mm below TotalSegmentator's pulmonary annulus
   (its pulmonary artery starts 1.5-4.8 mm below it), 17 mm below before.
   Noise (0.3-0.35 fat everywhere with 20 HU or more added) or thick slices
   (the fat blurred away) show no sleeve: the lobe is cut at the body's edge.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from modeling.coarse import label_maximum
from modeling.distance import distance_mm

__all__ = ["GreatVessels", "trace_great_vessels"]


@dataclass(frozen=True)
class GreatVessels:
    """The great vessels' lumen found in a blood pool.

    Attributes
    ----------
    lumen : bool array like the blood pool
        Blood of the vessels, from where they leave (the field of view, or the
        heart's surroundings) to their valve or junction.
    territory : bool array like the blood pool
        ``lumen`` and the voxels closer to it than to the chambers' blood, up to
        ``wall_mm`` from it (the vessels' walls), outside the heart's body when
        it is given: inside, the tissue around a lumen is the chambers' own (the
        aortic root sits between the atria, the RVOT and the LV's top).
    lobe_radii_mm : tuple of float
        Inscribed radius of each vessel lobe, largest first.
    note : str
        What was found, for the model's notes.
    """

    lumen: np.ndarray
    territory: np.ndarray
    lobe_radii_mm: tuple[float, ...]
    note: str


def _saddles(lobes, distance, n):
    """Saddle radius (mm) between adjacent lobes: the widest passage across their border.

    Returns
    -------
    dict of (int, int) -> float
        Keyed by label pairs ``(a, b)`` with ``a < b``.
    """
    keys, widths = [], []
    for axis in range(3):
        a = np.moveaxis(lobes, axis, 0)
        d = np.moveaxis(distance, axis, 0)
        x, y = a[:-1], a[1:]
        pair = (x > 0) & (y > 0) & (x != y)
        keys.append(np.minimum(x[pair], y[pair]).astype(np.int64) * (n + 1) + np.maximum(x[pair], y[pair]))
        widths.append(np.minimum(d[:-1], d[1:])[pair])
    keys = np.concatenate(keys)
    widths = np.concatenate(widths)
    if keys.size == 0:
        return {}
    unique, inverse = np.unique(keys, return_inverse=True)
    widest = np.zeros(unique.size)
    np.maximum.at(widest, inverse, widths)
    return {divmod(int(k), n + 1): float(w) for k, w in zip(unique, widest)}


#: Step 7's profile along a tube: bins of this length (mm), whatever the voxels.
PROFILE_BIN_MM = 1.5


def _step_up(count, fat):
    """Where a profile of fat fractions steps up: (bin, fraction before, fraction after), or None.

    One step fitted by least weighted squared error (weights: the shell's voxels in each bin), at least
    three bins before it and two after.
    """
    frac = fat / np.maximum(count, 1.0)
    best = None
    for split in range(3, count.size - 1):
        before, after = count[:split].sum(), count[split:].sum()
        if before == 0 or after == 0:
            continue
        mean_before, mean_after = fat[:split].sum() / before, fat[split:].sum() / after
        error = (count[:split] * (frac[:split] - mean_before) ** 2).sum() + (
            count[split:] * (frac[split:] - mean_after) ** 2).sum()
        if best is None or error < best[0]:
            best = (error, split, mean_before, mean_after)
    return None if best is None else best[1:]


def _outflow_tracts(tube, mouths, distance, pool, hu, spacing, *, ring_mm, fat_hu, min_rise, sleeve_fat, max_mm):
    """The stretch of each vessel tube from its mouth that is still its chamber's outflow tract.

    ``tube`` holds the lumen of vessel lobes open to a chamber (no narrowing
    between), past the heart body; ``mouths`` the part of it touching the
    chamber's blood.  Along each tube's axis (its core's, the voxels deeper
    than 0.8 of its widest: a tube's core is long and thin) from its mouth,
    the fraction of fat (below ``fat_hu``) ``ring_mm`` around the lumen, among
    the voxels nearer the tube than any other blood, is fitted by one step
    (:func:`_step_up`).  Where it rises by at least ``min_rise`` from at most
    ``sleeve_fat``, within ``max_mm`` of the mouth, the lumen before the step
    has a muscle wall (the right ventricle's infundibulum) and is the
    chamber's; after it the vessel lies in fat (the pulmonary trunk above its
    valve).  Where no such sleeve shows (a noisy CT: fat and muscle are not
    told apart voxel by voxel) the lobe is vessel from the body's edge, as
    without the CT; so where the rise comes farther out than an infundibulum
    reaches (slices of 4.5 mm blur the fat around the trunk into the
    tissue range up to its bifurcation, 58 mm out).

    Returns
    -------
    outflow : bool array like ``tube``
    lengths_mm : list of float
        How far each outflow tract reaches past its mouth, along the tube.
    """
    outflow = np.zeros_like(tube)
    lengths = []
    labels, _ = ndimage.label(tube)
    margin = [int(np.ceil(2.0 * ring_mm[1] / s)) + 1 for s in spacing]
    for label, found in enumerate(ndimage.find_objects(labels), start=1):
        box = tuple(slice(max(f.start - m, 0), min(f.stop + m, size))
                    for f, m, size in zip(found, margin, tube.shape))
        lumen = labels[box] == label
        mouth = lumen & mouths[box]
        if not mouth.any():
            continue
        core = np.argwhere(lumen & (distance[box] >= 0.8 * distance[box][lumen].max())) * spacing
        _, spread, axes = np.linalg.svd(core - core.mean(axis=0), full_matrices=False)
        axis = axes[0]
        if np.ptp(core @ axis) < 3 * PROFILE_BIN_MM or spread[0] < 2.0 * spread[1:].max(initial=0.0):
            continue  # no tube: a core as wide as long, or a few voxels
        k, j, i = np.ogrid[tuple(slice(0, n) for n in lumen.shape)]
        along = k * (spacing[0] * axis[0]) + j * (spacing[1] * axis[1]) + i * (spacing[2] * axis[2])
        if along[mouth].mean() > along[lumen].mean():
            along = -along
        along -= along[mouth].min()
        to_lumen = distance_mm(~lumen, spacing)
        ring = (to_lumen > ring_mm[0]) & (to_lumen <= ring_mm[1]) & ~pool[box] & (along >= 0.0)
        ring &= to_lumen < distance_mm(~(pool[box] & ~lumen), spacing)
        ring &= np.isfinite(hu[box])
        bins = (along[ring] // PROFILE_BIN_MM).astype(np.int64)
        found_step = _step_up(np.bincount(bins).astype(float), np.bincount(bins, weights=hu[box][ring] < fat_hu))
        if found_step is None:
            continue
        split, before, after = found_step
        length_mm = split * PROFILE_BIN_MM
        if before <= sleeve_fat and after - before >= min_rise and length_mm <= max_mm:
            outflow[box] |= lumen & (along < length_mm)
            lengths.append(length_mm)
    return outflow, lengths


def trace_great_vessels(
    pool,
    spacing_kji,
    *,
    min_radius_mm: float = 4.0,
    peak_spacing_mm: float = 7.5,
    max_vessel_radius_mm: float = 17.0,
    saddle_ratio: float = 0.8,
    widen_ratio: float = 1.1,
    wall_mm: float = 3.0,
    heart=None,
    leave_mm: float = 50.0,
    branch_ratio: float = 1.4,
    hu=None,
    ring_mm: tuple[float, float] = (1.0, 4.0),
    fat_hu: float = -30.0,
    min_fat_rise: float = 0.1,
    sleeve_fat: float = 0.25,
    max_outflow_mm: float = 25.0,
) -> GreatVessels:
    """Find the great vessels' lumen in a contrast blood pool.

    Parameters
    ----------
    pool : (n_k, n_j, n_i) bool
        Contrast-enhanced blood (one connected pool: chambers and vessels).
    spacing_kji : (3,) float, mm
        Voxel spacing along (k, j, i).
    min_radius_mm : float
        Peaks of the distance map below this radius start no lobe (thin vessels
        join the lobe they drain into).
    peak_spacing_mm : float
        Lobe peaks lie at least this far apart.
    max_vessel_radius_mm : float
        Lobes at the field of view's edge wider than this are chambers cut by
        the edge, not vessels (the aorta's lumen is 11-17 mm in radius, a
        chamber's 18-30 mm).  At 20 mm the real CT dimmed to a venous phase
        (``tests/modeling/test_realct.py::test_venous_phase``) lost its left
        atrium, cut by the field of view's edge, as a vessel.
    saddle_ratio : float
        A vessel continues into a neighbouring lobe across a saddle at least this
        fraction of the narrower lobe's radius (a valve or a junction narrows it more).
    widen_ratio : float
        ... into a neighbour at most this many times as wide as the vessel's
        narrowest lobe on the way (an aortic sinus is about as wide as the
        aorta, a chamber much wider).
    wall_mm : float
        Tissue closer to the lumen than to the chambers' blood, up to this far
        from the lumen and outside the heart's body (``heart``), is the
        vessels' wall.  Inside the body it is the chambers' myocardium around
        the aortic root's well: removed with the lumen, it put the
        anatomical phantom's well walls 2-3 mm outside the true ones.
    heart : bool array like the pool, optional
        The heart's body (the part of the segmentation's region a ball of the
        ventricles' size fits in: no vessel stub left below a near edge).  A
        lobe whose footprint on the edge lies mostly inside it is a chamber cut
        by the field of view, not a vessel leaving it: a right ventricle's thin
        crescent at the edge is as narrow and as compact there as a vessel
        (TotalSegmentator's aortic CTA with its lower edge through the right
        ventricle: a lobe of 10.6 mm, 91 % of its footprint inside the body,
        traced as a vessel and 39 ml of ventricle removed; every vessel leaving
        the real CTs' edges: 0 %).  With it, steps 4-6 above.
    leave_mm : float
        A lobe outside the heart body whose blood reaches farther than this
        from it is a vessel leaving the heart (step 4).  On TotalSegmentator's
        aortic CTA the lobes of the pulmonary arteries' branches reach 58-74
        mm from the body, the trunk's, the bifurcation's and the aortic root's
        30-31 mm (reached from their branches: no start), the other lobes
        outside the body (the right atrial appendage, the atria's outer
        corners) 23-26 mm.  A blind pouch reaching farther (an appendage
        longer than any seen here) would be taken for a vessel: its part
        outside the body where it opens into its chamber without a narrowing
        (step 6), all of it behind one.
    branch_ratio : float
        Outside the heart body the trace steps into a lobe at most this many
        times as wide as the vessel's narrowest lobe (step 5): Murray's
        2^(1/3) for a bifurcation of two equal branches, times 1.1 for the
        distance map's unevenness.  On ``shared/realct`` the pulmonary trunk
        (12.1 mm) is 1.26 times its left branch (9.6 mm); a right atrium
        outside the body fed by a superior vena cava of 10 mm, or a left
        atrium fed by veins of 7 mm, 1.5 times and more
        (``tests/modeling/test_greatvessels.py``).
    hu : float array like the pool, optional
        The CT on the pool's grid, for step 7 (without it the vessel open to a
        chamber is cut at the body's edge).
    ring_mm, fat_hu, min_fat_rise, sleeve_fat
        Step 7: the shell around the lumen whose fat (below ``fat_hu``) is
        counted, the least rise of its fraction that marks the valve, and the
        most fat a muscle sleeve below it holds (``shared/realct``: 0.20
        below, 0.36 above; with 70 or 100 HU of white noise added 0.35 / 0.34
        below, a rise found 38-40 mm up the trunk, which kept 10 ml of it).
    max_outflow_mm : float
        Step 7: an outflow tract reaches at most this far past the body (the
        right ventricle's infundibulum is 15-20 mm long; ``shared/realct``:
        15 mm).

    Returns
    -------
    GreatVessels
        Empty masks when no vessel leaves the field of view or the heart's surroundings.
    """
    from skimage.feature import peak_local_max
    from skimage.segmentation import watershed

    pool = np.asarray(pool, dtype=bool)
    if pool.ndim != 3:
        raise ValueError(f"pool must be a 3-D mask (k, j, i), got shape {pool.shape}")
    spacing = np.asarray(spacing_kji, dtype=float).reshape(3)
    empty = np.zeros(pool.shape, bool)
    found = ndimage.find_objects(pool.astype(np.uint8))
    if not found:
        return GreatVessels(empty, empty, (), "great vessels: no lobe in the blood pool")
    # work in the pool's box (with room for the walls); only the volume's own sides are the field of view's edge
    room = [int(np.ceil(wall_mm / s)) + 1 for s in spacing]
    box = tuple(slice(max(b.start - r, 0), min(b.stop + r, n)) for b, r, n in zip(found[0], room, pool.shape))
    edges = [(axis, end) for axis in range(3) for end, at_edge in
             ((0, box[axis].start == 0), (-1, box[axis].stop == pool.shape[axis])) if at_edge]
    full_shape, pool = pool.shape, pool[box]
    distance = distance_mm(pool, spacing)
    gap = max(1, int(round(peak_spacing_mm / float(spacing.min()))))
    peaks = peak_local_max(distance, min_distance=gap, threshold_abs=min_radius_mm,
                           labels=pool.astype(np.int32), exclude_border=False)
    if len(peaks) == 0:
        return GreatVessels(empty, empty, (), "great vessels: no lobe in the blood pool")
    markers = np.zeros(pool.shape, np.int32)
    markers[tuple(peaks.T)] = np.arange(1, len(peaks) + 1)
    lobes = watershed(-distance, markers, mask=pool)
    n = len(peaks)
    radius = np.zeros(n + 1)
    radius[1:] = label_maximum(distance, lobes, n)
    neighbours: list[list[tuple[int, float]]] = [[] for _ in range(n + 1)]
    for (a, b), width in _saddles(lobes, distance, n).items():
        neighbours[a].append((b, width))
        neighbours[b].append((a, width))

    sides = np.concatenate([np.take(lobes, end, axis=axis).ravel() for axis, end in edges] + [np.zeros(1, int)])
    starts = [int(i) for i in np.unique(sides) if i > 0 and radius[i] <= max_vessel_radius_mm]
    inside = np.zeros(n + 1, bool)  # lobes mostly inside the heart body
    outside = np.zeros(n + 1, bool)  # ... and mostly outside it (neither known without the body)
    heart_box = None
    if hu is not None and np.shape(hu) != full_shape:
        raise ValueError(f"hu must have the pool's shape {full_shape}, got {np.shape(hu)}")
    if heart is not None:
        if np.shape(heart) != full_shape:
            raise ValueError(f"heart must have the pool's shape {full_shape}, got {np.shape(heart)}")
        heart_box = np.asarray(heart, dtype=bool)[box]
        # a chamber cut by the edge, not a vessel leaving there
        on_heart = np.concatenate([np.take(heart_box, end, axis=axis).ravel() for axis, end in edges] + [[False]])
        on_edge, in_heart = np.bincount(sides, minlength=n + 1), np.bincount(sides, weights=on_heart, minlength=n + 1)
        cut_chambers = {i for i in starts if in_heart[i] > 0.5 * on_edge[i]}
        starts = [i for i in starts if i not in cut_chambers]
        if heart_box.any():  # vessels leaving the heart's surroundings, wherever they end
            inside[1:] = ndimage.mean(heart_box, lobes, np.arange(1, n + 1)) > 0.5
            outside[1:] = ~inside[1:]
            reach = np.zeros(n + 1)
            reach[1:] = label_maximum(distance_mm(~heart_box, spacing), lobes, n)
            leaving = np.flatnonzero(outside & (reach > leave_mm) & (radius <= max_vessel_radius_mm))
            starts = sorted(set(starts) | ({int(i) for i in leaving} - cut_chambers))
    vessel = np.zeros(n + 1, bool)
    vessel[starts] = True
    narrowest = radius.copy()  # the narrowest lobe on the way from the start
    stack = sorted(starts, key=lambda i: radius[i])
    while stack:
        a = stack.pop(0)
        for b, width in neighbours[a]:
            if not vessel[b] and width >= saddle_ratio * min(radius[a], radius[b]) and (
                    radius[b] <= widen_ratio * narrowest[a]
                    or (outside[b] and radius[b] <= min(max_vessel_radius_mm, branch_ratio * narrowest[a]))):
                vessel[b] = True
                narrowest[b] = min(narrowest[a], radius[b])
                stack.append(b)
    if not vessel.any():
        return GreatVessels(empty, empty, (), "great vessels: no blood leaves the field of view")
    lumen = np.zeros(full_shape, bool)
    lumen[box] = vessel[lobes]
    lengths = []
    if outside.any():  # a vessel lobe open to a chamber's runs on into it: only its part outside the body
        chamber = inside & ~vessel
        opened = np.zeros(n + 1, bool)
        for past_opened in (False, True):  # again past the lobes that went: lobes outside the body only
            candidates = vessel & ~opened & (outside if past_opened else True)
            for a in np.flatnonzero(candidates):
                opened[a] = any(chamber[b] and width >= saddle_ratio * min(radius[a], radius[b])
                                for b, width in neighbours[a])
            lumen[box] &= ~(opened[lobes] & heart_box)
            # gone: left without lumen, or opened and mostly inside (its stub past the body is the chamber's too)
            gone = vessel & ((np.bincount(lobes[lumen[box]], minlength=n + 1) == 0) | (opened & inside))
            lumen[box] &= ~gone[lobes]
            chamber |= gone
            vessel &= ~gone
        if not vessel.any():
            return GreatVessels(empty, empty, (), "great vessels: none outside the heart's body")
        if hu is not None:  # ... and past the body as far as a muscle wall surrounds it (step 7)
            tube = lumen[box] & opened[lobes]
            mouths = tube & ndimage.binary_dilation(pool & heart_box & ~lumen[box])
            outflow, lengths = _outflow_tracts(
                tube, mouths, distance, pool, np.asarray(hu)[box], spacing, ring_mm=ring_mm, fat_hu=fat_hu,
                min_rise=min_fat_rise, sleeve_fat=sleeve_fat, max_mm=max_outflow_mm)
            lumen[box] &= ~outflow
            vessel &= np.bincount(lobes[lumen[box]], minlength=n + 1) > 0
    to_lumen = distance_mm(~lumen[box], spacing)
    to_chambers = distance_mm(~(pool & ~lumen[box]), spacing)
    wall = (to_lumen < to_chambers) & (to_lumen <= wall_mm)
    if heart_box is not None:  # inside the heart's body the tissue around a lumen is the chambers' myocardium
        wall &= ~heart_box
    territory = np.zeros(full_shape, bool)
    territory[box] = lumen[box] | wall
    radii = tuple(sorted((float(r) for r in radius[vessel]), reverse=True))
    volume_ml = float(lumen.sum() * np.prod(spacing) / 1000.0)
    note = (
        f"great vessels traced to their valves: {len(radii)} lobe(s) of "
        f"{radii[-1]:.0f}-{radii[0]:.0f} mm radius, {volume_ml:.0f} ml of lumen; with their walls "
        f"(up to {wall_mm:.0f} mm) outside the heart's body they are not heart"
    )
    if lengths:
        note += (f"; outflow tract(s) kept {', '.join(f'{x:.0f}' for x in lengths)} mm past the body, "
                 "in muscle up to where fat surrounds the vessel")
    return GreatVessels(lumen, territory, radii, note)
