"""Rigid ICP of points to a triangle mesh, with exact closest points on the triangles.

Closest points
--------------
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

ICP
---
Point-to-point (closed-form SVD step) and point-to-plane (Gauss-Newton on the
linearised rotation, using the closest faces' normals) variants, with optional
trimming (keep the best fraction) and Huber weights; one implementation, run
on many point sets at once (a phase sweep makes one closest-point query per
iteration for all its phases).  It stops on a small step or on a loss that no
longer falls (:func:`icp`), keeping the best iterate.  Sliding along a surface
with a symmetry (sphere, cylinder, a flat patch) leaves directions of the rigid
motion undetermined: the result reports the eigenvalues of the point-to-plane
normal matrix at the solution (rotations scaled by the points' RMS radius so
all six are in mm^2 per point), its condition number and the weakest
direction, and flags ``degenerate`` when the ratio of smallest to largest is
below ``degeneracy_ratio``.
"""

from __future__ import annotations

import enum
import itertools
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

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
    "kabsch_batch",
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
        # each site's own radius: every point of its (sub-)triangle lies within it
        self._site_radius = (radii / m)[self._site_face]
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


def _face_d2(surface, q, rows, faces):
    """Squared distance of q[rows] to faces (pairs), (p,) float64; NaN (a degenerate face) as inf."""
    a, ab, ac = surface._a[faces], surface._ab[faces], surface._ac[faces]
    qr = q[rows]
    v, w = _closest_barycentric(qr, a, ab, ac, surface._dots[faces])
    diff = qr - a - v[:, None] * ab - w[:, None] * ac
    d2 = np.einsum("ij,ij->i", diff, diff)
    return np.where(np.isnan(d2), np.inf, d2)


def _improve(best_d2, best_face, surface, q, rows, sites, site_dist):
    """Lower ``best_d2`` / ``best_face`` in place with the candidate sites (pairs, rows sorted).

    A face can hold a point nearer than the current best only if one of its
    sites lies within the best distance plus that site's radius; the others
    are skipped unevaluated.
    """
    keep = site_dist - surface._site_radius[sites] <= np.sqrt(best_d2[rows])
    rows, faces = rows[keep], surface._site_face[sites[keep]]
    if rows.size == 0:
        return
    d2 = _face_d2(surface, q, rows, faces)
    starts = np.flatnonzero(np.r_[True, rows[1:] != rows[:-1]])
    low = np.minimum.reduceat(d2, starts)
    seg = np.repeat(np.arange(starts.size), np.diff(np.r_[starts, rows.size]))
    hit = np.flatnonzero(d2 == low[seg])
    hit = hit[np.r_[True, seg[hit][1:] != seg[hit][:-1]]]  # the first minimum of each row
    r = rows[hit]
    better = d2[hit] < best_d2[r]
    best_d2[r[better]], best_face[r[better]] = d2[hit][better], faces[hit][better]


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
    q = np.asarray(points, dtype=float)
    if q.ndim != 2 or q.shape[1] != 3:
        raise ValueError(f"points must have shape (n, 3), got {q.shape}")
    if not np.all(np.isfinite(q)):
        raise ValueError("points must be finite")
    if k < 1:
        raise ValueError(f"k must be >= 1, got {k}")
    n = q.shape[0]
    n_sites = surface._site_face.shape[0]
    kc = int(min(k, n_sites))
    dist_s, idx = surface.tree.query(q, k=kc, workers=-1)
    dist_s, idx = dist_s.reshape(n, kc), idx.reshape(n, kc)
    rows = np.arange(n)
    best_face = surface._site_face[idx[:, 0]]
    best_d2 = _face_d2(surface, q, rows, best_face)
    rr = np.repeat(rows, kc - 1)
    _improve(best_d2, best_face, surface, q, rr, idx[:, 1:].ravel(), dist_s[:, 1:].ravel())
    # faces without a site among the kc nearest are at least (kc-th site distance - r) away
    if kc < n_sites:
        unproven = np.flatnonzero(np.sqrt(best_d2) > dist_s[:, -1] - surface.site_radius_mm)
        if unproven.size:
            radius = np.sqrt(best_d2[unproven]) + surface.site_radius_mm
            lists = surface.tree.query_ball_point(q[unproven], np.where(np.isfinite(radius), radius, np.inf),
                                                  workers=-1, return_sorted=False)
            lengths = np.fromiter((len(x) for x in lists), dtype=np.int64, count=len(lists))
            sites = np.fromiter(itertools.chain.from_iterable(lists), dtype=np.int64, count=int(lengths.sum()))
            rr = np.repeat(unproven, lengths)
            _improve(best_d2, best_face, surface, q, rr, sites,
                     np.linalg.norm(surface.tree.data[sites] - q[rr], axis=1))
    a, ab, ac = surface._a[best_face], surface._ab[best_face], surface._ac[best_face]
    v, w = _closest_barycentric(q, a, ab, ac, surface._dots[best_face])
    cp = a + v[:, None] * ab + w[:, None] * ac
    return ClosestPoints(cp, np.linalg.norm(q - cp, axis=1), best_face, surface.normals[best_face])


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
        True when the iteration met one of :func:`icp`'s criteria (a step below
        ``tol_mm`` and ``tol_deg``, or a loss no longer falling by ``tol_loss``)
        within ``max_iterations``.
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


#: ICP stops when a step lowers its loss by less than this fraction (``tol_loss``).
TOL_LOSS = 1e-4


def kabsch_batch(source, target, weights=None) -> np.ndarray:
    """Rigid ``T`` (b, 4, 4) minimising ``sum_k w_k |T source_k - target_k|^2`` per set.

    Parameters
    ----------
    source, target : (b, k, 3) float, mm
        Corresponding points of b sets.
    weights : (b, k) float, optional
        Non-negative weights (equal by default).

    Returns
    -------
    (b, 4, 4) float64
    """
    source = np.asarray(source, dtype=float)
    target = np.asarray(target, dtype=float)
    w = np.ones(source.shape[:2]) if weights is None else np.asarray(weights, dtype=float)
    w = w / w.sum(axis=1, keepdims=True)
    cs, ct = np.einsum("bk,bki->bi", w, source), np.einsum("bk,bki->bi", w, target)
    H = np.einsum("bk,bki,bkj->bij", w, source - cs[:, None], target - ct[:, None])
    U, _, Vt = np.linalg.svd(H)
    V, Ut = np.swapaxes(Vt, 1, 2), np.swapaxes(U, 1, 2)
    d = np.sign(np.linalg.det(V @ Ut))
    d[d == 0] = 1.0
    R = (V * np.concatenate([np.ones((d.size, 2)), d[:, None]], axis=1)[:, None, :]) @ Ut
    T = np.zeros(source.shape[:1] + (4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = ct - np.einsum("bij,bj->bi", R, cs)
    T[:, 3, 3] = 1.0
    return T


def _plane_jacobian(q, normals, centre, scale):
    """Point-to-plane Jacobian (a, n, 6): rotation about ``centre`` (scaled by ``scale``), translation."""
    return np.concatenate([np.cross(q - centre[:, None], normals) / scale[:, None, None], normals], axis=2)


def _check_options(src, T_init, trim_fraction, huber_mm, max_iterations) -> np.ndarray:
    """Validate the options shared by :func:`icp` and :func:`icp_sweep`; return T_init."""
    if not np.all(np.isfinite(src)):
        raise ValueError("points must be finite")
    T = np.eye(4) if T_init is None else np.array(T_init, dtype=float)
    if T.shape != (4, 4):
        raise ValueError(f"T_init must have shape (4, 4), got {T.shape}")
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
    tol_loss: float = TOL_LOSS,
    trim_fraction: float = 0.0,
    huber_mm: float | None = None,
    degeneracy_ratio: float = 1e-3,
    k: int = 24,
) -> IcpResult:
    """Rigidly register points to a triangle mesh.

    Each iteration finds the exact closest points, then takes one step: the
    linearised point-to-plane least-squares step (Gauss-Newton) or the
    point-to-point SVD step.  The iteration has *converged* when a step moves
    the points' centroid less than ``tol_mm`` and rotates less than
    ``tol_deg``, or when the loss (half the sum of squared distances over the
    kept points, Huber's with ``huber_mm``) falls by less than the fraction
    ``tol_loss``: on a faceted mesh, with the points off the surface (the
    wrong phase of a sweep), the step can keep rotating the points by a
    tenth of a degree along a weakly constrained direction while the loss
    changes in its fifth digit; the minimum is then as sharp as the facets
    allow.  A step that raises the loss is halved once (back towards the best
    iterate); the best iterate is returned.  ``max_iterations`` bounds the
    steps: a registration still improving then returns with
    ``converged=False``.

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
        Most steps (``heartreg register --icp-max-iterations``).
    tol_mm, tol_deg : float, mm and degrees
        Converged when one step moves the points' centroid less than ``tol_mm``
        and rotates less than ``tol_deg``.
    tol_loss : float
        Converged when one step lowers the loss by less than this fraction.
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
    fit = _icp_batch(src[None], surface, T[None], method=method, max_iterations=max_iterations, tol_mm=tol_mm,
                     tol_deg=tol_deg, tol_loss=tol_loss, n_keep=max(3, int(np.ceil((1.0 - trim_fraction) * n))),
                     huber_mm=huber_mm, k=k)
    T = fit.T[0]
    d, w = fit.distances_mm[0], fit.weights[0]
    sel = w > 0
    centre_src = src.mean(axis=0)
    scale = float(np.sqrt(np.mean(np.sum((src - centre_src) ** 2, axis=1)))) or 1.0
    q = src @ T[:3, :3].T + T[:3, 3]
    J = _plane_jacobian(q[None, sel], fit.normals[0][None, sel], (T[:3, :3] @ centre_src + T[:3, 3])[None],
                        np.array([scale]))[0]
    A = (J * w[sel, None]).T @ J / w[sel].sum()
    evals, evecs = np.linalg.eigh(A)
    evals = np.clip(evals, 0.0, None)
    cond = float(evals[-1] / evals[0]) if evals[0] > 0 else float("inf")
    return IcpResult(
        T_target_from_source=T,
        rms_mm=float(np.sqrt(np.mean(d**2))),
        rms_inlier_mm=float(np.sqrt(np.mean(d[sel] ** 2))),
        distances_mm=d,
        closest_points=fit.closest_mm[0],
        inliers=sel,
        iterations=int(fit.iterations[0]),
        converged=bool(fit.converged[0]),
        method=method.value,
        hessian_eigenvalues=evals,
        weakest_direction=evecs[:, 0],
        condition_number=cond,
        degenerate=bool(evals[0] < degeneracy_ratio * evals[-1]),
    )


def icp_sweep(points, surface, **options):
    """:func:`icp` of many point sets at once, all from one seed.

    See :func:`icp_sweep_distances` for the parameters.

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
    method: IcpMethod | str = IcpMethod.POINT_TO_PLANE,
    max_iterations: int = 50,
    tol_mm: float = 1e-3,
    tol_deg: float = 1e-3,
    tol_loss: float = TOL_LOSS,
    trim_fraction: float = 0.0,
    huber_mm: float | None = None,
    k: int = 24,
    warm_start: bool = False,
    warm_stride: int = 10,
    signed: bool = False,
):
    """:func:`icp` of many point sets at once.

    The same iteration as :func:`icp` (one implementation), run on all ``m``
    point sets together so that each iteration makes one closest-point query
    for all active sets.

    With ``warm_start`` the sets are taken as ordered samples of a smooth
    family (the predicted points along a phase sweep): every ``warm_stride``-th
    set is registered from ``T_init``, then the others in waves outwards from
    those, each seeded by its already registered neighbour.  Each set iterates
    to the same tolerances, but where the loss is flat along a direction (the
    sets off the surface) the answer depends on the seed by up to the
    tolerances' effect there (hundredths of a mm at the heart's centre).

    Parameters
    ----------
    points : (m, n, 3) float, mm
        m source point sets (e.g. the predicted points at m phases).
    surface : SurfaceIndex or (vertices, faces)
    T_init : (4, 4) or (m, 4, 4) float, optional
        Seed of every registration, or one per set.
    method, max_iterations, tol_mm, tol_deg, tol_loss, trim_fraction, huber_mm, k
        As for :func:`icp`.
    warm_start : bool
        Seed each set by its registered neighbour (see above).
    warm_stride : int
        Sets registered from ``T_init`` when warm starting: every this many.
    signed : bool
        Signed distances: negative inside the surface (by the closest face's
        outward normal).

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
    options = dict(method=IcpMethod(method), max_iterations=max_iterations, tol_mm=tol_mm, tol_deg=tol_deg,
                   tol_loss=tol_loss, n_keep=max(3, int(np.ceil((1.0 - trim_fraction) * n))), huber_mm=huber_mm,
                   k=k)
    def distances(fit, points):
        if not signed:
            return fit.distances_mm
        q = np.einsum("aij,anj->ani", fit.T[:, :3, :3], points) + fit.T[:, None, :3, 3]
        return np.where(np.einsum("ani,ani->an", q - fit.closest_mm, fit.normals) < 0, -1.0, 1.0) * fit.distances_mm

    if not warm_start or m <= 2:
        fit = _icp_batch(src, surface, seeds, **options)
        return fit.T, distances(fit, src), fit.iterations, fit.converged
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
        fit = _icp_batch(src[wave], surface, seed, **options)
        T[wave], d[wave], iterations[wave], converged[wave] = fit.T, distances(fit, src[wave]), fit.iterations, fit.converged
        done[wave] = True
        nxt = {}
        for i in wave:
            for j in (i - 1, i + 1):
                if 0 <= j < m and not done[j] and j not in nxt:
                    nxt[int(j)] = int(i)
        source_of = nxt
        wave = np.array(sorted(nxt), dtype=np.int64)
    return T, d, iterations, converged


@dataclass(frozen=True)
class _BatchFit:
    """The best iterate of each set of :func:`_icp_batch`, with its closest points."""

    T: np.ndarray  # (m, 4, 4)
    distances_mm: np.ndarray  # (m, n)
    closest_mm: np.ndarray  # (m, n, 3)
    normals: np.ndarray  # (m, n, 3)
    weights: np.ndarray  # (m, n)
    iterations: np.ndarray  # (m,)
    converged: np.ndarray  # (m,)


def _step(method, q, cp, normals, w, centre, scale):
    """One ICP step (a, 4, 4) from the closest points: point-to-plane Gauss-Newton or point-to-point SVD."""
    if method is IcpMethod.POINT_TO_POINT:
        return kabsch_batch(q, cp, w)
    J = _plane_jacobian(q, normals, centre, scale)
    Jw = J * w[:, :, None]
    A = np.einsum("ani,anj->aij", Jw, J)
    b = np.einsum("ani,an->ai", Jw, np.einsum("ani,ani->an", q - cp, normals))
    x = -np.einsum("aij,aj->ai", np.linalg.pinv(A, rcond=1e-12), b)
    R = Rotation.from_rotvec(x[:, :3] / scale[:, None]).as_matrix()
    step = np.zeros((q.shape[0], 4, 4))
    step[:, :3, :3], step[:, :3, 3], step[:, 3, 3] = R, centre - np.einsum("aij,aj->ai", R, centre) + x[:, 3:], 1.0
    return step


def _half_step(T, T_best, centre):
    """Halfway from ``T_best`` to ``T`` (a, 4, 4): half the rotation about ``centre`` and half its shift."""
    S = T @ np.linalg.inv(T_best)
    R = Rotation.from_rotvec(Rotation.from_matrix(S[:, :3, :3]).as_rotvec() / 2).as_matrix()
    shift = np.einsum("aij,aj->ai", S[:, :3, :3], centre) + S[:, :3, 3] - centre
    half = np.zeros_like(S)
    half[:, :3, :3], half[:, :3, 3], half[:, 3, 3] = R, centre + shift / 2 - np.einsum("aij,aj->ai", R, centre), 1.0
    return half @ T_best


def _loss(d, w, huber_mm):
    """Half the sum of squared distances of the kept points (Huber's loss with ``huber_mm``), per row."""
    rho = 0.5 * d**2 if huber_mm is None else np.where(d <= huber_mm, 0.5 * d**2, huber_mm * (d - huber_mm / 2))
    return np.where(w > 0, rho, 0.0).sum(axis=1)


def _icp_batch(src, surface, seeds, *, method, max_iterations, tol_mm, tol_deg, tol_loss, n_keep, huber_mm, k):
    """The ICP iteration of :func:`icp` on m sets at once, one seed per set (criteria in ``icp``)."""
    m, n, _ = src.shape
    centre_src = src.mean(axis=1)  # (m, 3)
    scale = np.sqrt(np.mean(np.sum((src - centre_src[:, None]) ** 2, axis=2), axis=1))
    scale[scale == 0] = 1.0
    tol_rad = np.radians(tol_deg)

    T = np.array(seeds, dtype=float)
    best = _BatchFit(T.copy(), np.zeros((m, n)), np.zeros((m, n, 3)), np.zeros((m, n, 3)), np.zeros((m, n)),
                     np.zeros(m, dtype=np.int64), np.zeros(m, dtype=bool))
    best_loss = np.full(m, np.inf)
    small = np.zeros(m, dtype=bool)  # the step to T was below tol_mm and tol_deg
    halved = np.zeros(m, dtype=bool)  # T is a halved step back towards the best
    active = np.arange(m)
    while active.size:
        a = active
        q = np.einsum("aij,anj->ani", T[a, :3, :3], src[a]) + T[a, None, :3, 3]
        cp = closest_points(surface, q.reshape(-1, 3), k=k)
        d = cp.distances_mm.reshape(len(a), n)
        w = _weights_batch(d, n_keep, huber_mm)
        loss = _loss(d, w, huber_mm)
        improved = loss < best_loss[a]
        enough = loss < best_loss[a] * (1.0 - tol_loss)
        i = a[improved]
        best.T[i], best.distances_mm[i], best.weights[i] = T[i], d[improved], w[improved]
        best.closest_mm[i] = cp.points.reshape(len(a), n, 3)[improved]
        best.normals[i] = cp.normals.reshape(len(a), n, 3)[improved]
        best_loss[i] = loss[improved]
        # converged: a small step, a loss that no longer falls, or one that rose after a halved step
        done = small[a] | (improved & ~enough) | (~improved & halved[a])
        best.converged[a[done]] = True
        go = ~done & (best.iterations[a] < max_iterations)
        back = go & ~improved  # the step raised the loss: halve it
        if back.any():
            b = a[back]
            T[b] = _half_step(T[b], best.T[b], np.einsum("aij,aj->ai", best.T[b, :3, :3], centre_src[b])
                              + best.T[b, :3, 3])
            halved[b], small[b] = True, False
        fwd = go & improved
        if fwd.any():
            f = a[fwd]
            centre = np.einsum("aij,aj->ai", T[f, :3, :3], centre_src[f]) + T[f, :3, 3]
            step = _step(method, q[fwd], cp.points.reshape(len(a), n, 3)[fwd],
                         cp.normals.reshape(len(a), n, 3)[fwd], w[fwd], centre, scale[f])
            T[f] = step @ T[f]
            moved = np.linalg.norm(np.einsum("aij,aj->ai", step[:, :3, :3], centre) + step[:, :3, 3] - centre, axis=1)
            small[f] = (moved < tol_mm) & (Rotation.from_matrix(step[:, :3, :3]).magnitude() < tol_rad)
            halved[f] = False
        best.iterations[a[go]] += 1
        active = a[go]
    return best


def _weights_batch(d, n_keep, huber_mm):
    """Weights of each row of d (m, n): 1 on the ``n_keep`` nearest (trimming), Huber's on those."""
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
