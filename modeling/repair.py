"""Closed-surface checks and smoothing in numpy, for meshes that need no repair.

:func:`modeling.surface.mask_to_mesh` repairs its marching-cubes surface with
pymeshlab (duplicate vertices, null faces, non-manifold edges and vertices,
holes) before Taubin smoothing.  Marching cubes on a padded field usually gives
a surface with nothing to repair: :func:`clean_adjacency` tells so in one sort
of the half-edges and a walk round every vertex's fan, and :func:`taubin_smooth`
then smooths it with the same steps as pymeshlab, without the round trip.
"""

from __future__ import annotations

import numpy as np
from scipy import sparse

__all__ = ["clean_adjacency", "taubin_smooth"]


def clean_adjacency(verts: np.ndarray, faces: np.ndarray):
    """The vertex adjacency of a mesh that pymeshlab's clean-up would leave as it is.

    Such a mesh is closed, consistently wound, edge- and vertex-manifold, with
    no degenerate face, no unused vertex, no face of zero area and no two
    vertices at one position: what marching cubes on a padded field and most
    decimations give. :func:`modeling.surface.mask_to_mesh` then skips that clean-up.

    Returns
    -------
    scipy.sparse.csr_matrix (n, n) or None
        1 where two vertices share an edge (each edge in both directions);
        None when the mesh needs the clean-up.
    """
    n, m = len(verts), len(faces)
    if m == 0:
        return None
    a = faces.ravel()
    b = faces[:, [1, 2, 0]].ravel()
    valence = np.bincount(a, minlength=n)
    if np.any(a == b) or np.count_nonzero(valence) != n:
        return None
    key = a * n + b  # the half-edge a -> b leaving corner c = 3 * face + position
    order = np.argsort(key, kind="stable")
    sorted_key = key[order]
    if np.any(sorted_key[1:] == sorted_key[:-1]):
        return None  # a non-manifold edge, or faces wound inconsistently
    twin_key = b * n + a
    twin_order = np.argsort(twin_key, kind="stable")
    if not np.array_equal(twin_key[twin_order], sorted_key):
        return None  # an open edge
    twin = np.empty_like(order)  # the half-edge b -> a of each a -> b
    twin[twin_order] = order
    # the corner at the same vertex across that edge: stepping through them goes
    # round the vertex's fan of faces; one fan of all its faces = vertex-manifold
    turn = twin - twin % 3 + (twin + 1) % 3
    first = np.empty(n, dtype=np.int64)
    first[a[::-1]] = np.arange(len(a) - 1, -1, -1)
    at, fan = turn[first], np.ones(n, dtype=np.int64)
    walking = np.flatnonzero(at != first)
    while walking.size:
        at[walking] = turn[at[walking]]
        fan[walking] += 1
        walking = walking[at[walking] != first[walking]]
    if not np.array_equal(fan, valence):
        return None
    if not np.all(_cross_edges(verts, faces).any(axis=0)):
        return None  # a face of zero area
    if _has_coincident(verts):
        return None
    # the half-edges sorted by (a, b) are the rows of the adjacency, in order
    indptr = np.concatenate([[0], np.cumsum(valence)])
    return sparse.csr_matrix((np.ones(len(key)), b[order], indptr), shape=(n, n))


def _cross_edges(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(3, m) float64: (b - a) x (c - a) of every face (a, b, c), twice its area vector."""
    x, y, z = (np.ascontiguousarray(verts[:, k]) for k in range(3))
    f0, f1, f2 = (np.ascontiguousarray(faces[:, k]) for k in range(3))
    ux, uy, uz = x[f1] - x[f0], y[f1] - y[f0], z[f1] - z[f0]
    wx, wy, wz = x[f2] - x[f0], y[f2] - y[f0], z[f2] - z[f0]
    return np.stack([uy * wz - uz * wy, uz * wx - ux * wz, ux * wy - uy * wx])


def _has_coincident(verts: np.ndarray) -> bool:
    """Whether two rows of ``verts`` are equal (exact; a hash of the bits first)."""
    bits = np.ascontiguousarray(verts, dtype=np.float64).view(np.uint64)
    mixed = bits[:, 0] * np.uint64(0x9E3779B97F4A7C15) ^ bits[:, 1] * np.uint64(0xC2B2AE3D27D4EB4F)
    mixed ^= bits[:, 2] * np.uint64(0x165667B19E3779F9)
    mixed.sort()
    if not np.any(mixed[1:] == mixed[:-1]):
        return False
    return len(np.unique(verts, axis=0)) != len(verts)


def taubin_smooth(verts: np.ndarray, adjacency, iterations: int, *, lambda_: float, mu: float) -> np.ndarray:
    """Taubin lambda/mu smoothing with uniform weights.

    The same steps as pymeshlab's ``apply_coord_taubin_smoothing`` (vcglib
    ``VertexCoordTaubin``) on a closed mesh: each vertex moves ``lambda_``, then
    ``mu``, times the way to the mean of its edge neighbours, ``iterations`` times.

    Parameters
    ----------
    verts : (n, 3) float64, mm
    adjacency : (n, n) scipy.sparse matrix
        Edge neighbours (:func:`clean_adjacency`).
    iterations : int
    lambda_, mu : float
        The shrinking and the inflating step (``mu < -lambda_ < 0``).
    """
    count = np.asarray(adjacency.sum(axis=1))  # (n, 1)
    p = np.array(verts, dtype=np.float64)
    for _ in range(iterations):
        for factor in (lambda_, mu):
            p += factor * (adjacency @ p / count - p)
    return p
