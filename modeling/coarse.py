"""Coarse grids and boxes for fast work over a whole CT volume.

A full-size cardiac CT holds ~75 M voxels; finding the blood pool, the body
outline or the skin markers does not need that resolution.  Block statistics
over ``step`` voxels give a grid of ~1-2 mm on which those searches run, and the
answer is refined at full resolution only where it matters.  The segmentation
and the fiducial search both start from the volume's ~2 mm blocks: for a CT
that cannot change (a read-only array owning its voxels, as
:func:`imaging.load_study` returns) the last blocks are kept and given again.
"""

from __future__ import annotations

import weakref

import numpy as np

__all__ = [
    "coarse_step", "block_mean_max", "block_transform", "centroid", "fill_holes", "label_maximum",
    "largest_component", "mask_box", "sample_ct", "thin_metal", "without_thin_metal",
]


def sample_ct(hu, T_patient_from_voxel, points_mm) -> np.ndarray:
    """The CT at patient points, trilinear (nearest voxel beyond the volume's edge), float32.

    Reads only the box of voxels around the points, as stored: no float copy of
    the whole volume (a full-size CT as float32 is ~300 MB).

    Parameters
    ----------
    hu : (n_k, n_j, n_i) array
        The CT, indexed ``[k, j, i]``.
    T_patient_from_voxel : (4, 4) float64
    points_mm : (n, 3) float, patient frame
    """
    from scipy import ndimage

    T = np.asarray(T_patient_from_voxel, dtype=float)
    kji = np.linalg.solve(T[:3, :3], (np.asarray(points_mm, dtype=float) - T[:3, 3]).T)[::-1]  # (3, n)
    shape = np.array(np.shape(hu))
    lo = np.clip(np.floor(kji.min(axis=1)).astype(int) - 1, 0, shape - 1)
    hi = np.clip(np.ceil(kji.max(axis=1)).astype(int) + 2, 1, shape)
    box = np.asarray(hu[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]])
    return ndimage.map_coordinates(box, kji - lo[:, None], order=1, mode="nearest", output=np.float32)


def mask_box(mask, pad=0) -> tuple[slice, slice, slice] | None:
    """The smallest box (k, j, i slices) holding ``mask``'s voxels, grown by ``pad``.

    ``pad`` is voxels per axis (one number or three); the box is clipped to the
    volume.  None when the mask is empty.  Work on the box rather than the
    volume keeps what follows (meshing, distance transforms) to the heart.
    """
    pad = np.broadcast_to(np.asarray(pad, dtype=int), (3,))
    box = []
    for axis in range(3):
        nz = np.flatnonzero(mask.any(axis=tuple(a for a in range(3) if a != axis)))
        if nz.size == 0:
            return None
        grow = int(pad[axis])
        box.append(slice(max(int(nz[0]) - grow, 0), min(int(nz[-1]) + 1 + grow, mask.shape[axis])))
    return tuple(box)


def centroid(mask) -> np.ndarray:
    """Mean ``(k, j, i)`` index of a mask's voxels, as ``ndimage.center_of_mass``.

    From the mask's projections on its axes: ``center_of_mass`` multiplies the
    whole box by a float64 index grid per axis, tens of MB at full size.
    """
    mask = np.asarray(mask, dtype=bool)
    axes = range(mask.ndim)
    counts = [np.count_nonzero(mask, axis=tuple(b for b in axes if b != a)) for a in axes]
    total = counts[0].sum()
    return np.array([np.arange(len(c)) @ c / total for c in counts], dtype=float)


def label_maximum(values, labels, n: int) -> np.ndarray:
    """The largest of ``values`` in each label ``1..n`` (0 for an empty label).

    As ``scipy.ndimage.maximum(values, labels, np.arange(1, n + 1))``, in
    ``values``' dtype, without its sort of every labelled voxel (0.2 s on a
    heart region's branches).

    Examples
    --------
    >>> label_maximum(np.array([-5.0, -3.0, 2.0]), np.array([1, 1, 3]), 3).tolist()
    [-3.0, 0.0, 2.0]
    """
    values, labels = np.asarray(values), np.asarray(labels)
    inside = labels > 0
    top = np.full(n + 1, -np.inf, values.dtype if values.dtype.kind == "f" else np.float64)
    np.maximum.at(top, labels[inside], values[inside])
    top[np.isneginf(top)] = 0
    return top[1:]


def label_counts(mask, labels, n: int) -> np.ndarray:
    """How many voxels of ``mask`` lie in each label ``1..n``, float64.

    As ``scipy.ndimage.sum_labels(mask, labels, np.arange(1, n + 1))``, by one
    ``bincount``: scipy's path took 2 s of a whole-chest CT's segmentation
    (five calls over thousands of components).

    Examples
    --------
    >>> label_counts(np.array([True, True, False, True]), np.array([1, 1, 1, 3]), 3).tolist()
    [2.0, 0.0, 1.0]
    """
    labels = np.asarray(labels)
    return np.bincount(labels[np.asarray(mask, bool)], minlength=n + 1)[1:].astype(np.float64)


def block_transform(T_patient_from_voxel, step) -> np.ndarray:
    """(4, 4): the voxel -> patient transform of the blocks of ``step`` (k, j, i) voxels
    (:func:`block_mean_max`): a block's (i, j, k) index to the centre of its voxels (a full block's)."""
    T = np.asarray(T_patient_from_voxel, dtype=float)
    step_ijk = np.asarray(step, dtype=float)[::-1]
    out = T @ np.diag(np.r_[step_ijk, 1.0])
    out[:3, 3] = T[:3, :3] @ (0.5 * (step_ijk - 1.0)) + T[:3, 3]
    return out


def coarse_step(spacing_kji, target_mm: float) -> np.ndarray:
    """Integer block size per axis (k, j, i) giving voxels of about ``target_mm``."""
    return np.maximum(1, np.round(target_mm / np.asarray(spacing_kji, dtype=float))).astype(int)


#: Coarse planes (along k) reduced at a time: bounds the temporary arrays to a few MB.
_CHUNK_BLOCKS = 8


def _reduce_blocks(a, axis: int, step: int, ufunc, dtype=None):
    """``ufunc`` over consecutive runs of ``step`` along ``axis`` (the last run may be short)."""
    n = a.shape[axis]
    index = [slice(None)] * a.ndim
    index[axis] = slice(0, None, step)
    out = a[tuple(index)].astype(dtype or a.dtype, copy=True)
    for d in range(1, step):
        index[axis] = slice(d, None, step)
        part = a[tuple(index)]
        index[axis] = slice(0, -(-(n - d) // step))
        ufunc(out[tuple(index)], part, out=out[tuple(index)])
    return out


#: The last read-only volume's blocks: {"key": (id, step), "blocks": (mean, max)}, cleared with the volume.
_LAST: dict = {}


def _frozen(hu) -> bool:
    """Whether ``hu``'s voxels cannot change: read-only and owning them (not a view of a writeable array)."""
    return not hu.flags.writeable and hu.base is None


def block_mean_max(hu, step) -> tuple[np.ndarray, np.ndarray]:
    """Mean and maximum over blocks of ``step`` voxels (k, j, i); edge blocks are partial.

    Each axis is reduced in turn over a slab of a few coarse planes at a time,
    so the volume is read once and the temporaries stay small. Integer HU are
    summed exactly, others in float64.  For a read-only volume owning its voxels
    the result (read-only) is kept until the volume is freed: the segmentation
    and the fiducial search ask for the same blocks.

    Returns
    -------
    mean, maximum : (ceil(n_k/s_k), ceil(n_j/s_j), ceil(n_i/s_i)) float32
    """
    hu = np.asarray(hu)
    step = [int(s) for s in step]
    if not _frozen(hu):
        return _block_mean_max(hu, step)
    key = (id(hu), tuple(step))
    if _LAST.get("key") != key:
        _LAST.clear()
        blocks = _block_mean_max(hu, step)
        for b in blocks:
            b.flags.writeable = False
        _LAST.update(key=key, blocks=blocks)
        weakref.finalize(hu, _LAST.clear)  # a new array may get the same id
    return _LAST["blocks"]


def _block_mean_max(hu, step):
    shape = tuple(-(-n // s) for n, s in zip(hu.shape, step))
    if np.issubdtype(hu.dtype, np.integer):  # exact sums, as wide as the blocks need
        acc = np.int32 if hu.dtype.itemsize <= 2 and np.prod(step) < 2**15 else np.int64
    else:
        acc = np.float64
    mean = np.empty(shape, np.float32)
    peak = np.empty(shape, np.float32)
    count = np.ones(shape, np.float32)
    for axis, (n, s) in enumerate(zip(hu.shape, step)):
        per_block = np.minimum(s, n - s * np.arange(shape[axis])).astype(np.float32)
        count *= per_block.reshape([-1 if a == axis else 1 for a in range(3)])
    rows = _CHUNK_BLOCKS * step[0]
    for k0 in range(0, hu.shape[0], rows):
        part = hu[k0 : k0 + rows]
        out = slice(k0 // step[0], k0 // step[0] + -(-part.shape[0] // step[0]))
        total, top = part, part
        for axis in range(3):
            total = _reduce_blocks(total, axis, step[axis], np.add, acc)
            top = _reduce_blocks(top, axis, step[axis], np.maximum)
        mean[out] = total
        peak[out] = top
    mean /= count
    return mean, peak


def _label(mask):
    """Connected components with 16-bit labels when they fit (half the memory)."""
    from scipy import ndimage

    out = np.empty(mask.shape, np.uint16)
    try:
        n = ndimage.label(mask, output=out)
    except RuntimeError:  # more than 65535 components
        return ndimage.label(mask)
    return out, n


def fill_holes(mask, max_voxels: int | None = None) -> np.ndarray:
    """Fill enclosed cavities: background components not touching the border (of at most ``max_voxels``)."""
    labels, n = _label(~mask)
    if n == 0:
        return mask
    border = np.unique(np.concatenate([
        labels[[0, -1]].ravel(), labels[:, [0, -1]].ravel(), labels[:, :, [0, -1]].ravel()
    ]))
    inside = np.ones(n + 1, bool)
    inside[border] = False
    if max_voxels is not None:
        inside &= np.bincount(labels.ravel(), minlength=n + 1) <= max_voxels
    return mask | inside[labels]


def largest_component(mask) -> np.ndarray:
    """The largest connected component (face-connected) of a bool mask."""
    labels, n = _label(mask)
    if n <= 1:
        return mask
    # slice by slice: bincount casts its input to int64, four times the 16-bit labels of a full-size box
    sizes = np.zeros(n + 1, np.int64)
    for plane in labels:
        sizes += np.bincount(plane.ravel(), minlength=n + 1)
    sizes[0] = 0
    return labels == int(np.argmax(sizes))


def thin_metal(values, floor_hu: float, within=None) -> np.ndarray:
    """Voxels at or above ``floor_hu`` in structures less than three voxels thick: metal's bright streaks, a
    wire, a stent's struts (bone and dense contrast are thicker); only ``within`` a mask when given."""
    from scipy import ndimage

    bright = np.asarray(values) >= floor_hu
    thin = np.zeros_like(bright)
    if not (bright if within is None else bright & within).any():
        return thin
    box = mask_box(bright, pad=2)  # the bright voxels' box (a few staples, or the skeleton)
    # opened whole, not only within: a bone reaching into ``within`` is no thinner there
    thin[box] = bright[box] & ~ndimage.binary_opening(bright[box], structure=np.ones((3, 3, 3), bool))
    return thin if within is None else thin & within


def without_thin_metal(values, floor_hu: float) -> np.ndarray:
    """``values`` with :func:`thin_metal` replaced by their surroundings' level (a grey opening over 3 voxels).

    Lines of metal across the heart, above any tissue's HU, are neither tissue nor blood: one voxel thick in
    a few slices they parted the chambers, and no ball of the heart's size fitted between them (the real CT
    with three 3000 HU lines in each of five slices: 415 ml of 711, no warning; every 9 mm: 207 ml).
    """
    from scipy import ndimage

    thin = thin_metal(values, floor_hu)
    if not thin.any():
        return values
    box = mask_box(thin, pad=2)  # the opening reaches 2 voxels
    out = np.array(values, copy=True)
    out[box] = np.where(thin[box], ndimage.grey_opening(out[box], size=(3, 3, 3)), out[box])
    return out
