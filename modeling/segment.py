"""Automatic whole-heart (epicardial) segmentation of a chest CT, with contrast or without.

Classical tools only (scipy.ndimage, scikit-image), in six steps:

1. *tissue*: the HU volume, lightly smoothed against noise, between ``hu_low``
   (midway between fat and myocardium, so the mask's edge is the epicardium) and
   ``hu_high`` (below metal);
2. *seed*: the contrast blood pool, the largest connected component of
   ``blood_hu`` voxels — vertebrae are cut apart by their discs, the liver and
   muscle stay below it; in a venous phase, whose blood is dimmer, the lower
   bound steps down to ``blood_floor_hu`` until a chamber is found — or the
   component at a seed point the user gives in patient mm.  Without contrast (that component holds no ball of
   ``min_pool_radius_mm``: it is then the skeleton) the seed is the thickest
   soft tissue inside the convex hull of the lungs, slice by slice (or the
   point given), and the tissue is limited to that hull and to ``soft_hu``
   (bone is not heart);
3. *heart region*: the tissue component touching the seed; with contrast,
   parted also at thin fat planes that partial volume lifts above ``hu_low``
   (:mod:`modeling.planes`), and less the solid organs it touches (tissue too
   thick and too far from blood to be a heart wall: the liver through a thick
   slice's blurred diaphragm), parted at the dimmest layer between them by a
   watershed;
4. *cut the bridges*: a morphological opening with a ball of radius
   ``vessel_radius_mm`` (computed with distance transforms on a ~2 mm grid)
   removes thin bridges to the liver or chest wall and thin vessels;
5. *cut the great vessels at their root*, whatever their calibre: a second
   opening by ``heart_radius_mm`` (larger than any vessel's radius, smaller than
   the heart's) gives the heart body.  Without contrast, the soft tissue below
   the body and far from it (the liver under the diaphragm) is parted first
   at its dimmest layer (:func:`modeling.seed.part_abdomen`).  Of what the
   body leaves out, each branch is followed out while thicker than
   ``chamber_radius_mm`` (an atrium, the outflow tract); what reaches on
   beyond for more than ``vessel_length_mm`` is a tube leaving the heart
   (ascending aorta, pulmonary trunk, venae cavae; without contrast the atria
   and the vessels are one soft tissue), cut there, at least
   ``vessel_root_mm`` from the body; branches that end sooner (apex,
   auricles, an atrium's rounded wall) are kept.
   The full-resolution tissue mask within ``margin_mm`` of the result is the
   heart, holes filled;
6. *remove the great vessels' lumen down to their valves* (contrast CT only):
   the blood pool's lobes traced from where they leave
   (:mod:`modeling.greatvessels`), with their walls outside the heart's body,
   are taken out (the aortic root the opening keeps, the vessels' mouths; not
   the outflow tract in muscle below the pulmonary valve); the lumen cut at
   its valve inside the body (the aortic root's well) goes on to the mesh
   steps (:attr:`HeartSegmentation.vessel_lumen`); an outflow tract thinner
   than the opening's ball, in a sleeve of muscle up to its valve, is given
   back (:mod:`modeling.outflow`).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from hrcore.errors import HeartregError
from hrcore.geometry import apply_to_points, check_transform
from modeling.coarse import (block_mean_max, block_transform, coarse_step, fill_holes, label_counts, label_maximum,
                             largest_component, mask_box, thin_metal, without_thin_metal)
from modeling.distance import distance_mm, opening_mm
from modeling.greatvessels import trace_great_vessels
from modeling.outflow import keep_outflow_tracts
from modeling.planes import fat_planes
from modeling.seed import (blood_ceiling_hu, mediastinal_seed, not_hounsfield, part_abdomen, pool_at_the_cts_noise,
                           split_solid_organs)

__all__ = ["SegmentationError", "HeartSegmentation", "segment_heart"]

#: Thickness (mm) of the distance shells in which a great-vessel branch's radius is followed out from the heart body.
ROOT_SHELL_MM = 5.0
#: Fat planes are looked for this far (mm) around the contrast blood pool.
PLANE_REACH_MM = 30.0


class SegmentationError(HeartregError, ValueError):
    """No heart-like region could be segmented."""


@dataclass(frozen=True)
class HeartSegmentation:
    """The heart mask and how it was found.

    Attributes
    ----------
    mask : (n_slices, n_rows, n_cols) bool
        Whole heart (epicardium inward), indexed ``[k, j, i]`` like the volume.
    seed_patient_mm : (3,) float64
        Centre of the blood-pool seed, patient frame.
    volume_ml : float
        Volume of the mask.
    parameters : dict
        The parameters used.
    notes : tuple of str
    vessel_lumen : bool array, optional
        The great vessels' lumen traced to their valves and taken out of the
        mask (:func:`modeling.greatvessels.trace_great_vessels`) inside the
        heart's body (the aortic root's well, down to its valve; a lumen cut
        where it leaves the body is not here), on the segmentation's coarse
        grid; None when there is none.
    T_patient_from_lumen : (4, 4) float64, optional
        The coarse grid's voxel -> patient transform.
    """

    mask: np.ndarray
    seed_patient_mm: np.ndarray
    volume_ml: float
    parameters: dict
    notes: tuple[str, ...] = ()
    vessel_lumen: np.ndarray | None = None
    T_patient_from_lumen: np.ndarray | None = None


def _seeded_part(mask, seed):
    """The connected part of ``mask`` holding most of ``seed`` (the largest where none does); None if empty."""
    labels, n = ndimage.label(mask)
    if n == 0:
        return None
    counts = label_counts(seed, labels, n)
    sizes = np.bincount(labels.ravel(), minlength=n + 1)[1:]
    return labels == int(np.argmax(counts if counts.max() > 0 else sizes)) + 1


def _heart_body(body, seed, spacing_kji, heart_radius_mm):
    """The heart body: the part of ``body`` a ball of ``heart_radius_mm`` fits in, around the seed (None if none)."""
    return _seeded_part(opening_mm(body, spacing_kji, heart_radius_mm), seed)


def _thick_stretch(thick, start_mm) -> int:
    """Shells (from the heart body out) of a branch's thick stretch: the first run of thick shells.

    The run must start within ``start_mm`` of the body (an atrium is deepest
    about its radius past where it meets the ventricles, and narrower there)
    and may hold single thin shells (a 5 mm dip of the inscribed radius); it
    ends at two thin shells in a row.  0 when no thick shell starts near the
    body: a thick lobe beyond a longer thin neck is no atrium.
    """
    first = np.flatnonzero(thick)
    if first.size == 0 or first[0] * ROOT_SHELL_MM > start_mm:
        return 0
    end = int(first[0])
    while end + 1 < thick.size and (thick[end + 1] or (end + 2 < thick.size and thick[end + 2])):
        end += 1 if thick[end + 1] else 2
    return end + 1


def _cut_great_vessels(body, heart, spacing_kji, *, heart_radius_mm, vessel_length_mm, root_mm, chamber_radius_mm):
    """Cut the tubes leaving the heart body at their root, whatever their calibre.

    ``heart`` is the heart body (:func:`_heart_body`: thicker than any great
    vessel); the rest of ``body`` are its branches and corners.  Walking out
    from the body in shells :data:`ROOT_SHELL_MM` thick, a branch is heart (an
    atrium, the outflow tract: thicker than a vessel) as far as some voxel of
    a shell lies deeper than ``chamber_radius_mm`` inside ``body``
    (:func:`_thick_stretch`: a stretch starting within ``heart_radius_mm`` of
    the body, single thin shells bridged).  Then:

    - what lies beyond that thick stretch is a vessel when it reaches on for
      more than ``vessel_length_mm``: cut where the stretch ends, never nearer
      the body than ``root_mm``;
    - a branch that ends sooner is kept whole: the apex, the auricles, the
      corners of the ventricles, and an atrium whose far wall rounds off
      (without contrast the right atrium is a branch of the soft tissue
      35-45 mm long, 15-20 mm in inscribed radius, narrowed where it meets
      the ventricles; cut at its first thin shell, it was lost);
    - a branch thick for longer than ``2 * heart_radius_mm`` (an atrium
      reaches about one body-ball diameter past the ventricles) is another
      organ pressed to the heart (the liver, the descending aorta joined to
      the left atrium on a 3 mm CT): cut at its first thin shell, its neck,
      or ``2 * heart_radius_mm`` out where it has none (a liver pressed
      broadly against the heart).

    Without contrast the atria and the great vessels may form one branch of
    soft tissue; with a fixed cut the atria went with the vessels.

    Returns
    -------
    mask : bool array like ``body``
    note : str
        What was cut, or why nothing could be (the body is returned unchanged).
    """
    if heart is None:
        return body, (
            f"vessel cut skipped: no part of the heart region is thicker than {2 * heart_radius_mm:.0f} mm; "
            "great vessels may remain"
        )
    distance = distance_mm(~heart, spacing_kji)
    rest = body & ~heart
    labels, n = ndimage.label(rest)
    if n == 0:
        return body, "vessel cut: no branch leaves the heart body"
    reach = np.asarray(label_maximum(distance, labels, n))
    depth = distance_mm(body, spacing_kji)
    shell = (distance // ROOT_SHELL_MM).astype(np.int64)
    cut = np.zeros_like(body)
    cuts = []  # (reach, cut) of each vessel, in mm
    for label in np.argsort(-reach) + 1:
        if reach[label - 1] <= vessel_length_mm:
            break
        branch = labels == label
        thickest = np.zeros(int(shell[branch].max()) + 2)  # the last shell is empty: thin
        np.maximum.at(thickest, shell[branch], depth[branch])
        thick_mm = _thick_stretch(thickest > chamber_radius_mm, heart_radius_mm) * ROOT_SHELL_MM
        if thick_mm > 2.0 * heart_radius_mm:  # thick for longer than an atrium: an organ pressed to the heart
            thick_mm = min(float(np.argmax(thickest <= chamber_radius_mm)) * ROOT_SHELL_MM, 2.0 * heart_radius_mm)
        elif reach[label - 1] - thick_mm <= vessel_length_mm:
            continue
        root = max(root_mm, thick_mm)
        cut |= branch & (distance > root)
        cuts.append((float(reach[label - 1]), root))
    if not cuts:
        return body, (f"vessel cut: no branch reaches farther than {vessel_length_mm:.0f} mm from the heart body "
                      f"beyond where it is thicker than {chamber_radius_mm:.0f} mm in radius")
    kept = largest_component(body & ~cut)
    removed_ml = float((body & ~kept).sum() * np.prod(spacing_kji) / 1000.0)
    return kept, (
        f"great vessels cut at their root: {len(cuts)} branch(es) reaching "
        f"{', '.join(f'{r:.0f}' for r, _ in cuts)} mm from the heart body, cut "
        f"{', '.join(f'{c:.0f}' for _, c in cuts)} mm from it where thinner than "
        f"{chamber_radius_mm:.0f} mm in radius ({removed_ml:.0f} ml removed)"
    )


def segment_heart(
    hu, T_patient_from_voxel, *, hu_low: float = 0.0, hu_high: float = 1500.0,
    blood_hu: tuple[float, float] = (200.0, 650.0), blood_floor_hu: float = 150.0, seed_patient_mm=None,
    vessel_radius_mm: float = 14.0, heart_radius_mm: float = 20.0, vessel_length_mm: float = 25.0,
    vessel_root_mm: float = 10.0, chamber_radius_mm: float = 17.0, margin_mm: float = 1.0, smooth_mm: float = 0.6,
    coarse_mm: float = 2.0, min_volume_ml: float = 50.0, min_pool_radius_mm: float = 13.0, lung_hu: float = -400.0,
    soft_hu: tuple[float, float] = (-50.0, 150.0), trace_vessels: bool = True,
) -> HeartSegmentation:
    """Segment the whole heart (epicardial surface inward) in a contrast CT.

    Parameters
    ----------
    hu : (n_slices, n_rows, n_cols) array
        HU volume indexed ``[k, j, i]``.
    T_patient_from_voxel : (4, 4) float64
        Maps ``(i, j, k, 1)`` to patient mm.
    hu_low, hu_high : float
        Tissue range; ``hu_low`` sits midway between pericardial fat (~-100 HU)
        and myocardium (~100 HU).
    blood_hu : (float, float)
        Range of contrast-enhanced blood, for the automatic seed; the upper
        bound rises with brighter blood (low kV, a low-keV image:
        :func:`modeling.seed.blood_ceiling_hu`).
    blood_floor_hu : float
        Lowest lower bound tried for the blood pool when no chamber reaches
        ``blood_hu[0]`` (a venous-phase CT: blood 150-250 HU).
    seed_patient_mm : (3,) float, optional
        A point inside the heart (patient mm) instead of the automatic seed.
    vessel_radius_mm : float
        Tubes thinner than this radius are cut off (great vessels, bridges).
    heart_radius_mm : float
        Radius of the ball that fits in the heart body but not in a great
        vessel (the ascending aorta's lumen is 11-15 mm in radius, the heart's
        tissue 40-50 mm): what it cannot reach is a branch of the body.
    vessel_length_mm : float
        A branch reaching farther than this from the heart body beyond its
        last part thicker than ``chamber_radius_mm`` is a vessel leaving the
        heart (corners such as the apex or an auricle, and an atrium's far
        wall, end sooner).
    vessel_root_mm : float
        Vessels are cut at least this far from the heart body (at their root);
        their contrast lumen is traced to the valves apart (``trace_vessels``),
        so this tissue-level cut keeps off the atrial roofs and the outflow tract.
    chamber_radius_mm : float
        A branch of the heart body is followed out while it is thicker than
        this (an atrium, 18-25 mm in inscribed radius; a great vessel with its
        wall, at most ~16 mm); a vessel beyond is cut where that thick stretch
        ends (see ``_cut_great_vessels``).
    margin_mm : float
        How far past the opened core the full-resolution boundary is kept.
    smooth_mm : float
        Gaussian sigma applied on the coarse grid before thresholding; more
        on a noisy CT (:data:`modeling.seed.NOISE_HU`).
    coarse_mm : float
        Grid spacing of the coarse grid (block means) on which the seed, the
        region and the opening are found; the boundary is then taken at full
        resolution within ``margin_mm`` of the opened core.
    min_volume_ml : float
        Smaller results are refused as not heart-like.
    min_pool_radius_mm : float
        The largest ``blood_hu`` component is a contrast blood pool only if it
        holds a ball of this radius (a cardiac chamber's lumen: 12-25 mm); in a
        CT without contrast that component is the skeleton, whose marrow and
        cortex are thinner (a thoracic vertebral body, 20-25 mm high between
        its discs, holds at most ~11 mm).  13 mm: in a pulmonary CTA only the
        right heart is bright, and the real CT's right atrium and ventricle
        hold 13 mm on the coarse grid (15 mm, before session 29, gave no
        model); at the weaker levels of a venous phase the pool must hold
        18 mm (:data:`modeling.seed.WEAK_POOL_RADIUS_MM`).
    lung_hu : float
        Air below this HU, enclosed by the body, is lung (for the seed without contrast).
    soft_hu : (float, float)
        Soft tissue of a non-contrast heart (blood and myocardium 30-60 HU);
        without contrast the seed is the thickest such tissue lying between the
        lungs, and tissue above ``soft_hu[1]`` (bone) is not heart.
    trace_vessels : bool
        Remove the great vessels' lumen (and their walls outside the heart's body)
        traced in the contrast blood pool down to their valves (:func:`modeling.greatvessels.trace_great_vessels`).

    Raises
    ------
    SegmentationError
        If no blood pool or no heart-sized region is found.

    Examples
    --------
    On the sample study (a few seconds, hence skipped here):

    >>> from imaging import load_study
    >>> from modeling import segment_heart
    >>> volume = load_study("sample_dicom/ct")
    >>> segmentation = segment_heart(volume.hu, volume.T_patient_from_voxel)  # doctest: +SKIP
    >>> segmentation.volume_ml > 50  # doctest: +SKIP
    True
    """
    hu = np.asarray(hu)
    if hu.ndim != 3:
        raise ValueError(f"hu must be a 3-D volume (k, j, i), got shape {hu.shape}")
    T = check_transform(T_patient_from_voxel, name="T_patient_from_voxel")
    if not hu_low < hu_high:
        raise ValueError(f"hu_low ({hu_low}) must be below hu_high ({hu_high})")
    spacing_kji = np.linalg.norm(T[:3, :3], axis=0)[::-1]  # voxel size along k, j, i, mm
    voxel_ml = abs(np.linalg.det(T[:3, :3])) / 1000.0
    notes: list[str] = []

    # ---- coarse grid (~coarse_mm): block means, which also average the noise
    step = coarse_step(spacing_kji, coarse_mm)
    raw, _ = block_mean_max(hu, step)
    raw = without_thin_metal(raw, hu_high)  # metal's streaks part nothing
    cspacing = spacing_kji * step
    coarse = ndimage.gaussian_filter(raw, sigma=smooth_mm / cspacing) if smooth_mm > 0 else raw
    if (problem := not_hounsfield(coarse, hu)) is not None:
        raise SegmentationError(problem)

    # ---- seed: the contrast blood pool, or the soft tissue between the lungs without contrast
    contrast = True
    height_axis = 2 - int(np.argmax(np.abs(T[2, :3]) / spacing_kji[::-1]))  # array axis along the patient's height
    seed_between = functools.cache(lambda: mediastinal_seed(coarse, cspacing, lung_hu=lung_hu, soft_hu=soft_hu,
                                                            height_axis=height_axis))

    def mediastinum():
        found = seed_between()
        return None if found is None else found[1]

    def soft_tissue_between_lungs(tissue):
        """Without contrast: tissue above soft_hu[1] is bone, and the heart lies between the lungs (where found)."""
        between = mediastinum()
        tissue &= coarse < soft_hu[1]
        if between is not None:
            tissue &= ndimage.binary_dilation(between, iterations=1)
        return tissue

    blood_hu = (blood_hu[0], blood_ceiling_hu(coarse, cspacing, blood_hu, hu_high, mediastinum))  # bright blood
    pool, pool_hu, coarse, noise_note = pool_at_the_cts_noise(
        raw, coarse, cspacing, smooth_mm, blood_hu, min_pool_radius_mm, blood_floor_hu, mediastinum)
    notes += [noise_note] if noise_note else []
    tissue = (coarse > hu_low) & (coarse < hu_high)
    if seed_patient_mm is None:
        if pool is not None:
            seed_mask = pool
            kji = (np.argwhere(seed_mask).mean(axis=0) + 0.5) * step - 0.5
            notes.append(f"seed: largest blood-pool component ({seed_mask.sum() * voxel_ml * step.prod():.0f} ml"
                         + (f", blood above {pool_hu:.0f} HU: weak contrast" if pool_hu < blood_hu[0] else "") + ")")
        else:
            found = seed_between()
            if found is None:
                raise SegmentationError(
                    "no contrast blood pool and no soft tissue between two lungs in the volume; "
                    "give a point inside the heart with --seed=X,Y,Z or a heart mask with --mask"
                )
            seed_mask = found[0]
            contrast = False
            tissue = soft_tissue_between_lungs(tissue)
            kji = (np.argwhere(seed_mask).mean(axis=0) + 0.5) * step - 0.5
            notes.append(
                f"no contrast blood pool (none holds a ball of {min_pool_radius_mm:.0f} mm radius at "
                f"{min(blood_floor_hu, blood_hu[0]):.0f}-{blood_hu[1]:.0f} HU): seeded in the thickest soft tissue between the lungs, "
                f"tissue up to {soft_hu[1]:.0f} HU"
            )
        seed_mm = apply_to_points(T, kji[::-1])
    else:
        seed_mm = np.asarray(seed_patient_mm, dtype=float).reshape(3)
        ijk = np.linalg.solve(T[:3, :3], seed_mm - T[:3, 3])
        kji = np.floor(ijk[::-1] / step + 0.5 / step).astype(int)
        if np.any(kji < 0) or np.any(kji >= np.array(coarse.shape)):
            raise SegmentationError(f"seed point {seed_mm.tolist()} mm (--seed) lies outside the volume; give one in the heart")
        if pool is None and blood_floor_hu < coarse[tuple(kji)] < blood_hu[1]:
            # the point lies in contrast blood where no pool holds a chamber's ball (artefacts parting the
            # chambers): the blood connected to it is the pool, not bone in a CT without contrast
            pool_hu = float(blood_hu[0] if coarse[tuple(kji)] > blood_hu[0] else blood_floor_hu)
            labels, _ = ndimage.label((coarse > pool_hu) & (coarse < blood_hu[1]))
            pool = labels == labels[tuple(kji)]
            notes.append(f"blood pool: the contrast blood around the given point (above {pool_hu:.0f} HU)")
        contrast = pool is not None
        if not contrast:  # as unseeded
            tissue = soft_tissue_between_lungs(tissue)
        if not tissue[tuple(kji)]:
            raise SegmentationError(
                f"seed point {seed_mm.tolist()} mm (--seed) is not in heart tissue ({coarse[tuple(kji)]:.0f} HU outside "
                f"{hu_low:.0f}..{hu_high if contrast else soft_hu[1]:.0f}); give one in the heart's blood or muscle"
            )
        seed_mask = np.zeros(coarse.shape, bool)
        seed_mask[tuple(kji)] = True
        notes.append("seed: given point" + ("" if contrast else " (no contrast blood pool in the CT)"))

    # ---- heart region: tissue connected to the seed (with contrast, parted also at fat planes blurred above hu_low)
    if contrast and pool is not None:
        planes = fat_planes(coarse, cspacing, hu_low=hu_low, box=mask_box(pool, np.ceil(PLANE_REACH_MM / cspacing)))
        tissue &= ~planes | seed_mask  # a point given on one stays
    labels, _ = ndimage.label(tissue)
    touched = np.setdiff1d(labels[seed_mask & tissue], [0])
    if touched.size == 0:
        raise SegmentationError("the blood-pool seed does not touch any tissue in range")
    region = np.isin(labels, touched)
    del labels
    if contrast and pool is not None:
        region, split_note = split_solid_organs(region, pool, coarse, cspacing, pool_hu, height_axis,
                                                seed_between()[1:] if seed_between() else None, T[2, 2::-1] * step)
        if split_note:
            notes.append(split_note)

    # ---- open (cut vessels and bridges) on the coarse grid, cropped to the region
    box = ndimage.find_objects(region.astype(np.uint8))[0]
    pad = [int(np.ceil((vessel_radius_mm + margin_mm) / s)) + 2 for s in cspacing]
    box = tuple(slice(max(b.start - p, 0), min(b.stop + p, n)) for b, p, n in zip(box, pad, coarse.shape))
    core = _seeded_part(opening_mm(region[box], cspacing, vessel_radius_mm), seed_mask[box])
    if core is None:
        start = "the blood pool" if contrast else (
            "the soft tissue between the lungs (no blood pool was found: with contrast too weak or chambers too "
            "small, the heart's blood counts as bone and the heart is hollow)")
        raise SegmentationError(
            f"no heart-sized region: nothing thicker than {2 * vessel_radius_mm:.0f} mm is connected to "
            f"{start}; give a point inside the heart with --seed=X,Y,Z or a heart mask with --mask"
        )
    heart_body = _heart_body(core, seed_mask[box], cspacing, heart_radius_mm)
    if not contrast and heart_body is not None:
        core, split_note = part_abdomen(core, heart_body, coarse[box], cspacing, T[2, 2::-1] * step)
        if split_note:
            notes.append(split_note)
    core, cut_note = _cut_great_vessels(
        core, heart_body, cspacing, heart_radius_mm=heart_radius_mm,
        vessel_length_mm=vessel_length_mm, root_mm=vessel_root_mm, chamber_radius_mm=chamber_radius_mm,
    )
    notes.append(cut_note)
    reach = margin_mm + 0.5 * float(np.max(cspacing))
    near = distance_mm(~core, cspacing) <= reach
    vessel_lumen = T_lumen = None
    if trace_vessels and contrast and pool is not None:
        body = np.pad(core if heart_body is None else heart_body,  # the heart body on the whole grid
                      [(b.start, n - b.stop) for b, n in zip(box, coarse.shape)])
        vessels = trace_great_vessels(pool, cspacing, heart=body, hu=coarse)
        near &= ~vessels.territory[box]
        notes.append(vessels.note)
        if (vessels.lumen & body).any():  # cut at its valve (the aortic root's well), not at the body's edge
            vessel_lumen = vessels.lumen & body
            T_lumen = block_transform(T, step)
    if contrast and pool is not None:  # an outflow tract thinner than the opening's ball (modeling.outflow)
        near, outflow_note = keep_outflow_tracts(near, core, region[box] & (coarse[box] > pool_hu), coarse[box], cspacing,
                                                 reach, not_heart=vessels.territory[box] if trace_vessels else None,
                                                 up_kji=T[2, 2::-1] * step)
        notes += [outflow_note] if outflow_note else []
    # ---- full resolution inside the near band's bounding box
    nbox = ndimage.find_objects(near.astype(np.uint8))[0]
    cbox = tuple(slice(b.start + o.start, b.stop + o.start) for b, o in zip(nbox, box))
    full_box = tuple(slice(c.start * st, min(c.stop * st, n)) for c, st, n in zip(cbox, step, hu.shape))
    idx = [
        np.minimum((np.arange(f.start, f.stop) // st) - c.start, c.stop - c.start - 1)
        for f, st, c in zip(full_box, step, cbox)
    ]
    near_full = near[nbox][np.ix_(*idx)]
    sub = hu[full_box]
    heart = near_full & (sub > hu_low) & (sub < (hu_high if contrast else soft_hu[1]))
    heart |= thin_metal(sub, hu_high, within=near_full)  # metal's streaks through the heart are no gap in it
    heart = largest_component(fill_holes(heart))

    mask = np.zeros(hu.shape, bool)
    mask[full_box] = heart
    volume_ml = float(heart.sum() * voxel_ml)
    if volume_ml < min_volume_ml:
        raise SegmentationError(
            f"segmented region is {volume_ml:.0f} ml, smaller than a heart ({min_volume_ml:.0f} ml); "
            "give a point inside the heart with --seed=X,Y,Z or a heart mask with --mask"
        )
    parameters = dict(
        hu_low=hu_low, hu_high=hu_high, blood_hu=list(blood_hu), blood_floor_hu=blood_floor_hu, pool_hu=pool_hu,
        vessel_radius_mm=vessel_radius_mm, heart_radius_mm=heart_radius_mm, vessel_length_mm=vessel_length_mm,
        vessel_root_mm=vessel_root_mm, chamber_radius_mm=chamber_radius_mm, margin_mm=margin_mm, smooth_mm=smooth_mm,
        coarse_mm=coarse_mm, min_volume_ml=min_volume_ml, min_pool_radius_mm=min_pool_radius_mm, lung_hu=lung_hu,
        soft_hu=list(soft_hu), contrast=contrast, trace_vessels=trace_vessels,
        seed_patient_mm=None if seed_patient_mm is None else seed_mm.tolist())
    return HeartSegmentation(mask, seed_mm, volume_ml, parameters, tuple(notes), vessel_lumen, T_lumen)

