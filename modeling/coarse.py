"""Coarse grids for fast searches over a whole CT volume.

A full-size cardiac CT holds ~75 M voxels; finding the blood pool, the body
outline or the skin markers does not need that resolution.  Block statistics
over ``step`` voxels give a grid of ~1-2 mm on which those searches run, and the
answer is refined at full resolution only where it matters.
"""

from __future__ import annotations

import numpy as np

__all__ = ["coarse_step", "block_mean_max"]


def coarse_step(spacing_kji, target_mm: float) -> np.ndarray:
    """Integer block size per axis (k, j, i) giving voxels of about ``target_mm``."""
    return np.maximum(1, np.round(target_mm / np.asarray(spacing_kji, dtype=float))).astype(int)


def block_mean_max(hu, step) -> tuple[np.ndarray, np.ndarray]:
    """Mean and maximum over blocks of ``step`` voxels (k, j, i); edge blocks are partial.

    Returns
    -------
    mean, maximum : (ceil(n_k/s_k), ceil(n_j/s_j), ceil(n_i/s_i)) float32
    """
    hu = np.asarray(hu)
    step = np.asarray(step, dtype=int)
    shape = tuple(int(n) for n in -(-np.array(hu.shape) // step))
    total = np.zeros(shape, np.float32)
    peak = np.full(shape, -np.inf, np.float32)
    count = np.zeros(shape, np.float32)
    for dk in range(step[0]):
        for dj in range(step[1]):
            for di in range(step[2]):
                part = hu[dk :: step[0], dj :: step[1], di :: step[2]]
                view = (slice(0, part.shape[0]), slice(0, part.shape[1]), slice(0, part.shape[2]))
                total[view] += part
                np.maximum(peak[view], part, out=peak[view])
                count[view] += 1
    return total / count, peak
