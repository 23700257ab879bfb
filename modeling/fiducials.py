"""Chest fiducials: metal skin staples found in the CT (paper section 2.2.1).

Staples (about 6.5 x 4.7 mm) show as small blobs far above bone HU.  Each blob
is a connected component of voxels above ``threshold_hu``; its centre is the
HU-weighted centroid over the blob grown by one voxel (so partial-volume voxels
count), mapped through ``T_patient_from_voxel``.  Blobs much larger or smaller
than a staple (wires, dental work, noise) are discarded with a note.

Order (docs/CONTRACTS.md): a grid of ``n_rows`` rows, superior to inferior;
within a row patient right to left (increasing LPS x).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

__all__ = ["FiducialError", "Fiducials", "find_fiducials", "order_fiducials"]

#: HU above which a voxel on the skin is taken for metal.  Partial volume dims a
#: 1.6 mm thick staple to about 1000 HU at 2 mm voxels; bone is told apart by
#: where it is (inside the body wall), not by HU alone.
METAL_HU = 800.0
#: A staple lies on the skin: its blob must come this close to the air outside.
SKIN_REACH_MM = 3.0


class FiducialError(ValueError):
    """The fiducials found do not match what was expected."""


@dataclass(frozen=True)
class Fiducials:
    """Fiducial centres in the patient frame.

    Attributes
    ----------
    centres_patient_mm : (n, 3) float64
        In the documented order.
    volumes_mm3 : (n,) float64
        Volume of each blob above the threshold.
    notes : tuple of str
        Blobs discarded and why.
    """

    centres_patient_mm: np.ndarray
    volumes_mm3: np.ndarray
    notes: tuple[str, ...] = ()


def order_fiducials(centres_mm, *, n_rows: int = 3) -> np.ndarray:
    """Indices that put fiducial centres in row-major order.

    Rows are ``n_rows`` groups by height (LPS z, superior first); within a row
    the staples go from patient right to left (increasing x).

    Parameters
    ----------
    centres_mm : (n, 3) float
        Centres in the patient frame; n must be a multiple of ``n_rows``.

    Returns
    -------
    (n,) int
    """
    centres = np.asarray(centres_mm, dtype=float)
    if centres.ndim != 2 or centres.shape[1] != 3:
        raise ValueError(f"centres_mm must have shape (n, 3), got {centres.shape}")
    n = len(centres)
    if n_rows < 1 or n % n_rows:
        raise FiducialError(f"{n} fiducials cannot form {n_rows} equal rows")
    per_row = n // n_rows
    by_height = np.argsort(-centres[:, 2], kind="stable")
    order = []
    for r in range(n_rows):
        row = by_height[r * per_row : (r + 1) * per_row]
        order.extend(row[np.argsort(centres[row, 0], kind="stable")])
    return np.asarray(order, dtype=int)


def find_fiducials(
    hu,
    T_patient_from_voxel,
    *,
    expected: int | None = 9,
    n_rows: int = 3,
    threshold_hu: float = METAL_HU,
    min_volume_mm3: float = 4.0,
    max_volume_mm3: float = 400.0,
) -> Fiducials:
    """Find metal fiducials in a CT volume.

    Parameters
    ----------
    hu : (n_slices, n_rows, n_cols) array
        HU volume indexed ``[k, j, i]``.
    T_patient_from_voxel : (4, 4) float64
        Maps ``(i, j, k, 1)`` to patient LPS mm.
    expected : int or None
        Number of fiducials expected; a different count is an error naming both.
        ``None`` accepts any count (then ordered by height, then x).
    n_rows : int
        Rows of the grid, for the ordering.
    threshold_hu : float
        Voxels above it are metal.
    min_volume_mm3, max_volume_mm3 : float
        Blob volumes accepted as staples.

    Raises
    ------
    FiducialError
        If the count differs from ``expected``.
    """
    hu = np.asarray(hu)
    if hu.ndim != 3:
        raise ValueError(f"hu must be a 3-D volume (k, j, i), got shape {hu.shape}")
    T = np.asarray(T_patient_from_voxel, dtype=float)
    if T.shape != (4, 4):
        raise ValueError(f"T_patient_from_voxel must have shape (4, 4), got {T.shape}")
    voxel_mm3 = abs(np.linalg.det(T[:3, :3]))

    metal = hu > threshold_hu
    labels, n = ndimage.label(metal, structure=np.ones((3, 3, 3), bool))
    # the air outside the body: low-HU components that reach the in-plane border
    # (not the end slices, where trachea and lungs leave the volume)
    air_labels, _ = ndimage.label(hu < -500)
    border = np.unique(np.concatenate([air_labels[:, [0, -1]].ravel(), air_labels[:, :, [0, -1]].ravel()]))
    outside = np.isin(air_labels, border[border > 0])
    del air_labels
    spacing_kji = np.linalg.norm(T[:3, :3], axis=0)[::-1]
    to_air_mm = ndimage.distance_transform_edt(~outside, sampling=spacing_kji) if outside.any() else None
    notes = []
    centres, volumes = [], []
    slices = ndimage.find_objects(labels)
    for label, box in enumerate(slices, start=1):
        volume = float(np.count_nonzero(labels[box] == label)) * voxel_mm3
        if to_air_mm is not None and to_air_mm[box][labels[box] == label].min() > SKIN_REACH_MM:
            notes.append(f"dense blob of {volume:.1f} mm3 inside the body ignored (not on the skin)")
            continue
        if not (min_volume_mm3 <= volume <= max_volume_mm3):
            notes.append(f"metal blob of {volume:.1f} mm3 ignored (staple size {min_volume_mm3}-{max_volume_mm3} mm3)")
            continue
        # grow the box by 2 voxels and weight every voxel of the dilated blob by
        # its HU above soft tissue, so partial-volume voxels pull the centre.
        grown = tuple(slice(max(s.start - 2, 0), s.stop + 2) for s in box)
        blob = ndimage.binary_dilation(labels[grown] == label, iterations=1)
        weight = np.clip(hu[grown].astype(float) - 100.0, 0.0, None) * blob
        kji = np.argwhere(weight > 0)
        w = weight[weight > 0]
        offset = np.array([s.start for s in grown])
        k, j, i = ((kji + offset) * w[:, None]).sum(axis=0) / w.sum()
        centres.append(T[:3, :3] @ np.array([i, j, k]) + T[:3, 3])
        volumes.append(volume)

    centres = np.asarray(centres, dtype=float).reshape(-1, 3)
    volumes = np.asarray(volumes, dtype=float)
    if expected is not None and len(centres) != expected:
        raise FiducialError(
            f"found {len(centres)} fiducial(s) of staple size above {threshold_hu:.0f} HU, "
            f"expected {expected}; check the scan covers all skin markers, or set the "
            "expected count (--fiducials N) / threshold (--fiducial-hu)"
        )
    if len(centres) == 0:
        return Fiducials(centres, volumes, tuple(notes))
    rows = n_rows if len(centres) % n_rows == 0 else 1
    order = order_fiducials(centres, n_rows=rows)
    return Fiducials(centres[order], volumes[order], tuple(notes))
