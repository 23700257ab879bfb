"""Exact closest points on a triangle mesh (the search of :mod:`registration.icp`).

:func:`closest_points` returns the exact closest point on the mesh (not on a
sampled cloud).  :class:`SurfaceIndex` holds a bounding-volume hierarchy of
the faces' boxes (a complete binary tree, each node split at the median of
its faces' centroids along their longest extent, two to four faces per
leaf).  A compiled (numba) loop searches it depth first for each point, the
nearer child first, opening a box only when it lies within the best distance
so far, and evaluates the point-triangle closest point (Ericson, *Real-Time
Collision Detection*, 5.1.5) on the faces of the leaves it reaches: on the
bench's 20 000-face heart 0.4 us a point half a millimetre off the surface,
1.8 us at 6 mm.  The kernel does the
vectorised code's arithmetic (:func:`_closest_barycentric`) operation for
operation, so its distances are those of a brute-force evaluation bit for
bit; of faces equally near (a point nearest to a shared edge or vertex) the
one with the nearest search site wins, then the lowest index (the sites: the
faces' centroids, and those of sub-triangles of the few large faces).

The loop lives in :mod:`registration._closest_kernel`, imported on the first
search: importing numba costs ~0.15 s and ~75 MB, which code that only
builds an index (or the live localiser's single-sample path) need not pay.
The first search in a process loads the compiled loop from numba's cache
(about 0.2 s more, mostly numba's own start-up); the very first one compiles
it (about 1.5 s).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["SurfaceIndex", "ClosestPoints", "closest_points", "closest_points_on_triangles"]


def _subtriangle_centroids(m: int) -> np.ndarray:
    """Barycentric centroids of the m^2 sub-triangles of a triangle split m times."""
    out = []
    for i in range(m):
        for j in range(m - i):
            out.append([(i + 1 / 3), (j + 1 / 3), m - i - j - 2 / 3])  # upright
            if i + j < m - 1:
                out.append([(i + 2 / 3), (j + 2 / 3), m - i - j - 4 / 3])  # inverted
    return np.asarray(out) / m


class SurfaceIndex:
    """A triangle mesh prepared for exact closest-point queries.

    Parameters
    ----------
    vertices : (V, 3) float, mm
    faces : (F, 3) int
        Vertex indices; counter-clockwise seen from outside gives outward normals.

    Attributes
    ----------
    vertices, faces, centroids : arrays as above, (F, 3) centroids
    normals : (F, 3) float64
        Unit face normals (zero for degenerate faces).
    radius_mm : float
        Largest centroid-to-vertex distance over the faces.
    site_radius_mm : float
        Every point of every face lies within this distance of one of the face's
        search sites: the centroids of the faces, and of sub-triangles of the
        few large faces.  They break ties between equally near faces, and the
        live localiser (:mod:`registration.localise`) searches them.
    tree : scipy.spatial.cKDTree
        The search sites.
    """

    def __init__(self, vertices, faces):
        vertices = np.ascontiguousarray(vertices, dtype=float)
        faces = np.asarray(faces)
        if vertices.ndim != 2 or vertices.shape[1] != 3:
            raise ValueError(f"vertices must have shape (V, 3), got {vertices.shape}")
        if faces.ndim != 2 or faces.shape[1] != 3 or faces.shape[0] == 0:
            raise ValueError(f"faces must have shape (F, 3) with F >= 1, got {faces.shape}")
        if not np.issubdtype(faces.dtype, np.integer):
            raise ValueError(f"faces must be integer indices, got dtype {faces.dtype}")
        if faces.min() < 0 or faces.max() >= vertices.shape[0]:
            raise ValueError(f"faces index vertices outside 0..{vertices.shape[0] - 1}")
        if not np.all(np.isfinite(vertices)):
            raise ValueError("vertices must be finite")
        self.vertices = vertices
        self.faces = np.ascontiguousarray(faces, dtype=np.int64)
        tri = vertices[self.faces]
        self._a = np.ascontiguousarray(tri[:, 0])
        self._ab = np.ascontiguousarray(tri[:, 1] - tri[:, 0])
        self._ac = np.ascontiguousarray(tri[:, 2] - tri[:, 0])
        self.centroids = tri.mean(axis=1)
        self._dots = np.stack(
            [
                np.einsum("ij,ij->i", self._ab, self._ab),
                np.einsum("ij,ij->i", self._ab, self._ac),
                np.einsum("ij,ij->i", self._ac, self._ac),
            ],
            axis=1,
        )
        n = np.cross(self._ab, self._ac)
        norm = np.linalg.norm(n, axis=1, keepdims=True)
        self.normals = np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)
        radii = np.linalg.norm(tri - self.centroids[:, None], axis=2).max(axis=1)
        self.radius_mm = float(radii.max())
        # Search sites: each face split into m x m sub-triangles (m = 1 for most),
        # one site at each sub-triangle's centroid, so that every point of every
        # face is within ``site_radius_mm`` of a site of the same face.
        site_radius = float(np.percentile(radii, 90)) or self.radius_mm or 1.0
        m = np.maximum(1, np.ceil(radii / site_radius - 1e-9)).astype(int)
        sites, owners = [self.centroids[m == 1]], [np.flatnonzero(m == 1)]
        for level in np.unique(m[m > 1]):
            ids = np.flatnonzero(m == level)
            bary = _subtriangle_centroids(int(level))  # (s, 3) barycentric weights
            sites.append(np.einsum("sk,fkj->fsj", bary, tri[ids]).reshape(-1, 3))
            owners.append(np.repeat(ids, bary.shape[0]))
        self.site_radius_mm = float(max(site_radius, (radii / m).max()))
        self._site_face = np.concatenate(owners)
        self.tree = cKDTree(np.concatenate(sites))
        # each face's sites, for the tie rule of the search: (F + 1,) offsets into (S, 3) sites
        by_face = np.argsort(self._site_face, kind="stable")
        self._face_sites = np.ascontiguousarray(self.tree.data[by_face])
        self._face_site_ptr = np.r_[0, np.cumsum(np.bincount(self._site_face, minlength=self.n_faces))]
        # the bounding-volume hierarchy of the search, the faces' constants in its leaf order
        self._node_lo, self._node_hi, self._leaf_ptr, self._leaf_faces = \
            _build_bvh(tri.min(axis=1), tri.max(axis=1), self.centroids)
        self._leaf_a, self._leaf_ab, self._leaf_ac, self._leaf_dots = \
            (np.ascontiguousarray(x[self._leaf_faces]) for x in (self._a, self._ab, self._ac, self._dots))

    @property
    def n_faces(self) -> int:
        return self.faces.shape[0]

    def __repr__(self) -> str:
        return f"SurfaceIndex({self.vertices.shape[0]} vertices, {self.n_faces} faces)"


def _as_index(surface) -> SurfaceIndex:
    if isinstance(surface, SurfaceIndex):
        return surface
    if isinstance(surface, tuple) and len(surface) == 2:
        return SurfaceIndex(*surface)
    if hasattr(surface, "vertices") and hasattr(surface, "faces"):
        return SurfaceIndex(surface.vertices, surface.faces)
    raise ValueError("surface must be a SurfaceIndex, a (vertices, faces) tuple or a mesh")


def _as_points(points, *, at_least: int = 1) -> np.ndarray:
    """``points`` as finite (n, 3) float64 with n >= ``at_least``; ValueError naming them otherwise."""
    q = np.asarray(points, dtype=float)
    if q.ndim != 2 or q.shape[1] != 3:
        raise ValueError(f"points must have shape (n, 3), got {q.shape}")
    if q.shape[0] < at_least:
        raise ValueError(f"need at least {at_least} points, got {q.shape[0]}")
    if not np.all(np.isfinite(q)):
        raise ValueError("points must be finite")
    return q


def _closest_barycentric(p, a, ab, ac, dots=None):
    """Closest point on triangles (a, a + ab, a + ac) to p; all (..., 3).

    ``dots`` (..., 3) may hold the per-face constants (ab.ab, ab.ac, ac.ac).
    Returns the point as ``a + v ab + w ac``: (v, w) each (...).
    """
    ap = p - a
    if dots is None:
        dots = np.stack(
            [
                np.einsum("...i,...i->...", ab, ab),
                np.einsum("...i,...i->...", ab, ac),
                np.einsum("...i,...i->...", ac, ac),
            ],
            axis=-1,
        )
    d1 = np.einsum("...i,...i->...", ab, ap)
    d2 = np.einsum("...i,...i->...", ac, ap)
    ab_ab, ab_ac, ac_ac = dots[..., 0], dots[..., 1], dots[..., 2]
    d3 = d1 - ab_ab  # ab . (p - b)
    d4 = d2 - ab_ac  # ac . (p - b)
    d5 = d1 - ab_ac  # ab . (p - c)
    d6 = d2 - ac_ac  # ac . (p - c)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        denom = np.where(denom == 0, 1.0, denom)
        v_face, w_face = vb / denom, vc / denom
        e_ab = d1 - d3
        v_ab = d1 / np.where(e_ab == 0, 1.0, e_ab)
        e_ac = d2 - d6
        w_ac = d2 / np.where(e_ac == 0, 1.0, e_ac)
        e_bc = (d4 - d3) + (d5 - d6)
        w_bc = (d4 - d3) / np.where(e_bc == 0, 1.0, e_bc)
    in_a = (d1 <= 0) & (d2 <= 0)
    in_b = (d3 >= 0) & (d4 <= d3)
    in_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    in_c = (d6 >= 0) & (d5 <= d6)
    in_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    in_bc = (va <= 0) & (d4 >= d3) & (d5 >= d6)
    conditions = [in_a, in_b, in_ab, in_c, in_ac, in_bc]
    zero, one = np.zeros_like(d1), np.ones_like(d1)
    v = np.select(conditions, [zero, one, v_ab, zero, zero, 1.0 - w_bc], v_face)
    w = np.select(conditions, [zero, zero, zero, one, w_ac, w_bc], w_face)
    return v, w


def closest_points_on_triangles(points, triangles) -> np.ndarray:
    """Exact closest point on each triangle to the matching point.

    Parameters
    ----------
    points : (n, 3) float, mm
    triangles : (n, 3, 3) float, mm
        ``triangles[i]`` = vertices (a, b, c) of the i-th triangle.

    Returns
    -------
    (n, 3) float64, mm
    """
    points = np.asarray(points, dtype=float)
    triangles = np.asarray(triangles, dtype=float)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (n, 3), got {points.shape}")
    if triangles.shape != (points.shape[0], 3, 3):
        raise ValueError(f"triangles must have shape ({points.shape[0]}, 3, 3), got {triangles.shape}")
    a = triangles[:, 0]
    ab = triangles[:, 1] - a
    ac = triangles[:, 2] - a
    v, w = _closest_barycentric(points, a, ab, ac)
    return a + v[:, None] * ab + w[:, None] * ac


@dataclass(frozen=True)
class ClosestPoints:
    """Closest points on a mesh.

    Attributes
    ----------
    points : (n, 3) float64, mm
        The closest point on the surface to each query point.
    distances_mm : (n,) float64
    face_index : (n,) int64
        The face the closest point lies on (one of them on a shared edge/vertex).
    normals : (n, 3) float64
        That face's unit normal.
    """

    points: np.ndarray
    distances_mm: np.ndarray
    face_index: np.ndarray
    normals: np.ndarray


# ---------------------------------------------------------------- the search

#: Faces per leaf of the bounding-volume hierarchy.
_LEAF_SIZE = 4

def _build_bvh(lo, hi, centres, leaf_size=_LEAF_SIZE):
    """A bounding-volume hierarchy of the face boxes ``lo``..``hi`` (F, 3) with centres (F, 3).

    A complete binary tree of depth ``D`` (the least with at most
    ``leaf_size`` faces per leaf), stored as a heap: node ``i`` has children
    ``2 i + 1`` and ``2 i + 2``, the last ``2**D`` nodes are the leaves.  Each
    node splits its faces at the median centre along the longest extent of
    their centres (all nodes of a level in one sort).

    Returns
    -------
    node_lo, node_hi : (2**(D+1) - 1, 3) float64
        The nodes' boxes.
    leaf_ptr : (2**D + 1,) int64
        Leaf ``j`` holds the faces ``order[leaf_ptr[j]:leaf_ptr[j + 1]]`` (2 to ``leaf_size`` of them).
    order : (F,) int64
        The faces in leaf order.
    """
    f = lo.shape[0]
    depth = int(np.ceil(np.log2(f / leaf_size))) if f > leaf_size else 0
    order = np.arange(f)
    bounds = np.array([0, f])
    for _ in range(depth):
        s, e = bounds[:-1], bounds[1:]
        seg = np.repeat(np.arange(s.size), e - s)
        c = centres[order]
        extent = np.maximum.reduceat(c, s) - np.minimum.reduceat(c, s)
        order = order[np.lexsort((c[np.arange(f), np.argmax(extent, axis=1)[seg]], seg))]
        bounds = np.r_[np.stack([s, (s + e) // 2], axis=1).ravel(), f]
    n_leaves = bounds.size - 1
    node_lo, node_hi = np.empty((2 * n_leaves - 1, 3)), np.empty((2 * n_leaves - 1, 3))
    node_lo[n_leaves - 1:] = np.minimum.reduceat(lo[order], bounds[:-1])
    node_hi[n_leaves - 1:] = np.maximum.reduceat(hi[order], bounds[:-1])
    for level in range(depth - 1, -1, -1):  # parents from their children, bottom up
        i = np.arange(2**level - 1, 2 ** (level + 1) - 1)
        node_lo[i] = np.minimum(node_lo[2 * i + 1], node_lo[2 * i + 2])
        node_hi[i] = np.maximum(node_hi[2 * i + 1], node_hi[2 * i + 2])
    return node_lo, node_hi, bounds.astype(np.int64), order


def _nearest(surface: SurfaceIndex, q):
    """The exact nearest face (n,) int64 of each point q (n, 3), and (n, 2) the (v, w) of its closest point."""
    # imported here, on the first search: see the module docstring
    from registration._closest_kernel import nearest_faces

    s = surface
    return nearest_faces(np.ascontiguousarray(q, dtype=float), s._node_lo, s._node_hi, s._leaf_ptr,
                          s._leaf_faces, s._leaf_a, s._leaf_ab, s._leaf_ac, s._leaf_dots, s._face_site_ptr,
                          s._face_sites)


def closest_points(surface, points) -> ClosestPoints:
    """Exact closest points on a triangle mesh.

    A depth-first search of a bounding-volume hierarchy of the faces (built
    once per :class:`SurfaceIndex`), compiled: the nearer child first, a box
    opened only when it lies within the best distance so far.  Of faces
    equally near (a point nearest to a shared edge or vertex) the face with
    the nearest search site wins, then the lowest index.

    Parameters
    ----------
    surface : SurfaceIndex or (vertices, faces)
        Build a :class:`SurfaceIndex` once when querying repeatedly.
    points : (n, 3) float, mm

    Returns
    -------
    ClosestPoints
    """
    surface = _as_index(surface)
    q = _as_points(points)
    face, vw = _nearest(surface, q)
    a, ab, ac = surface._a[face], surface._ab[face], surface._ac[face]
    cp = a + vw[:, :1] * ab + vw[:, 1:] * ac
    return ClosestPoints(cp, np.linalg.norm(q - cp, axis=1), face, surface.normals[face])
