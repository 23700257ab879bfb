"""Fat planes that partial volume lifts above the tissue threshold, found by their shape.

Thin fat planes part the heart from what touches it: the left atrium from the
oesophagus and the descending aorta behind it, the pulmonary trunk from the
aortic root and the atrial appendage.  On a CT whose voxels are not much finer
than the plane, or resampled (a linear interpolation averages each plane into
its neighbours), a plane of fat (-100 HU) between muscle (100 HU) no longer
reaches below ``hu_low`` (0 HU): the threshold sees one tissue, and the heart's
region runs on into its neighbours (``shared/realct`` resampled to 2 mm or
1 mm: 60-70 ml of the posterior mediastinum, or the pulmonary trunk, joined
the heart).

What is left of such a plane is a *valley* of the HU: a thin sheet dimmer than
the tissue on both of its sides.  In the Hessian of the CT smoothed over
:data:`SIGMA_MM`, a voxel at a sheet's centre has one large positive curvature
(across the sheet, at least :data:`MIN_CURVATURE_HU_MM2`), two small ones
(along it, below :data:`SHEET_RATIO` of the first) and no slope across it (the
gradient along that axis below :data:`CENTRE_SLOPE` of the curvature times
sigma: the valley's floor, not its flank, so the edge of a structure lying
against fat is not taken).  Only tissue dimmer than :data:`PLANE_HU` (muscle
is 80-150 HU) is a candidate, and only sheets of at least
:data:`MIN_AREA_MM2` part anything: a plane is an extended surface, while
noise leaves single dim voxels inside muscle whose curvature may be sheet-like
by chance (the opening that follows takes a dent around every such hole).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

__all__ = ["fat_planes"]

#: Tissue dimmer than this (HU) may be a fat plane blurred by partial volume (myocardium 80-150 HU).
PLANE_HU = 60.0
#: Scale (mm, the Gaussian's sigma) of the Hessian: planes 1-3 mm thick.
SIGMA_MM = 1.5
#: Least curvature across a plane (HU/mm^2): a dip of ~10 HU or more at that scale.
MIN_CURVATURE_HU_MM2 = 5.0
#: The curvatures along a plane are below this fraction of the one across it.
SHEET_RATIO = 0.5
#: The slope across the plane is below this fraction of curvature x sigma: its floor.
CENTRE_SLOPE = 0.5
#: Least area (mm^2) of a connected sheet that parts tissue.
MIN_AREA_MM2 = 30.0


def _gaussian_derivatives_at(ct, sigma, at) -> dict:
    """The image's Gaussian derivatives of orders 1 and 2 at the voxels ``at``, by each axis's order
    (``(1, 0, 1)``: along k and i).

    Each is ``scipy.ndimage.gaussian_filter(ct, sigma, order=...)[at]`` to the bit (the same 1-D passes, axis by
    axis, in ``ct``'s dtype), the passes along the first axes shared between the nine: 18 passes instead of 27,
    one filtered volume per axis alive at a time.
    """
    def along(image, axis, order):
        return ndimage.gaussian_filter1d(image, sigma[axis], axis=axis, order=order, mode="reflect", truncate=4.0)

    out = {}
    for o0 in range(3):
        first = along(ct, 0, o0)
        for o1 in range(3 - o0):
            second = along(first, 1, o1)
            for o2 in range(3 - o0 - o1):
                if o0 + o1 + o2:
                    out[(o0, o1, o2)] = along(second, 2, o2)[at]
            del second
        del first
    return out


def fat_planes(coarse, spacing_kji, *, hu_low: float, box=None) -> np.ndarray:
    """Voxels of ``coarse`` at the floor of thin dim sheets (fat planes blurred above ``hu_low``).

    Parameters
    ----------
    coarse : (k, j, i) float array
        The CT on the segmentation's coarse grid, HU.
    spacing_kji : (3,) float
        Its voxel size, mm.
    hu_low : float
        The tissue threshold: dimmer voxels are parted already.
    box : tuple of slice, optional
        Where to look (the rest is returned False).

    Returns
    -------
    (k, j, i) bool
    """
    spacing = np.asarray(spacing_kji, dtype=float)
    out = np.zeros(coarse.shape, bool)
    box = tuple(slice(0, n) for n in coarse.shape) if box is None else box
    ct = np.asarray(coarse[box], dtype=np.float32)
    candidate = (ct > hu_low) & (ct < PLANE_HU)
    at = np.nonzero(candidate)
    if at[0].size == 0:
        return out
    sigma = SIGMA_MM / spacing
    derivative = _gaussian_derivatives_at(ct, sigma, at)
    hessian = np.empty((at[0].size, 3, 3))
    slope = np.empty((at[0].size, 3))
    for a in range(3):
        order = [0, 0, 0]
        order[a] = 1
        slope[:, a] = derivative[tuple(order)] / spacing[a]
        for b in range(a, 3):
            order = [0, 0, 0]
            order[a] += 1
            order[b] += 1
            hessian[:, a, b] = hessian[:, b, a] = derivative[tuple(order)] / (spacing[a] * spacing[b])
    # a sheet's Hessian has a norm above MIN_CURVATURE and (SHEET_RATIO <= 0.5) a positive trace: only those
    # voxels need its eigen-decomposition
    maybe = np.trace(hessian, axis1=1, axis2=2) > 0
    maybe[maybe] = np.linalg.norm(hessian[maybe], axis=(1, 2)) > MIN_CURVATURE_HU_MM2
    at, hessian, slope = tuple(i[maybe] for i in at), hessian[maybe], slope[maybe]
    curvature, axes = np.linalg.eigh(hessian)  # ascending: the last is across a valley
    across = curvature[:, 2]
    along = np.abs(curvature[:, :2]).max(axis=1)
    floor = np.abs(np.einsum("ni,ni->n", slope, axes[:, :, 2])) < CENTRE_SLOPE * across * SIGMA_MM
    sheet = np.zeros(ct.shape, bool)
    sheet[tuple(i[(across > MIN_CURVATURE_HU_MM2) & (along < SHEET_RATIO * across) & floor] for i in at)] = True
    labels, n = ndimage.label(sheet, structure=np.ones((3, 3, 3)))
    if n:
        area_mm2 = np.bincount(labels.ravel())[1:] * float(np.prod(spacing)) ** (2.0 / 3.0)
        out[box] = np.isin(labels, np.flatnonzero(area_mm2 >= MIN_AREA_MM2) + 1)
    return out
