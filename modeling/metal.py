"""Metal in or beside the heart: a pacing or defibrillator lead, said with the model.

A lead runs through the superior vena cava and the right atrium into the right
ventricle.  Its wire is thin metal, which the segmentation reads through
(:func:`modeling.coarse.without_thin_metal`), but a scanner reconstructs it with
streaks, bright and dark bands across the chambers that no image-domain
correction removes well (the projections they come from are not in the
DICOM).  The real CT of ``shared/realct`` with a 2 mm lead put into its right
heart and scanned again in simulation (``bench/realct_robustness.py``, the
"scanner simulated" rows) keeps its model (Dice 0.899 against 0.906); with
more beam hardening and fewer photons it loses 140 ml of its right heart
without a word, or finds no blood pool at all.  So metal beside the heart
is said with the model, and the user looks at it over the CT.

Metal here is a voxel at or above :data:`METAL_HU`: above undiluted contrast
and bone (the real CT's densest contrast, in the superior vena cava, and its
sternal wires and stent graft lie farther than :data:`METAL_REACH_MM` from the
heart: none within it).
"""

from __future__ import annotations

import numpy as np

from modeling.coarse import mask_box
from modeling.distance import distance_mm

__all__ = ["METAL_HU", "METAL_REACH_MM", "METAL_MIN_MM3", "LEAD_MIN_MM", "PARTED_POOL", "metal_in_chest",
           "metal_near_heart"]

#: HU at and above which a voxel is metal (a 12-bit reconstruction saturates at 3071).
METAL_HU = 3000.0
#: Metal within this distance (mm) of the heart's mask is beside the heart; a lead whose chamber the
#: streaks took out of the mask lies just outside it (the simulated harsh lead: 51 voxels inside, 223 within 5 mm).
METAL_REACH_MM = 5.0
#: Less metal than this (mm^3) is not a lead: a 2 mm wire over 5 mm holds about 15.
METAL_MIN_MM3 = 15.0
#: A piece of metal at least this long (mm) is a lead's wire: the simulated lead's spans 129 mm, the real CT's
#: pieces (stent struts, sternal wires, its densest contrast) 20 mm at most.
LEAD_MIN_MM = 40.0


def metal_near_heart(hu, mask, T_patient_from_voxel) -> str:
    """What to say of metal in or beside the heart's mask, '' when there is none.

    Parameters
    ----------
    hu : (n_k, n_j, n_i) array
        The CT.
    mask : (n_k, n_j, n_i) bool
        The heart, on the CT's grid.
    T_patient_from_voxel : (4, 4) float

    Returns
    -------
    str
        A warning's text naming the metal's volume, or ''.

    Examples
    --------
    >>> import numpy as np
    >>> hu = np.zeros((20, 20, 20), np.int16)
    >>> heart = np.zeros(hu.shape, bool)
    >>> heart[5:15, 5:15, 5:15] = True
    >>> metal_near_heart(hu, heart, np.diag([1.0, 1.0, 1.0, 1.0]))
    ''
    >>> hu[2:18, 10, 10] = 3071  # a wire through it
    >>> metal_near_heart(hu, heart, np.diag([1.0, 1.0, 1.0, 1.0]))[:32]
    'metal in or beside the heart (16'
    """
    spacing = np.linalg.norm(np.asarray(T_patient_from_voxel, dtype=float)[:3, :3], axis=0)[::-1]  # k, j, i
    box = mask_box(mask, pad=np.ceil(METAL_REACH_MM / spacing).astype(int))
    if box is None:
        return ""
    metal = np.asarray(hu[box]) >= METAL_HU
    if np.count_nonzero(metal) * float(np.prod(spacing)) < METAL_MIN_MM3:  # most CTs: no distance map needed
        return ""
    near = metal & (distance_mm(~mask[box], spacing) <= METAL_REACH_MM)
    mm3 = float(np.count_nonzero(near) * np.prod(spacing))
    if mm3 < METAL_MIN_MM3:
        return ""
    return (f"metal in or beside the heart ({mm3:.0f} mm^3 above {METAL_HU:.0f} HU within {METAL_REACH_MM:g} mm of "
            "it: a pacing or defibrillator lead?): its streaks can part or shrink the chambers; check the model "
            "over the CT (model_ct.png)")


#: Refusals of the segmentation that a lead's streaks can cause (the blood pool parted).
PARTED_POOL = ("no heart-sized region", "no contrast blood pool", "smaller than a heart")


def metal_in_chest(hu, T_patient_from_voxel, refusal: str | None = None) -> str:
    """What a refusal adds when the CT holds a lead-like piece of metal ('' when none): "; ..." naming its length.

    ``refusal``, the segmentation's message: only one of :data:`PARTED_POOL` is given the addition (a seed
    outside the volume has nothing to do with metal).

    A segmentation that finds no blood pool blames weak contrast; a lead's streaks part the pool as well (the
    real CT with a simulated defibrillator lead: "no heart-sized region").  A piece of metal
    (:data:`METAL_HU`, 26-connected) whose box's diagonal spans :data:`LEAD_MIN_MM` or more is said.  The
    pieces are found among the metal voxels alone (a few thousand): electrodes or staples spread over the
    chest would make a labelled box of the whole CT.

    Examples
    --------
    >>> import numpy as np
    >>> hu = np.zeros((60, 20, 20), np.int16)
    >>> metal_in_chest(hu, np.eye(4))
    ''
    >>> hu[5:55, 10, 10] = 3071
    >>> metal_in_chest(hu, np.eye(4))[:40]
    '; the CT holds metal (a piece 49 mm long'
    """
    if refusal is not None and not any(words in refusal for words in PARTED_POOL):
        return ""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    kji = np.argwhere(np.asarray(hu) >= METAL_HU)
    if len(kji) < 2:
        return ""
    pairs = cKDTree(kji).query_pairs(np.sqrt(3.0) + 1e-6, output_type="ndarray")  # 26-neighbours
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(kji), len(kji)))
    _, piece = connected_components(graph, directed=False)
    spacing = np.linalg.norm(np.asarray(T_patient_from_voxel, dtype=float)[:3, :3], axis=0)[::-1]  # k, j, i
    order = np.argsort(piece, kind="stable")
    starts = np.flatnonzero(np.r_[True, np.diff(piece[order]) > 0])
    lo = np.minimum.reduceat(kji[order], starts, axis=0)
    hi = np.maximum.reduceat(kji[order], starts, axis=0)
    longest = float(np.linalg.norm((hi - lo) * spacing, axis=1).max())
    if longest < LEAD_MIN_MM:
        return ""
    return (f"; the CT holds metal (a piece {longest:.0f} mm long above {METAL_HU:.0f} HU: a pacing or "
            "defibrillator lead?), whose streaks can part the blood pool as well")
