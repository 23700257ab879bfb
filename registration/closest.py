"""Exact closest points on a triangle mesh (the search of :mod:`registration.icp`).

:func:`closest_points` returns the exact closest point on the mesh (not on a
sampled cloud): the point-triangle closest point (Ericson, *Real-Time Collision
Detection*, 5.1.5) is evaluated, vectorised, on a candidate set that provably
contains the closest triangle.  Search sites (the faces' centroids, and those
of sub-triangles of the few large faces) sit in a KD-tree; every point of a
face lies within its site's radius ``r_s`` of one of the face's sites, and
within ``r_max`` (the largest) of one.  A face can therefore hold a point
nearer than ``d`` to the query only if one of its sites lies within
``d + r_s``.  The search takes the ``k`` nearest sites, bounds ``d`` by the
nearest site's face, evaluates only the candidates within that bound, and
accepts the best when ``d <= d_k - r_max`` (``d_k`` the k-th site distance:
every other face is then at least ``d`` away); otherwise it searches every site
within ``d + r_max`` (a ball query).
"""

from __future__ import annotations

import itertools
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
        search sites (KD-tree points): the centroids of the faces, and of
        sub-triangles of the few large faces.
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
        # each site's own radius: every point of its (sub-)triangle lies within it, in its face's plane
        self._site_radius = (radii / m)[self._site_face]
        self._site_normal = self.normals[self._site_face]
        self.tree = cKDTree(np.concatenate(sites))

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


def _face_d2(surface, q, rows, faces, offsets=False):
    """Squared distance of q[rows] to faces (pairs), (p,) float64; NaN (a degenerate face) as inf.

    With ``offsets`` also the (p, 3) offsets of the points from their closest points.
    """
    a, ab, ac = surface._a[faces], surface._ab[faces], surface._ac[faces]
    qr = q[rows]
    v, w = _closest_barycentric(qr, a, ab, ac, surface._dots[faces])
    diff = qr - a - v[:, None] * ab - w[:, None] * ac
    d2 = np.einsum("ij,ij->i", diff, diff)
    d2 = np.where(np.isnan(d2), np.inf, d2)
    return (d2, diff) if offsets else d2


def _lower_best(best, rows, faces, d2, key):
    """Lower the best (d2, face, key) of each row in place with the pairs (rows sorted).

    Of equal distances (a point nearest to an edge or a vertex shared by
    faces) the face with the nearest search site (``key``, mm) wins, as in a
    scan of the sites nearest first.
    """
    if rows.size == 0:
        return
    best_d2, best_face, best_key = best
    starts = np.flatnonzero(np.r_[True, rows[1:] != rows[:-1]])
    low = np.minimum.reduceat(d2, starts)
    seg = np.repeat(np.arange(starts.size), np.diff(np.r_[starts, rows.size]))
    hit = np.flatnonzero(d2 == low[seg])
    hit = hit[np.lexsort((key[hit], seg[hit]))]
    hit = hit[np.r_[True, seg[hit][1:] != seg[hit][:-1]]]  # the nearest site of each row's minima
    r = rows[hit]
    better = (d2[hit] < best_d2[r]) | ((d2[hit] == best_d2[r]) & (key[hit] < best_key[r]))
    r, hit = r[better], hit[better]
    best_d2[r], best_face[r], best_key[r] = d2[hit], faces[hit], key[hit]


#: Slack (mm) on the bounds' comparisons: a face tied with the nearest within
#: rounding is evaluated, never skipped.
_SLACK_MM = 1e-9


def _site_bounds(surface, q, sites):
    """Lower bounds on the distance of q (n, 3) from the sub-triangles of ``sites`` (n, s).

    A site's (sub-)triangle lies in its face's plane within the site's radius
    of the site: in a disk.  The distance from that disk bounds the
    triangle's from below; far from the surface, where the sites' balls all
    reach about as near, the disks of the faces beside the foot stay away.

    Returns
    -------
    lower : (n, s) float64, mm
    offsets : (n, s, 3) float64, mm
        q less its closest point on each disk (``offsets / lower`` is the
        bound's gradient, a unit vector).
    """
    v = q[:, None] - surface.tree.data[sites]
    normal = surface._site_normal[sites]
    h = np.einsum("nsi,nsi->ns", v, normal)
    along = v - h[..., None] * normal  # in the plane, from the site
    rho = np.linalg.norm(along, axis=2)
    out = np.maximum(rho - surface._site_radius[sites], 0.0)
    offsets = h[..., None] * normal + along * np.divide(out, rho, out=np.zeros_like(rho), where=rho > 0)[..., None]
    return np.sqrt(h**2 + out**2), offsets


def _ball_search(best, surface, q, rows):
    """Settle ``rows`` by every site within their best distance plus the largest site radius (in place)."""
    best_d2 = best[0]
    radius = np.sqrt(best_d2[rows]) + surface.site_radius_mm
    lists = surface.tree.query_ball_point(q[rows], np.where(np.isfinite(radius), radius, np.inf),
                                          workers=-1, return_sorted=False)
    lengths = np.fromiter((len(x) for x in lists), dtype=np.int64, count=len(lists))
    sites = np.fromiter(itertools.chain.from_iterable(lists), dtype=np.int64, count=int(lengths.sum()))
    rr = np.repeat(rows, lengths)
    # a face can hold a point nearer than the best only if the disk of one of its sites
    # (:func:`_site_bounds`) lies within the best distance; the others are skipped unevaluated
    dist = np.linalg.norm(surface.tree.data[sites] - q[rr], axis=1)
    keep = _site_bounds(surface, q[rr], sites[:, None])[0][:, 0] <= np.sqrt(best_d2[rr]) + _SLACK_MM
    rr, faces, dist = rr[keep], surface._site_face[sites[keep]], dist[keep]
    _lower_best(best, rr, faces, _face_d2(surface, q, rr, faces), dist)


def _search(surface, q, k):
    """Exact nearest face of the points q from their ``k`` nearest sites (module docstring).

    Returns ``best`` (d2, face, key: the site distance) per point and what the
    search proved, for :mod:`registration.tracking`: the listed ``sites``
    (n, kc), the ``lower`` bounds on their faces' distances (exact where
    ``evaluated``, else the distance from the site's disk, :func:`_site_bounds`)
    with the ``offsets`` (n, kc, 3) of q from the points where they are
    attained, and ``excluded``: every face with no listed site is at least that
    far (-inf where the listed sites did not settle the point).
    """
    n = q.shape[0]
    n_sites = surface._site_face.shape[0]
    kc = int(min(k, n_sites))
    dist_s, idx = surface.tree.query(q, k=kc, workers=-1)
    dist_s, idx = dist_s.reshape(n, kc), idx.reshape(n, kc)
    faces = surface._site_face[idx]
    lower, offsets = _site_bounds(surface, q, idx)
    evaluated = np.zeros((n, kc), dtype=bool)
    # the nearest site's face bounds the distance
    d2, offsets[:, 0] = _face_d2(surface, q, np.arange(n), faces[:, 0], offsets=True)
    best = (d2, faces[:, 0].copy(), dist_s[:, 0].copy())
    lower[:, 0] = np.sqrt(d2)
    r, c = np.nonzero(lower[:, 1:] <= lower[:, :1] + _SLACK_MM)
    c += 1
    d2, offsets[r, c] = _face_d2(surface, q, r, faces[r, c], offsets=True)
    lower[r, c] = np.sqrt(d2)
    evaluated[:, 0], evaluated[r, c] = True, True
    _lower_best(best, r, faces[r, c], d2, dist_s[r, c])
    # faces without a site among the kc nearest are at least (kc-th site distance - r) away
    excluded = dist_s[:, -1] - surface.site_radius_mm if kc < n_sites else np.full(n, np.inf)
    unproven = np.flatnonzero(np.sqrt(best[0]) > excluded)
    if unproven.size:
        _ball_search(best, surface, q, unproven)
        excluded[unproven] = -np.inf
    return best, dict(sites=idx, lower=lower, evaluated=evaluated, offsets=offsets, excluded=excluded)


def _finish(surface, q, best_face) -> ClosestPoints:
    """The closest points on the found faces."""
    a, ab, ac = surface._a[best_face], surface._ab[best_face], surface._ac[best_face]
    v, w = _closest_barycentric(q, a, ab, ac, surface._dots[best_face])
    cp = a + v[:, None] * ab + w[:, None] * ac
    return ClosestPoints(cp, np.linalg.norm(q - cp, axis=1), best_face, surface.normals[best_face])


def closest_points(surface, points, *, k: int = 24) -> ClosestPoints:
    """Exact closest points on a triangle mesh.

    The ``k`` nearest search sites give candidate faces; the nearest site's
    face bounds the distance, and only the faces whose sites lie within that
    bound plus their own radius are evaluated.  Where the ``k``-th site is not
    far enough to exclude the faces beyond it (module docstring), every site
    within the found distance plus the largest site radius is searched.

    Parameters
    ----------
    surface : SurfaceIndex or (vertices, faces)
        Build a :class:`SurfaceIndex` once when querying repeatedly.
    points : (n, 3) float, mm
    k : int
        Nearest search sites tried first.

    Returns
    -------
    ClosestPoints
    """
    surface = _as_index(surface)
    q = _as_points(points)
    if k < 1:
        raise ValueError(f"k must be >= 1, got {k}")
    best, _ = _search(surface, q, k)
    return _finish(surface, q, best[1])
