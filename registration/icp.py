"""Rigid ICP of points to a triangle mesh, with exact closest points on the triangles.

Closest points
--------------
:func:`closest_points` returns the exact closest point on the mesh (not on a
sampled cloud): the point-triangle closest point (Ericson, *Real-Time Collision
Detection*, 5.1.5) is evaluated, vectorised, on a candidate set that provably
contains the closest triangle.  A triangle lies inside the ball of radius
``r_i = max_v |v - centroid_i|`` about its centroid; with ``r_max`` the largest
such radius over the mesh and ``d`` an upper bound on the distance from a query
point to the mesh, the closest triangle's centroid lies within ``d + r_max`` of
the query.  The search takes the ``k`` nearest centroids (KD-tree), computes the
best distance ``d`` among them and accepts it when ``d <= d_k - r_max`` (``d_k``
the k-th centroid distance: every other triangle is then at least ``d`` away);
otherwise it repeats with all centroids within ``d + r_max``.

ICP
---
Point-to-point (closed-form SVD step) and point-to-plane (Gauss-Newton on the
linearised rotation, using the closest faces' normals) variants, with optional
trimming (keep the best fraction) and Huber weights.  Sliding along a surface
with a symmetry (sphere, cylinder, a flat patch) leaves directions of the rigid
motion undetermined: the result reports the eigenvalues of the point-to-plane
normal matrix at the solution (rotations scaled by the points' RMS radius so
all six are in mm^2 per point), its condition number and the weakest
direction, and flags ``degenerate`` when the ratio of smallest to largest is
below ``degeneracy_ratio``.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from hrcore.geometry import apply_to_points, check_transform, kabsch

__all__ = [
    "IcpMethod",
    "SurfaceIndex",
    "ClosestPoints",
    "IcpResult",
    "closest_points",
    "closest_points_on_triangles",
    "icp",
    "icp_sweep",
    "icp_sweep_distances",
]


def _subtriangle_centroids(m: int) -> np.ndarray:
    """Barycentric centroids of the m^2 sub-triangles of a triangle split m times."""
    out = []
    for i in range(m):
        for j in range(m - i):
            out.append([(i + 1 / 3), (j + 1 / 3), m - i - j - 2 / 3])  # upright
            if i + j < m - 1:
                out.append([(i + 2 / 3), (j + 2 / 3), m - i - j - 4 / 3])  # inverted
    return np.asarray(out) / m


class IcpMethod(str, enum.Enum):
    """ICP error metric."""

    POINT_TO_POINT = "point_to_point"
    POINT_TO_PLANE = "point_to_plane"


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


def _best_among(surface, q, cand):
    """Closest point of q (n, 3) among candidate faces cand (n, k)."""
    a, ab, ac = surface._a[cand], surface._ab[cand], surface._ac[cand]
    qq = q[:, None, :]
    v, w = _closest_barycentric(qq, a, ab, ac, surface._dots[cand])
    diff = qq - a - v[..., None] * ab - w[..., None] * ac
    d2 = np.einsum("nki,nki->nk", diff, diff)
    j = np.argmin(d2, axis=1)
    rows = np.arange(q.shape[0])
    return q - diff[rows, j], np.sqrt(d2[rows, j]), cand[rows, j]


def _best_pruned(surface, q, sites, dist_s):
    """Closest point of q (n, 3) among the faces of candidate sites (n, k).

    Only the sites within ``d0 + site_radius_mm`` of a query are evaluated
    (and the nearest one), ``d0`` being the exact distance to the face of its
    nearest candidate site: a face closer than ``d0`` has a site within
    ``d0 + site_radius_mm`` (module docstring), so a candidate farther than
    that cannot reveal it.  Same answer as evaluating every candidate, in the
    same column order.
    """
    n, kc = sites.shape
    rows = np.arange(n)
    faces = surface._site_face[sites]
    j0 = np.argmin(dist_s, axis=1)
    _, d0, _ = _best_among(surface, q, faces[rows, j0][:, None])
    # "not farther" so that a NaN bound (degenerate face) keeps every candidate; the
    # nearest site's own face is always kept (its closest point may lie nearer
    # another site of the same face, one outside this candidate list)
    mask = ~(dist_s > (d0 + surface.site_radius_mm)[:, None])
    mask[rows, j0] = True
    rr, cc = np.nonzero(mask)
    fc = faces[rr, cc]
    a, ab, ac = surface._a[fc], surface._ab[fc], surface._ac[fc]
    qr = q[rr]
    v, w = _closest_barycentric(qr, a, ab, ac, surface._dots[fc])
    diff = qr - a - v[:, None] * ab - w[:, None] * ac
    d2 = np.einsum("ij,ij->i", diff, diff)
    full = np.full((n, kc), np.inf)
    full[rr, cc] = d2
    j = np.argmin(full, axis=1)
    where = np.empty((n, kc), dtype=np.int64)
    where[rr, cc] = np.arange(rr.size)
    p = where[rows, j]
    return q - diff[p], np.sqrt(d2[p]), faces[rows, j]


def closest_points(surface, points, *, k: int = 16) -> ClosestPoints:
    """Exact closest points on a triangle mesh.

    Parameters
    ----------
    surface : SurfaceIndex or (vertices, faces)
        Build a :class:`SurfaceIndex` once when querying repeatedly.
    points : (n, 3) float, mm
    k : int
        Nearest centroids tried first; more are searched only where the bound in
        the module docstring does not prove the answer.

    Returns
    -------
    ClosestPoints
    """
    surface = _as_index(surface)
    q = np.asarray(points, dtype=float)
    if q.ndim != 2 or q.shape[1] != 3:
        raise ValueError(f"points must have shape (n, 3), got {q.shape}")
    if not np.all(np.isfinite(q)):
        raise ValueError("points must be finite")
    if k < 1:
        raise ValueError(f"k must be >= 1, got {k}")
    n = q.shape[0]
    n_sites = surface._site_face.shape[0]
    r = surface.site_radius_mm
    kc = int(min(k, n_sites))
    dist_s, idx = surface.tree.query(q, k=kc, workers=-1)
    dist_s, idx = dist_s.reshape(n, kc), idx.reshape(n, kc)
    cp, d, face = _best_pruned(surface, q, idx, dist_s)
    # Faces without a site among the kc nearest are at least (kc-th site
    # distance - r) away: the answer is proven where d is below that.
    unproven = np.flatnonzero(d > dist_s[:, -1] - r) if kc < n_sites else np.empty(0, int)
    while unproven.size:
        k_old, kc = kc, min(4 * kc, n_sites)
        qu = q[unproven]
        dist_s, idx = surface.tree.query(qu, k=kc, workers=-1)
        dist_s, idx = dist_s.reshape(-1, kc), idx.reshape(-1, kc)
        cp2, d2, f2 = _best_pruned(surface, qu, idx[:, k_old:], dist_s[:, k_old:])
        better = d2 < d[unproven]
        sel = unproven[better]
        cp[sel], d[sel], face[sel] = cp2[better], d2[better], f2[better]
        if kc == n_sites:
            break
        unproven = unproven[d[unproven] > dist_s[:, -1] - r]
    return ClosestPoints(cp, d, face, surface.normals[face])


@dataclass(frozen=True)
class IcpResult:
    """Result of :func:`icp`.

    Attributes
    ----------
    T_target_from_source : (4, 4) float64
        Maps the source points onto the surface's frame.
    rms_mm : float
        RMS point-to-surface distance over all points at the solution.
    rms_inlier_mm : float
        The same over the inliers kept by trimming.
    distances_mm : (n,) float64
        Point-to-surface distance of each point at the solution.
    closest_points : (n, 3) float64, mm
        Closest surface points (target frame).
    inliers : (n,) bool
    iterations : int
    converged : bool
        True when the last step moved less than ``tol_mm`` and ``tol_deg``.
    method : str
    hessian_eigenvalues : (6,) float64, mm^2 per point
        Ascending eigenvalues of the point-to-plane normal matrix at the solution
        (rotation parts scaled by the RMS radius of the points).
    weakest_direction : (6,) float64
        Unit eigenvector of the smallest eigenvalue: (rotation about the
        points' centroid scaled by the radius, translation), target frame.
    condition_number : float
        Largest over smallest eigenvalue.
    degenerate : bool
        Smallest / largest eigenvalue below ``degeneracy_ratio``: the surface lets
        the points slide; the solution along ``weakest_direction`` is not unique.
    """

    T_target_from_source: np.ndarray
    rms_mm: float
    rms_inlier_mm: float
    distances_mm: np.ndarray
    closest_points: np.ndarray
    inliers: np.ndarray
    iterations: int
    converged: bool
    method: str
    hessian_eigenvalues: np.ndarray
    weakest_direction: np.ndarray
    condition_number: float
    degenerate: bool


def _plane_system(q, c, normals, w, centre, scale):
    qc = q - centre
    J = np.concatenate([np.cross(qc, normals) / scale, normals], axis=1)
    r = np.einsum("ij,ij->i", q - c, normals)
    Jw = J * w[:, None]
    return Jw.T @ J, Jw.T @ r


def _check_options(src, T_init, trim_fraction, huber_mm, max_iterations) -> np.ndarray:
    """Validate the options shared by :func:`icp` and :func:`icp_sweep`; return T_init."""
    if not np.all(np.isfinite(src)):
        raise ValueError("points must be finite")
    T = np.eye(4) if T_init is None else check_transform(T_init, name="T_init").copy()
    if not 0.0 <= trim_fraction < 0.5:
        raise ValueError(f"trim_fraction must be in [0, 0.5), got {trim_fraction}")
    if huber_mm is not None and not huber_mm > 0:
        raise ValueError(f"huber_mm must be positive, got {huber_mm}")
    if max_iterations < 1:
        raise ValueError(f"max_iterations must be >= 1, got {max_iterations}")
    return T


def icp(
    points,
    surface,
    *,
    T_init=None,
    method: IcpMethod | str = IcpMethod.POINT_TO_PLANE,
    max_iterations: int = 50,
    tol_mm: float = 1e-3,
    tol_deg: float = 1e-3,
    trim_fraction: float = 0.0,
    huber_mm: float | None = None,
    degeneracy_ratio: float = 1e-3,
    k: int = 16,
) -> IcpResult:
    """Rigidly register points to a triangle mesh.

    Parameters
    ----------
    points : (n, 3) float, mm
        Source points (e.g. predicted robot positions, probe frame), n >= 3.
    surface : SurfaceIndex or (vertices, faces)
        Target surface (e.g. the heart model, map frame).
    T_init : (4, 4) float, optional
        Initial ``T_target_from_source`` (the fiducial seed); identity by default.
    method : IcpMethod or str
        ``"point_to_plane"`` (default, converges in few iterations) or
        ``"point_to_point"``.
    max_iterations : int
    tol_mm, tol_deg : float, mm and degrees
        Converged when one step moves the points' centroid less than ``tol_mm``
        and rotates less than ``tol_deg``.
    trim_fraction : float in [0, 0.5)
        Fraction of the points with the largest distances ignored in each step.
    huber_mm : float, optional
        Huber weights ``min(1, huber_mm / d)`` on the kept points.
    degeneracy_ratio : float
        See :attr:`IcpResult.degenerate`.
    k : int
        Candidate faces per point tried first by :func:`closest_points`.

    Returns
    -------
    IcpResult
    """
    surface = _as_index(surface)
    src = np.asarray(points, dtype=float)
    if src.ndim != 2 or src.shape[1] != 3:
        raise ValueError(f"points must have shape (n, 3), got {src.shape}")
    if src.shape[0] < 3:
        raise ValueError(f"ICP needs at least 3 points, got {src.shape[0]}")
    method = IcpMethod(method)
    T = _check_options(src, T_init, trim_fraction, huber_mm, max_iterations)
    n = src.shape[0]
    n_keep = max(3, int(np.ceil((1.0 - trim_fraction) * n)))
    centre_src = src.mean(axis=0)
    scale = float(np.sqrt(np.mean(np.sum((src - centre_src) ** 2, axis=1)))) or 1.0
    tol_rad = np.radians(tol_deg)

    converged = False
    iterations = 0
    for iterations in range(1, max_iterations + 1):
        q = apply_to_points(T, src)
        cp = closest_points(surface, q, k=k)
        w = _weights(cp.distances_mm, n_keep, huber_mm)
        sel = w > 0
        centre = apply_to_points(T, centre_src)
        if method is IcpMethod.POINT_TO_POINT:
            fit = kabsch(q[sel], cp.points[sel], weights=w[sel])
            R, t = fit[:3, :3], fit[:3, 3]
        else:
            A, b = _plane_system(q[sel], cp.points[sel], cp.normals[sel], w[sel], centre, scale)
            x = np.linalg.lstsq(A, -b, rcond=1e-12)[0]
            R = Rotation.from_rotvec(x[:3] / scale).as_matrix()
            t = centre - R @ centre + x[3:]
        step = np.eye(4)
        step[:3, :3], step[:3, 3] = R, t
        T = step @ T
        moved = np.linalg.norm(R @ centre + t - centre)
        angle = Rotation.from_matrix(R).magnitude()
        if moved < tol_mm and angle < tol_rad:
            converged = True
            break

    q = apply_to_points(T, src)
    cp = closest_points(surface, q, k=k)
    w = _weights(cp.distances_mm, n_keep, huber_mm)
    sel = w > 0
    centre = apply_to_points(T, centre_src)
    A, _ = _plane_system(q[sel], cp.points[sel], cp.normals[sel], w[sel], centre, scale)
    A = A / w[sel].sum()
    evals, evecs = np.linalg.eigh(A)
    evals = np.clip(evals, 0.0, None)
    cond = float(evals[-1] / evals[0]) if evals[0] > 0 else float("inf")
    d = cp.distances_mm
    return IcpResult(
        T_target_from_source=T,
        rms_mm=float(np.sqrt(np.mean(d**2))),
        rms_inlier_mm=float(np.sqrt(np.mean(d[sel] ** 2))),
        distances_mm=d,
        closest_points=cp.points,
        inliers=sel,
        iterations=iterations,
        converged=converged,
        method=method.value,
        hessian_eigenvalues=evals,
        weakest_direction=evecs[:, 0],
        condition_number=cond,
        degenerate=bool(evals[0] < degeneracy_ratio * evals[-1]),
    )


def _weights(d, n_keep, huber_mm):
    w = np.zeros_like(d)
    if n_keep >= d.shape[0]:
        keep = np.arange(d.shape[0])
    else:
        keep = np.argpartition(d, n_keep - 1)[:n_keep]
    w[keep] = 1.0
    if huber_mm is not None:
        w[keep] = np.minimum(1.0, huber_mm / np.maximum(d[keep], 1e-12))
    return w


def icp_sweep(points, surface, **options):
    """Point-to-plane :func:`icp` of many point sets at once, all from one seed.

    See :func:`icp_sweep_distances` for the parameters (``T_init``, ``max_iterations``,
    ``tol_mm``, ``tol_deg``, ``trim_fraction``, ``huber_mm``, ``k``).

    Returns
    -------
    T_target_from_source : (m, 4, 4) float64
    rms_mm : (m,) float64
        RMS point-to-surface distance at each solution.
    iterations : (m,) int64
    converged : (m,) bool
    """
    T, d, iterations, converged = icp_sweep_distances(points, surface, **options)
    return T, np.sqrt(np.mean(d**2, axis=1)), iterations, converged


def icp_sweep_distances(
    points,
    surface,
    *,
    T_init=None,
    max_iterations: int = 50,
    tol_mm: float = 1e-3,
    tol_deg: float = 1e-3,
    trim_fraction: float = 0.0,
    huber_mm: float | None = None,
    k: int = 16,
    warm_start: bool = False,
    warm_stride: int = 10,
):
    """Point-to-plane :func:`icp` of many point sets at once.

    The same iteration as :func:`icp` (method ``"point_to_plane"``), run on all
    ``m`` point sets together so that each iteration makes one closest-point
    query for all active sets; a set stops when its step is below the
    tolerances, or when it returns within them to where it was two steps
    before (a two-cycle between faces of the mesh: it has converged as far as
    the facets allow).  The 6 x 6 steps are solved with a pseudo-inverse
    (``rcond = 1e-12``, as ``icp``'s ``lstsq``).

    With ``warm_start`` the sets are taken as ordered samples of a smooth
    family (the predicted points along a phase sweep): every ``warm_stride``-th
    set is registered from ``T_init``, then the others in waves outwards from
    those, each seeded by its already registered neighbour, which is a
    fraction of a millimetre away rather than the seed's ~10 mm; the sweep
    then takes a few iterations per set instead of ten or more.  Each set still
    iterates to the same tolerances, so the answers agree with the cold start
    to about the tolerance (the bench checks 0.01 mm).

    Parameters
    ----------
    points : (m, n, 3) float, mm
        m source point sets (e.g. the predicted points at m phases).
    surface : SurfaceIndex or (vertices, faces)
    T_init : (4, 4) or (m, 4, 4) float, optional
        Seed of every registration, or one per set.
    max_iterations, tol_mm, tol_deg, trim_fraction, huber_mm, k
        As for :func:`icp`.
    warm_start : bool
        Seed each set by its registered neighbour (see above).
    warm_stride : int
        Sets registered from ``T_init`` when warm starting: every this many.

    Returns
    -------
    T_target_from_source : (m, 4, 4) float64
    distances_mm : (m, n) float64
        Point-to-surface distance of every point at each solution.
    iterations : (m,) int64
    converged : (m,) bool
    """
    surface = _as_index(surface)
    src = np.asarray(points, dtype=float)
    if src.ndim != 3 or src.shape[2] != 3 or src.shape[0] == 0:
        raise ValueError(f"points must have shape (m, n, 3), got {src.shape}")
    if src.shape[1] < 3:
        raise ValueError(f"ICP needs at least 3 points, got {src.shape[1]}")
    m, n, _ = src.shape
    seeds = None if T_init is None else np.array(T_init, dtype=float)
    if seeds is not None and seeds.shape == (m, 4, 4):
        _check_options(src, seeds[0], trim_fraction, huber_mm, max_iterations)
    else:
        seeds = np.repeat(_check_options(src, seeds, trim_fraction, huber_mm, max_iterations)[None], m, axis=0)
    if int(warm_stride) != warm_stride or warm_stride < 1:
        raise ValueError(f"warm_stride must be a positive integer, got {warm_stride}")
    options = dict(max_iterations=max_iterations, tol_mm=tol_mm, tol_deg=tol_deg,
                   n_keep=max(3, int(np.ceil((1.0 - trim_fraction) * n))), huber_mm=huber_mm, k=k)
    if not warm_start or m <= 2:
        return _icp_batch(src, surface, seeds, **options)
    T = np.empty((m, 4, 4))
    d = np.empty((m, n))
    iterations = np.zeros(m, dtype=np.int64)
    converged = np.zeros(m, dtype=bool)
    anchors = np.unique(np.r_[np.arange(0, m, warm_stride), m - 1])
    done = np.zeros(m, dtype=bool)
    wave = anchors
    source_of = {int(i): None for i in anchors}
    while wave.size:
        seed = np.stack([seeds[i] if source_of[int(i)] is None else T[source_of[int(i)]] for i in wave])
        T[wave], d[wave], iterations[wave], converged[wave] = _icp_batch(src[wave], surface, seed, **options)
        done[wave] = True
        nxt = {}
        for i in wave:
            for j in (i - 1, i + 1):
                if 0 <= j < m and not done[j] and j not in nxt:
                    nxt[int(j)] = int(i)
        source_of = nxt
        wave = np.array(sorted(nxt), dtype=np.int64)
    return T, d, iterations, converged


def _icp_batch(src, surface, seeds, *, max_iterations, tol_mm, tol_deg, n_keep, huber_mm, k):
    """The batched point-to-plane iteration of :func:`icp_sweep_distances`, one seed per set."""
    m, n, _ = src.shape
    centre_src = src.mean(axis=1)  # (m, 3)
    scale = np.sqrt(np.mean(np.sum((src - centre_src[:, None]) ** 2, axis=2), axis=1))
    scale[scale == 0] = 1.0
    tol_rad = np.radians(tol_deg)

    T = np.array(seeds, dtype=float)
    T_before = np.full_like(T, np.nan)  # two steps back, for the two-cycle test
    iterations = np.zeros(m, dtype=np.int64)
    converged = np.zeros(m, dtype=bool)
    active = np.arange(m)
    for _ in range(max_iterations):
        a = active
        R0, t0 = T[a, :3, :3], T[a, :3, 3]
        q = np.einsum("aij,anj->ani", R0, src[a]) + t0[:, None]
        cp = closest_points(surface, q.reshape(-1, 3), k=k)
        d = cp.distances_mm.reshape(len(a), n)
        w = _weights_batch(d, n_keep, huber_mm)
        centre = np.einsum("aij,aj->ai", R0, centre_src[a]) + t0
        normals = cp.normals.reshape(len(a), n, 3)
        J = np.concatenate([np.cross(q - centre[:, None], normals) / scale[a, None, None], normals], axis=2)
        r = np.einsum("ani,ani->an", q - cp.points.reshape(len(a), n, 3), normals)
        Jw = J * w[:, :, None]
        A = np.einsum("ani,anj->aij", Jw, J)
        b = np.einsum("ani,an->ai", Jw, r)
        x = -np.einsum("aij,aj->ai", np.linalg.pinv(A, rcond=1e-12), b)
        R = Rotation.from_rotvec(x[:, :3] / scale[a, None]).as_matrix()
        t = centre - np.einsum("aij,aj->ai", R, centre) + x[:, 3:]
        step = np.zeros((len(a), 4, 4))
        step[:, :3, :3], step[:, :3, 3], step[:, 3, 3] = R, t, 1.0
        previous = T[a]
        T[a] = step @ previous
        iterations[a] += 1
        moved = np.linalg.norm(np.einsum("aij,aj->ai", R, centre) + t - centre, axis=1)
        angle = Rotation.from_matrix(R).magnitude()
        # two-cycle: back within the tolerances of where the set was two steps ago
        back = T[a] @ np.linalg.inv(np.where(np.isnan(T_before[a]), previous, T_before[a]))
        back_moved = np.linalg.norm(np.einsum("aij,aj->ai", back[:, :3, :3], centre) + back[:, :3, 3] - centre, axis=1)
        back_angle = Rotation.from_matrix(back[:, :3, :3]).magnitude()
        cycled = ~np.isnan(T_before[a, 0, 0]) & (back_moved < tol_mm) & (back_angle < tol_rad)
        done = ((moved < tol_mm) & (angle < tol_rad)) | cycled
        T_before[a] = previous
        converged[a[done]] = True
        active = a[~done]
        if active.size == 0:
            break

    q = np.einsum("aij,anj->ani", T[:, :3, :3], src) + T[:, None, :3, 3]
    d = closest_points(surface, q.reshape(-1, 3), k=k).distances_mm.reshape(m, n)
    return T, d, iterations, converged


def _weights_batch(d, n_keep, huber_mm):
    """:func:`_weights` of each row of d (m, n)."""
    m, n = d.shape
    if n_keep >= n:
        w = np.ones_like(d)
    else:
        w = np.zeros_like(d)
        keep = np.argpartition(d, n_keep - 1, axis=1)[:, :n_keep]
        np.put_along_axis(w, keep, 1.0, axis=1)
    if huber_mm is not None:
        w = np.where(w > 0, np.minimum(1.0, huber_mm / np.maximum(d, 1e-12)), 0.0)
    return w
