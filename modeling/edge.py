"""Move a surface meshed from a mask onto the CT's own edge, at sub-voxel accuracy.

A mesh of a mask is only as fine as the mask's voxels: a threshold's boundary
steps by whole voxels, and smoothing leaves it up to about half a voxel off
the image's edge.  :func:`refine_to_edge` moves each vertex of the final mesh
along its normal to where the CT itself crosses the threshold (linear
interpolation), within a fraction of a voxel, the moves averaged over each
vertex's neighbours against noise; not on voxels coarser than 2.5 mm
(:func:`edge_refinable`).  Over a great vessel's lumen, taken out of the
heart on the segmentation's coarse grid, the edge is the blood's instead.
"""

from __future__ import annotations

import numpy as np

from hrcore.geometry import check_transform
from modeling.coarse import sample_ct
from modeling.mesh import Mesh, vertex_normals

__all__ = ["edge_refinable", "refine_to_edge"]

#: :func:`refine_to_edge`: the farthest a vertex moves, in voxels (largest spacing); the CT sampled every
#: this fraction of the smallest spacing along the normal; the moves averaged over neighbours this many times.
REFINE_REACH_VOX = 0.75
REFINE_STEP_VOX = 0.25
REFINE_SMOOTH = 3
#: ... only on a CT whose voxels are at most this large (mm, each way).  On coarser voxels the CT's blur mixes a
#: thin wall's contrast blood into its edge, and across thick slices the edge is a grey-level interpolation, which
#: the shape-based interpolation of :func:`modeling.surface.mask_to_mesh` does better.  Measured on
#: ``shared/realct`` (1.5 mm): averaged to 3 mm voxels the move took the surface 0.3 mm further out from the 1.5 mm
#: CT's (median distance 0.85 -> 0.94 mm; Dice against the reference 0.876 -> 0.866); to 3 and 6 mm slices, Dice
#: 0.886 -> 0.882 and 0.820 -> 0.806; at 1.5 mm it is neutral there (0.899 -> 0.898).  With the truth: the
#: anatomical phantom (full size) blurred by a scanner's PSF (FWHM 1-1.5 mm) and averaged to 1.5 mm voxels, mean /
#: p95 0.21 / 0.67 -> 0.17 / 0.38 mm with the move; averaged to 3 mm (FWHM 2.5 mm) it would gain too (0.48 / 1.11 ->
#: 0.40 / 0.73 mm), but the real CT, whose walls and fat are not the phantom's, decides.
REFINE_MAX_VOXEL_MM = 2.5


def edge_refinable(T_patient_from_voxel) -> bool:
    """Whether :func:`refine_to_edge` may move a surface of this CT: its voxels at most
    ``REFINE_MAX_VOXEL_MM`` each way."""
    spacing = np.linalg.norm(check_transform(T_patient_from_voxel, name="T_patient_from_voxel")[:3, :3], axis=0)
    return bool(spacing.max() <= REFINE_MAX_VOXEL_MM + 1e-6)


def _crossings(hu, T, v, normals, level: float, reach: float, step: float, *, brighter_outside=False):
    """Signed move (mm, along ``normals``) of each of ``v`` to the CT's ``level`` crossing nearest it within
    ``reach`` (above inside, below outside; the other way round with ``brighter_outside``), and whether one was
    found."""
    offsets = np.linspace(-reach, reach, 2 * int(np.ceil(reach / step)) + 1)
    points = v[:, None, :] + offsets[None, :, None] * normals[:, None, :]  # (n, m, 3)
    profile = sample_ct(hu, T, points.reshape(-1, 3)).reshape(len(v), len(offsets)) - np.float32(level)
    inside = (profile < 0) if brighter_outside else (profile > 0)
    crossing = inside[:, :-1] & ~inside[:, 1:]
    centre = (len(offsets) - 1) / 2.0
    rank = np.where(crossing, np.abs(np.arange(len(offsets) - 1) + 0.5 - centre), np.inf)
    j = rank.argmin(axis=1)
    rows = np.arange(len(v))
    found = np.isfinite(rank[rows, j])
    a, b = profile[rows, j], profile[rows, j + 1]
    move = np.where(found, offsets[j] + (offsets[1] - offsets[0]) * a / np.where(found, a - b, 1.0), 0.0)
    return move, found


def refine_to_edge(mesh: Mesh, hu, T_patient_from_voxel, level: float, *, over_blood=None,
                   blood_level: float | None = None, blood_reach_mm: float = 0.0, reach_vox: float = REFINE_REACH_VOX,
                   smooth: int = REFINE_SMOOTH) -> tuple[Mesh, float]:
    """Move each vertex along its normal to where the CT crosses ``level`` HU.

    Along each vertex's outward normal, within ``reach_vox`` times the largest
    voxel spacing either way, the CT is sampled every ``REFINE_STEP_VOX`` of the
    smallest spacing (trilinear); the crossing from above ``level`` (inside) to
    below it (outside) nearest the vertex gives its move.  Vertices without such
    a crossing (a lid across a vessel's lumen, the heart against the liver) have
    none.  A vertex ``over_blood`` (a great vessel's lumen taken out of the
    heart down to its valve lies beyond it, :func:`modeling.vessels.over_lumen`:
    the floor and the walls of the aortic root's well) looks for the opposite
    edge, from below ``blood_level`` inside (myocardium) to above it outside,
    as far as ``blood_reach_mm`` if that is farther (the lumen was taken out
    on a coarser grid than the CT's).  The moves are then averaged ``smooth`` times
    over each vertex and its neighbours (image noise moves single crossings),
    vertices without a crossing taking their neighbours' mean: a lid's rim
    follows the wall it closes.

    Parameters
    ----------
    mesh : Mesh
        Closed surface in the patient frame (mm), outward normals.
    hu : (n_k, n_j, n_i) array
        The CT, indexed ``[k, j, i]``.
    T_patient_from_voxel : (4, 4) float64
    level : float, HU
        The threshold the surface stands for (the segmentation's ``hu_low``:
        half-way between pericardial fat and myocardium).
    over_blood : (n_vertices,) bool, optional
        The vertices over a traced lumen.
    blood_level : float, HU, optional
        The threshold of the contrast blood pool the segmentation took the
        vessels' lumen from (its ``pool_hu``, the pool's lower bound: the edge
        found lies a little into the blood's partial volume, as the lumen's
        own outline does); needed with ``over_blood``.
    blood_reach_mm : float
        Reach of the search for the blood edge (the segmentation's coarse grid spacing).

    Returns
    -------
    mesh : Mesh
        Same faces, vertices moved.
    fraction : float
        Of vertices that found a crossing.
    """
    import scipy.sparse as sparse

    if over_blood is not None and blood_level is None:
        raise ValueError("over_blood needs blood_level: the HU of the blood's edge")
    T = check_transform(T_patient_from_voxel, name="T_patient_from_voxel")
    spacing = np.linalg.norm(T[:3, :3], axis=0)
    reach, step = reach_vox * float(spacing.max()), REFINE_STEP_VOX * float(spacing.min())
    v = np.asarray(mesh.vertices, dtype=float)
    faces = np.asarray(mesh.faces)
    normals = vertex_normals(v, faces)
    move, found = _crossings(hu, T, v, normals, level, reach, step)
    if over_blood is not None:  # over a lumen taken out at its valve: the myocardium -> blood edge
        over = np.asarray(over_blood, dtype=bool)
        if over.shape != (len(v),):
            raise ValueError(f"over_blood must hold one flag per vertex ({len(v)}), got shape {over.shape}")
        if over.any():
            move[over], found[over] = _crossings(hu, T, v[over], normals[over], blood_level,
                                                 max(reach, blood_reach_mm), step, brighter_outside=True)
    # average over each vertex and its neighbours, weighted by whether a crossing was found
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    ring = sparse.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(len(v), len(v))).tocsr()
    ring = ((ring + ring.T) > 0).astype(float) + sparse.identity(len(v), format="csr")
    weight = found.astype(float)
    for _ in range(int(smooth)):
        total = ring @ weight
        move = np.where(total > 0, (ring @ (move * weight)) / np.maximum(total, 1e-12), 0.0)
        weight = (total > 0).astype(float)
    # where two sheets of the surface lie within a voxel (a narrow groove), their moves can cross: such
    # vertices and their neighbours keep their place (on the anatomical phantom 18 of 16 636 faces crossed)
    for _ in range(3):
        crossed = _self_intersecting(v + move[:, None] * normals, faces) & (move != 0)
        if not crossed.any():
            break
        move[(ring @ crossed.astype(float)) > 0] = 0.0
    return Mesh(v + move[:, None] * normals, faces), float(found.mean())


def _self_intersecting(vertices, faces) -> np.ndarray:
    """(n,) bool: vertices of faces that intersect another face of the mesh (pymeshlab)."""
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=vertices, face_matrix=np.asarray(faces, dtype=np.int32)))
    ms.compute_selection_by_self_intersections_per_face()
    out = np.zeros(len(vertices), bool)
    out[np.asarray(faces)[ms.current_mesh().face_selection_array()].ravel()] = True
    return out
