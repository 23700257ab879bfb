"""Where the heart starts in a CT, and what its tissue touches that is no heart.

- :func:`blood_pool`: the contrast blood pool, the segmentation's seed, at the
  contrast level the CT has (arterial or venous phase);
- :func:`blood_noise_hu`: the CT's noise, measured in the blood pool;
- :func:`mediastinal_seed`: without contrast, the thickest soft tissue between
  the lungs;
- :func:`split_solid_organs`: with contrast, the solid organs joined to the
  heart's tissue (the liver through a thick slice's blurred diaphragm),
  parted from it;
- :func:`part_abdomen`: without contrast, the liver under the diaphragm
  parted from the heart's soft tissue.

Both part at the dimmest layer between the heart and the other organ (the
diaphragm's, with the fat over it): a watershed of the HU, brightest first,
from markers of each (:func:`_flood`).

All work on the segmentation's coarse grid (:mod:`modeling.segment`).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from modeling.coarse import fill_holes, label_counts, label_maximum, mask_box
from modeling.distance import distance_mm, opening_mm

__all__ = ["blood_ceiling_hu", "blood_noise_hu", "blood_pool", "mediastinal_seed", "not_hounsfield", "part_abdomen",
           "pool_at_the_cts_noise", "split_solid_organs"]

#: Step (HU) by which the blood pool's lower bound is lowered towards ``blood_floor_hu`` when no chamber is found.
POOL_STEP_HU = 25.0

#: Solid tissue holding a ball of this radius (mm), farther than SOLID_FAR_MM from blood, is no heart wall
#: (``split_solid_organs``): the left ventricle's wall is 8-12 mm thick, the apex lies within ~15 mm of blood.
SOLID_RADIUS_MM = 12.0
SOLID_FAR_MM = 30.0
#: Solid tissue between the lungs is spared as heart (a right heart washed out by a saline chaser), unless lung lies
#: within this distance (mm) straight above it: a liver's dome under a lung's base (on 4.5 mm slices of
#: TotalSegmentator's aortic CTA cut 15 mm below the heart, sparing all of it kept 331 ml of liver; at 10 mm 36-71
#: ml more than sparing none; at 20 mm the washed-out right heart of ``shared/realct`` was lost again).
UNDER_LUNG_MM = 10.0
#: Farthest the heart's tissue reaches beyond the box of its blood pool (mm; a washed-out right ventricle's wall ~50).
HEART_REACH_MM = 60.0
#: Blood holding a ball of this radius (mm), in a part of the pool that holds a chamber's ball
#: (CHAMBER_BALL_MM), is a chamber's or a great artery's lumen; the pool within BLOOD_REACH_MM of that
#: lumen seeds the heart in ``split_solid_organs`` (see ``_heart_seeds``).  At 20 mm the human phantom's
#: right atrium (seed 4) lay beyond it and went with the liver; TotalSegmentator's aortic CTA on 4.5 mm
#: slices keeps its liver out at 30 mm as at 20 (``tests/modeling/test_aortic_cta.py``).
CHAMBER_CORE_MM = 8.0
CHAMBER_BALL_MM = 15.0
BLOOD_REACH_MM = 30.0
#: Blood components smaller than this (ml) are specks (noise, a small vessel), not blood that makes tissue
#: near it heart wall (``split_solid_organs``).
BLOOD_SPECK_ML = 1.0

#: Room air reads -1000 HU, lung -900 to -700 (it holds tissue and blood): CTChest4's outside air -994 HU
#: (median), its lungs -864; the real CT's lungs, cut by its tight field of view, -798.
ROOM_AIR_HU = -950.0

#: Inscribed radius (mm) a pool found below ``blood_hu[0]`` must hold (see ``blood_pool``).
WEAK_POOL_RADIUS_MM = 18.0
#: Components tried, largest first, at each level below ``blood_hu[0]``.
WEAK_POOL_CANDIDATES = 3


#: A CT in Hounsfield units holds fat, lung or air below FAT_HU in at least MIN_FAT_SHARE of its voxels (a
#: heart lies in fat: the real CT cropped around it has 47 % there, a whole chest 56-76 %); an MR
#: (TotalSegmentator's example: -47 to 833) or a CT stored without its rescale (0 to 4095) has none; such a CT
#: padded outside its circular field of view with negative values passes, and fails later in the segmentation.
FAT_HU = -80.0
MIN_FAT_SHARE = 0.005


def not_hounsfield(coarse, hu) -> str | None:
    """Why a volume is no CT in Hounsfield units, or None: too little of its ``coarse`` grid lies below
    :data:`FAT_HU` (fat, lung, air), so its values would be read as HU they are not."""
    share = float(np.mean(coarse < FAT_HU))
    if share >= MIN_FAT_SHARE:
        return None
    return (f"the volume does not look like a CT in Hounsfield units: {100 * share:.1f} % of it lies below "
            f"{FAT_HU:.0f} HU (fat, lung, air; its values run {float(np.min(hu)):.0f} to {float(np.max(hu)):.0f}); "
            "an MR, or a CT stored without its rescale, cannot be segmented: give a CT, or a heart mask with --mask")


#: A cavity of the blood pool of at most this many voxels of its grid, and mm^3 (a ball of 2 mm radius), is a
#: speckle of its blood.
SPECKLE_VOXELS = 2
SPECKLE_MM3 = 35.0


def _with_speckles(pool, cspacing) -> np.ndarray:
    """The pool with its cavities of :data:`SPECKLE_VOXELS` voxels and :data:`SPECKLE_MM3` at most: its noise.

    With white noise of 40-50 HU standard deviation on the real CT they riddle the left atrium (700-1100
    cavities, most of a voxel or two): its inscribed radius fell from 24 mm to 16-18, and the vessel trace
    took its lobes at the field of view's edge for vessels leaving it (426-469 ml of heart left instead of
    707).  Without noise added the real CTs have them too: on TotalSegmentator's aortic CTA they narrowed
    the outflow tract's lobe (13.2 mm, 13.6 without), so that the trace ran from the pulmonary trunk into
    the right ventricle.  Larger cavities stay out: the aortic valve's leaflets and calcium (filled up to 35
    mm^3, the trace ran through the annulus into the outflow tract), a stent's struts, and, at a weak
    pool's level, the skeleton's marrow's cavities (filled whole, or two of CTChest4's 3 x 3 x 10 mm voxels,
    they made a pool of its bones).
    """
    return fill_holes(pool, max_voxels=int(min(SPECKLE_VOXELS, SPECKLE_MM3 // float(np.prod(cspacing)))))


def blood_pool(coarse, cspacing, blood_hu, min_radius_mm, floor_hu, mediastinum=None):
    """The contrast blood pool and the lower HU that found it, or (None, None) without contrast.

    The pool is the largest component of ``blood_hu`` voxels if it holds a
    ball of ``min_radius_mm`` (a cardiac chamber's lumen).  Contrast timing
    sets how bright blood is: 300-600 HU in an arterial phase, 150-250 HU in a
    venous one, where no chamber reaches ``blood_hu[0]``.  The lower bound is
    then lowered by :data:`POOL_STEP_HU` down to ``floor_hu`` (above
    myocardium and liver, 60-130 HU) until a chamber is found, a larger one
    (:data:`WEAK_POOL_RADIUS_MM`): below 200 HU the skeleton's marrow joins
    into components of a size with a chamber (CTChest4 of slicerio, without
    contrast: 476 ml holding a 15.5 mm ball at 175 HU), while a venous phase
    fills all four chambers (the real CT's pool at 150 HU, dimmed to a venous
    phase: 20 mm).  Such a pool must also lie between the lungs where there
    are lungs: ``mediastinum()`` gives that region (None without lungs), so
    that the marrow of a pelvis on a whole-body CT is no pool.

    The pool's speckles are blood too (:func:`_with_speckles`).
    """
    for low in np.arange(blood_hu[0], min(floor_hu, blood_hu[0]) - 1e-9, -POOL_STEP_HU):
        weak = low < blood_hu[0]
        radius_mm = max(min_radius_mm, WEAK_POOL_RADIUS_MM) if weak else min_radius_mm
        blood = (coarse > low) & (coarse < blood_hu[1])
        labels, n = ndimage.label(blood)
        if n == 0:
            continue
        sizes = label_counts(blood, labels, n)
        # the largest component; at a weak level the next ones too (WEAK_POOL_CANDIDATES), where a whole-body
        # CT's marrow may outgrow the heart's pool
        for label in np.argsort(-sizes)[: WEAK_POOL_CANDIDATES if weak else 1] + 1:
            pool = _with_speckles(labels == label, cspacing)
            box = ndimage.find_objects(pool.astype(np.uint8))[0]
            if distance_mm(np.pad(pool[box], 1), cspacing).max() < radius_mm:
                continue
            if weak and mediastinum is not None:
                between = mediastinum()
                if between is not None and not (pool & between).any():
                    continue
            return pool, float(low)
    return None, None


#: The pool reaches this many times the blood's own level (:func:`blood_ceiling_hu`), at least ``blood_hu[1]``.
BRIGHT_BLOOD_FACTOR = 1.3
#: Least volume (ml) of the lumen's core (at least CHAMBER_CORE_MM deep) that raises the pool's upper bound: the
#: chambers' (the real CT's: 126 ml), not a dense vertebra's or a calcified mass's (a ball of
#: 14 mm radius: 1 ml; lung1 without contrast with one at 800 HU in a vertebral body got a 1041 HU bound, and the
#: vertebra became the pool: a "heart" of 129 ml in the spine; session 29's review).
BRIGHT_CORE_ML = 20.0


def blood_ceiling_hu(coarse, cspacing, blood_hu, hu_high, mediastinum=None) -> float:
    """The pool's upper HU for this CT's contrast: ``blood_hu[1]``, or above it for brighter blood.

    The upper bound keeps bone's cortex, calcium and metal out of the pool; 650
    HU holds diagnostic CTAs at 120 kV (blood 300-600 HU: the real CT's 496).
    At 70-80 kV (low-dose cardiac CT, children) and in a dual-energy CT's
    40-50 keV image, iodine reads 700-1200 HU: the pool, only blood below
    650 HU, then broke apart (the real CT's blood scaled to 600 HU: Dice 0.863;
    to 750 HU or more: no model).  The blood's level is the median HU of the
    chambers' lumen: the voxels at least :data:`CHAMBER_CORE_MM` deep in the
    largest component above ``blood_hu[0]`` (below ``hu_high``); the bound is
    :data:`BRIGHT_BLOOD_FACTOR` times that, capped at ``hu_high``.  It is
    raised only for a core of a chamber's size (:data:`BRIGHT_CORE_ML`), and
    only the core's part between the lungs counts where there are lungs
    (``mediastinum()``, as :func:`blood_pool`): a dense vertebra, a calcified
    mass, a bladder full of excreted contrast joined through the aorta raise
    nothing.  Without contrast the largest component is
    the skeleton, whose thin marrow and cortex hold no such core.
    """
    bright = (coarse > blood_hu[0]) & (coarse < hu_high)
    labels, n = ndimage.label(bright)
    if n == 0:
        return float(blood_hu[1])
    largest = labels == int(np.argmax(label_counts(bright, labels, n))) + 1
    box = mask_box(largest)
    core = distance_mm(np.pad(largest[box], 1), cspacing)[1:-1, 1:-1, 1:-1] >= CHAMBER_CORE_MM  # the edge: outside

    def level(part):  # the part's median HU, or None for a part smaller than a chamber's core
        small = np.count_nonzero(part) * float(np.prod(cspacing)) / 1000.0 < BRIGHT_CORE_ML
        return None if small else float(np.median(coarse[box][part]))

    found = level(core)
    if found is None or BRIGHT_BLOOD_FACTOR * found <= blood_hu[1]:
        return float(blood_hu[1])  # the common case: the lungs' region is not needed
    between = None if mediastinum is None else mediastinum()
    if between is not None:  # only the core between the lungs: not a bladder joined to it through the aorta
        found = level(core & between[box])
        if found is None:
            return float(blood_hu[1])
    return float(max(blood_hu[1], min(hu_high, BRIGHT_BLOOD_FACTOR * found)))


#: Distance (mm) between the voxels whose HU differences measure the blood's noise (:func:`blood_noise_hu`).
NOISE_LAG_MM = 4.0
#: The blood's noise (HU, :func:`blood_noise_hu`) up to which the segmentation's coarse grid is smoothed over
#: ``smooth_mm``; above, over ``smooth_mm * sqrt(noise / NOISE_HU)``.  Diagnostic contrast CTs: 36 HU
#: (``shared/realct``, TotalSegmentator's aortic CTA), the phantoms 4-25.  With white noise added to
#: ``shared/realct`` the model collapsed from 50 HU on (70 HU: 357 ml of 707, Dice 0.61 against the reference).
NOISE_HU = 40.0


def blood_noise_hu(raw, pool, cspacing) -> float | None:
    """The CT's noise (HU, one standard deviation) in the blood pool, or None where the pool is too thin.

    Contrast blood is the CT's most uniform tissue, but not uniform between chambers (the right heart, the
    left, the aorta differ by 100 HU and more in an arterial phase), so the spread of its HU is no noise
    measure (43 HU on ``shared/realct`` without added noise).  Differences between voxels
    :data:`NOISE_LAG_MM` apart, both two voxels inside the pool, cancel those slow changes and keep the
    noise, correlated noise up to that scale too: their robust spread (1.4826 x the median absolute
    deviation) over sqrt(2), the median of the three axes.  ``raw`` are the unsmoothed block means.
    Measured on ``shared/realct``: 36 HU; with white noise of 30 / 50 / 70 / 100 HU added 49 / 64 / 82 /
    108 (the quadrature sums 47 / 62 / 79 / 106), with 60 HU of noise correlated over ~1.5 mm 66 (70).
    """
    core = ndimage.binary_erosion(pool, iterations=2)
    spreads = []
    for axis in range(3):
        lag = max(1, int(round(NOISE_LAG_MM / float(cspacing[axis]))))
        n = raw.shape[axis] - lag
        if n <= 0:
            continue
        both = np.take(core, range(n), axis=axis) & np.take(core, range(lag, lag + n), axis=axis)
        if np.count_nonzero(both) < 1000:
            continue
        d = (np.take(raw, range(n), axis=axis) - np.take(raw, range(lag, lag + n), axis=axis))[both]
        spreads.append(1.4826 * float(np.median(np.abs(d - np.median(d)))) / np.sqrt(2.0))
    return float(np.median(spreads)) if spreads else None


#: Smoothing (mm) of the coarse grid at which the blood pool is looked for again, to measure the CT's noise in it,
#: when none is found at the light smoothing: a sharp kernel's edge overshoot with 100 HU of noise parted the real
#: CT's pool in 3 of 5 noise draws (no model), the noise then unmeasured and the grid not smoothed for it.
NOISE_PROBE_MM = 1.2


def pool_at_the_cts_noise(raw, coarse, cspacing, smooth_mm, blood_hu, min_radius_mm, floor_hu, mediastinum):
    """The blood pool (:func:`blood_pool`) on a coarse grid smoothed for the CT's noise.

    ``coarse`` is ``raw`` smoothed over ``smooth_mm``; where the pool's noise
    (:func:`blood_noise_hu`) is above :data:`NOISE_HU` the grid is smoothed
    again over ``smooth_mm * sqrt(noise / NOISE_HU)`` and the pool looked for
    on it.  Where no pool is found at ``smooth_mm`` the noise is measured in
    one found smoothed over :data:`NOISE_PROBE_MM` (the smoothing for ~160 HU
    of noise); that pool serves only to measure it, and the grid is then
    smoothed at least as much.

    Returns
    -------
    (pool, pool_hu, coarse, note) : the pool or None, its lower HU, the grid it was found on, and a note
    when the grid was smoothed for noise (else None).
    """
    pool, pool_hu = blood_pool(coarse, cspacing, blood_hu, min_radius_mm, floor_hu, mediastinum)
    probe = pool
    if probe is None and smooth_mm > 0:
        probe = blood_pool(ndimage.gaussian_filter(raw, sigma=NOISE_PROBE_MM / cspacing), cspacing, blood_hu,
                           min_radius_mm, floor_hu, mediastinum)[0]
    noise = None if probe is None or smooth_mm <= 0 else blood_noise_hu(raw, probe, cspacing)
    if noise is None or noise <= NOISE_HU:
        return pool, pool_hu, coarse, None
    smoothing = smooth_mm * float(np.sqrt(noise / NOISE_HU))
    if pool is None:  # found by the probe: at least its smoothing, where the pool was seen
        smoothing = max(smoothing, NOISE_PROBE_MM)
    coarse = ndimage.gaussian_filter(raw, sigma=smoothing / cspacing)
    pool, pool_hu = blood_pool(coarse, cspacing, blood_hu, min_radius_mm, floor_hu, mediastinum)
    return pool, pool_hu, coarse, (f"noisy CT (the blood's noise {noise:.0f} HU, above {NOISE_HU:.0f}): the coarse "
                                   f"grid smoothed over {smoothing:.2f} mm instead of {smooth_mm:.2f}")


def split_solid_organs(region, pool, coarse, cspacing, blood_hu, height_axis: int = 0, mediastinum=None, up_kji=None):
    """Part the heart from solid organs its tissue touches (the liver under the diaphragm).

    On a thick-slice CT (3 mm and more) the diaphragm and the fat over it
    blur into the tissue range, and the liver joins the heart over a broad
    front that no opening can cut.  With contrast, the heart's tissue is a
    wall around its blood: nowhere is it both thicker than
    2 x :data:`SOLID_RADIUS_MM` (a ball of that radius fits in no myocardium)
    and farther than :data:`SOLID_FAR_MM` from blood (above ``blood_hu``, in
    components of :data:`BLOOD_SPECK_ML` or more: every enhanced chamber).
    Such tissue is another organ, unless it lies between the lungs
    (``mediastinum``: the region between them and the lungs, from
    :func:`mediastinal_seed`, when the CT shows them) and not just under a
    lung (:data:`UNDER_LUNG_MM` along ``up_kji``, the patient's height per
    index step, needed with ``mediastinum``): a right heart whose contrast has washed out (a saline chaser,
    the usual coronary CTA) is as thick and as far from the left heart's
    blood, and nearly as dim as a liver; the chest wall lies outside the
    lungs, the liver below them or, its dome, under a lung's base.  On ``shared/realct`` with its right heart's blood dimmed to
    100 HU the segmentation kept 434 ml (the right heart went with the chest
    wall: Dice 0.705 against the reference less its pulmonary artery); with
    the mediastinum spared, 693 ml and 0.908, as at full contrast.  The other
    organ and the blood seed a watershed of the HU
    (brightest first), which floods each organ up to the dimmest layer between
    them, the diaphragm's.  The heart's seed is the pool near its chambers
    only (:func:`_heart_seeds`): blood in the other organ (a liver's veins)
    would flood it from within.  What the other organ's front took where the
    heart's part encloses it in a plane across ``height_axis`` (the array
    axis along the patient's height) is given back (:func:`_enclosed`).
    Returns the heart's part of ``region`` and a note (empty when nothing is
    split).
    """
    # the heart lies within HEART_REACH_MM of its pool's box: the rest of the region (chest wall, abdomen) is
    # no heart, and leaving it out keeps the distance maps and the watershed small
    pad = np.ceil(HEART_REACH_MM / cspacing).astype(int)
    box = tuple(slice(max(p.start - d, r.start), min(p.stop + d, r.stop)) for p, r, d in zip(
        ndimage.find_objects(pool.astype(np.uint8))[0], ndimage.find_objects(region.astype(np.uint8))[0], pad))
    inside, hu = region[box], coarse[box]
    blood_pool = pool[box] & inside
    if not blood_pool.any():  # a region grown from a given point away from the pool: nothing to part it from
        return region, ""
    # blood, but not its specks: on thin noisy slices a liver is speckled with voxels as bright as blood, which
    # broke its marker (TotalSegmentator's aortic CTA with every third 1.5 mm slice: 850 ml with a lobe of liver,
    # its marker 20 ml, against 701 ml without); blood apart from the pool counts (a right heart apart from it)
    labels, n = ndimage.label(hu > blood_hu)
    ml = label_counts(labels > 0, labels, n) * float(np.prod(cspacing)) / 1000.0
    blood = np.isin(labels, np.flatnonzero(ml >= BLOOD_SPECK_ML) + 1)
    del labels
    solid = opening_mm(inside & ~blood, cspacing, SOLID_RADIUS_MM)
    solid &= distance_mm(~blood, cspacing) > SOLID_FAR_MM
    if mediastinum is not None:  # a washed-out right heart is no liver; a liver's dome lies under a lung's base
        between, lung = (m[box] for m in mediastinum)
        up = float(up_kji[height_axis])
        solid &= ~(between & ~_under(lung, height_axis, up > 0, max(1, int(round(UNDER_LUNG_MM / abs(up))))))
    if not solid.any() and inside.sum() == region.sum():
        return region, ""
    seeds, flood_hu = _heart_seeds(blood_pool, hu, cspacing)
    heart = _flood(flood_hu, seeds, solid, inside)
    heart |= _enclosed(heart, height_axis) & inside
    out = np.zeros_like(region)
    out[box] = heart
    removed_ml = float((region.sum() - heart.sum()) * np.prod(cspacing) / 1000.0)
    solid_note = (f"solid organs at their dimmest layer (thicker than {2 * SOLID_RADIUS_MM:.0f} mm and farther than "
                  f"{SOLID_FAR_MM:.0f} mm from blood: liver, chest wall), " if solid.any() else "")
    return out, (f"{removed_ml:.0f} ml of tissue parted from the heart: {solid_note}all beyond "
                 f"{HEART_REACH_MM:.0f} mm of the blood pool")


def _under(mask, axis: int, up: bool, reach: int) -> np.ndarray:
    """Voxels with a voxel of ``mask`` at most ``reach`` voxels above them along ``axis`` (``up``: the index grows
    upwards)."""
    m = np.moveaxis(mask, axis, 0)
    out = np.zeros_like(m)
    for d in range(1, reach + 1):
        if up:
            out[:-d] |= m[d:]
        else:
            out[d:] |= m[:-d]
    return np.moveaxis(out, 0, axis)


def _heart_seeds(pool, hu, cspacing):
    """The heart's seeds for :func:`_flood` and the HU it floods: the pool near the chambers' lumen;
    blood farther from it is flooded last.

    Contrast refluxing from the right atrium into the inferior vena cava and
    the liver's veins joins them to the pool.  Seeded, or flooded as early as
    the chambers (they are as bright), they carry the heart's front into the
    liver from within, past the diaphragm (TotalSegmentator's aortic CTA
    averaged to 4.5 mm slices: 1095 ml with a lobe of liver, against 740 ml at
    its 1.5 mm).  The chambers' lumen is the pool's part holding a ball of
    :data:`CHAMBER_CORE_MM` where that part also holds one of
    :data:`CHAMBER_BALL_MM`; the pool within :data:`BLOOD_REACH_MM` of it seeds
    the heart.  The rest of the pool is given the lowest HU, so that it goes
    to the organ around it; blood apart from the pool keeps its HU (the
    anatomical phantom's right heart, apart from its left at full size, lost
    the caval junctions when it was lowered too: inferior vena cava 1.4 ->
    20 mm from its origin).  Unchanged when the pool holds no such lumen.
    """
    hu = np.asarray(hu, dtype=np.float32)  # lowered to its minimum, an integer HU would wrap when negated
    depth = distance_mm(pool, cspacing)
    labels, n = ndimage.label(depth >= CHAMBER_CORE_MM)
    if n == 0:
        return pool, hu
    cores = np.isin(labels, np.flatnonzero(label_maximum(depth, labels, n) >= CHAMBER_BALL_MM) + 1)
    if not cores.any():
        return pool, hu
    # the lumen reaches CHAMBER_CORE_MM beyond its cores: within BLOOD_REACH_MM of it, the cores' reach plus that
    near = distance_mm(~cores, cspacing) <= CHAMBER_CORE_MM + BLOOD_REACH_MM
    return pool & near, np.where(pool & ~near, hu.min(), hu)


def _enclosed(heart, height_axis: int) -> np.ndarray:
    """What ``heart`` encloses in each plane across the patient's height (its holes in axial slices).

    An organ below the heart meets it at the diaphragm and lies inside none of
    its cross-sections; what its flood takes there came up through a vessel.
    The inferior vena cava's unopacified stream (150 HU) reaches into the
    right atrium: on the anatomical phantom (seed 1) the liver's front climbed
    it along its noise, a channel of 1 ml about 6 mm wide into the atrium,
    which left the atrium no ball of the heart body's radius (inscribed radius
    21.6 -> 5 mm), and the vessel cut took it (truth -> mesh p95 23.4 mm; 3.3
    with the channel given back).  Filled in 3-d, closed over 6 mm, it took back
    22 ml of liver around the vena cava of TotalSegmentator's aortic CTA on
    4.5 mm slices; filled in the axial planes, 4 ml (its mouth at the atrium).
    """
    from scipy.ndimage import binary_fill_holes

    planes = np.moveaxis(heart, height_axis, 0)
    return np.moveaxis(np.stack([binary_fill_holes(p) for p in planes]), 0, height_axis)


def _flood(hu, heart, other, inside):
    """The part of ``inside`` flooded from ``heart`` when it and ``other`` flood the HU, brightest first."""
    from skimage.segmentation import watershed

    out = np.zeros(hu.shape, bool)
    box = mask_box(inside)
    if box is None:
        return out
    # within the box that holds ``inside`` (the flood stays in it; the voxels keep their raster order, and so
    # the flood's ties): a whole-chest CT's body fills a fraction of its volume
    markers = np.zeros(hu[box].shape, np.int32)
    markers[other[box]] = 2
    markers[heart[box]] = 1
    out[box] = watershed(-np.asarray(hu[box]), markers, mask=inside[box]) == 1
    return out


def part_abdomen(body, heart, hu, cspacing, up_kji):
    """Part the liver under the diaphragm from the heart's soft tissue, in a CT without contrast.

    Without contrast the heart's blood and walls (35-50 HU) are one soft
    tissue with the liver beneath (55-70 HU), and where the diaphragm presses
    them together no opening parts them (a third of the slicerio package's
    CTChest4, 10 mm slices, and of pyradiomics' lung2, 5 mm, was liver).
    ``heart`` is the heart body (the part of ``body`` a ball of the ventricles'
    size fits in); ``up_kji`` the patient's height (LPS z, mm) gained per
    index step along each array axis.  Tissue of ``body`` lower than the heart body's lowest
    level and farther than :data:`SOLID_FAR_MM` from it is the abdomen's: no
    atrium or vessel mouth of the heart reaches there (the right atrium lies
    beside the ventricles, the inferior vena cava's mouth within ~20 mm).  It
    and the heart body flood the HU (:func:`_flood`) up to the dimmest layer
    between them, the diaphragm's.  Returns the heart's part of ``body`` and a
    note (empty when nothing is parted).
    """
    k, j, i = (np.arange(n, dtype=np.float32) * float(u) for n, u in zip(body.shape, up_kji))
    height = k[:, None, None] + j[None, :, None] + i[None, None, :]
    below = height < height[heart].min()
    other = body & below & (distance_mm(~heart, cspacing) > SOLID_FAR_MM)
    if not other.any():
        return body, ""
    part = _flood(hu, heart, other, body)
    removed_ml = float((body.sum() - part.sum()) * np.prod(cspacing) / 1000.0)
    return part, (f"{removed_ml:.0f} ml of soft tissue below the heart parted from it at its dimmest layer (the "
                  f"diaphragm; farther than {SOLID_FAR_MM:.0f} mm below the heart body: liver)")


def mediastinal_seed(coarse, cspacing, *, lung_hu, soft_hu, height_axis: int = 0):
    """Seed of a CT without contrast: the thickest soft tissue lying between the lungs.

    Lungs are the air components larger than 100 ml enclosed in the body
    (not touching the volume's sides in-plane) or, where a tight field of view
    cuts them, denser than room air (median above :data:`ROOM_AIR_HU`).  A voxel lies *between the
    lungs* when it is inside the convex hull of the lungs in its slice (the
    mediastinum, and the heart in it).  The soft-tissue voxel of that
    region farthest from anything else is the heart's centre (the great
    vessels, oesophagus and chest wall are thinner; the liver lies below the
    lungs).

    ``height_axis`` is the array axis along the patient's height (0 for a CT
    stored as axial slices): the hull is taken in the planes across it.

    Returns
    -------
    (seed, between, lung) : bool arrays like ``coarse`` (the seed: one voxel), or
        None if no lungs or no soft tissue between them are found.
    """
    from skimage.morphology import convex_hull_image

    air = coarse < lung_hu
    labels, n = ndimage.label(air)
    sides = np.unique(np.concatenate([np.take(labels, [0, -1], axis=a).ravel() for a in range(3) if a != height_axis]))
    sizes = label_counts(air, labels, n) * np.prod(cspacing) / 1000.0
    is_lung = np.zeros(n + 1, bool)
    is_lung[1:] = sizes > 100.0
    # air at the volume's sides is the room's, unless it is lung cut by a tight field of view (a cardiac
    # reconstruction): lung holds tissue and blood
    for label in sides[is_lung[sides]]:  # only large air at the sides needs its density (a median per label is slow)
        is_lung[label] = float(np.median(coarse[labels == label])) >= ROOM_AIR_HU
    lung = is_lung[labels]
    between = np.zeros_like(lung)
    # axial slices: along the array axis that runs along the patient's height; each hull within its lungs' box
    lung_axial, between_axial = np.moveaxis(lung, height_axis, 0), np.moveaxis(between, height_axis, 0)
    for k in np.flatnonzero(lung_axial.any(axis=(1, 2))):
        (box,) = ndimage.find_objects(lung_axial[k].astype(np.uint8))
        between_axial[k][box] = convex_hull_image(lung_axial[k][box])
    between &= ~lung
    candidate = between & (coarse > soft_hu[0]) & (coarse < soft_hu[1])
    if not candidate.any():
        return None
    depth = distance_mm(candidate, cspacing)
    seed = np.zeros(coarse.shape, bool)
    seed[np.unravel_index(int(np.argmax(depth)), depth.shape)] = True
    return seed, between, lung
