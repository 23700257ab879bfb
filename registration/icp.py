"""Rigid ICP of points to a triangle mesh, with exact closest points on the triangles.

Closest points
--------------
:func:`closest_points` (:mod:`registration.closest`) returns the exact closest
point on the mesh, not on a sampled cloud: a compiled search of a
bounding-volume hierarchy of the faces, one call per iteration for all the
points of all the active sets.

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
import inspect
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from hrcore.geometry import kabsch
from registration.closest import (
    ClosestPoints,
    SurfaceIndex,
    _as_index,
    _as_points,
    closest_points,
    closest_points_on_triangles,
)

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


class IcpMethod(str, enum.Enum):
    """ICP error metric."""

    POINT_TO_POINT = "point_to_point"
    POINT_TO_PLANE = "point_to_plane"


@dataclass(frozen=True)
class IcpResult:
    """Result of :func:`icp`.

    Attributes
    ----------
    T_heart_from_probe : (4, 4) float64
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

    T_heart_from_probe: np.ndarray
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
        Initial ``T_heart_from_probe`` (the fiducial seed); identity by default.
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

    Returns
    -------
    IcpResult
    """
    surface = _as_index(surface)
    src = _as_points(points, at_least=3)
    method = IcpMethod(method)
    T = _check_options(src, T_init, trim_fraction, huber_mm, max_iterations)
    n = src.shape[0]
    fit = _icp_batch(src[None], surface, T[None], method=method, max_iterations=max_iterations, tol_mm=tol_mm,
                     tol_deg=tol_deg, tol_loss=tol_loss, n_keep=max(3, int(np.ceil((1.0 - trim_fraction) * n))),
                     huber_mm=huber_mm)
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
        T_heart_from_probe=T,
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
    T_heart_from_probe : (m, 4, 4) float64
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
    warm_start: bool = False,
    warm_stride: int = 10,
    signed: bool = False,
    **options,
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
    sets off the surface) the answer depends on the seed: the faceted loss
    has nearby local minima there (on the bench sweep at most 0.009 mm apart
    at the heart's centre but 0.13 deg in rotation, 0.09 deg even when both
    iterate to 1e-5 mm; :data:`registration.spatiotemporal.WARM_START`).

    Parameters
    ----------
    points : (m, n, 3) float, mm
        m source point sets (e.g. the predicted points at m phases).
    surface : SurfaceIndex or (vertices, faces)
    T_init : (4, 4) or (m, 4, 4) float, optional
        Seed of every registration, or one per set.
    warm_start : bool
        Seed each set by its registered neighbour (see above).
    warm_stride : int
        Sets registered from ``T_init`` when warm starting: every this many.
    signed : bool
        Signed distances: negative inside the surface (by the closest face's
        outward normal).
    **options
        The other keyword arguments of :func:`icp` (``method``,
        ``max_iterations``, the tolerances, ``trim_fraction``, ``huber_mm``),
        with its defaults.

    Returns
    -------
    T_heart_from_probe : (m, 4, 4) float64
    distances_mm : (m, n) float64
        Point-to-surface distance of every point at each solution.
    iterations : (m,) int64
    converged : (m,) bool
    """
    surface = _as_index(surface)
    bound = inspect.signature(icp).bind(points, surface, **options)
    bound.apply_defaults()
    kw = bound.arguments
    trim_fraction, huber_mm, max_iterations = kw["trim_fraction"], kw["huber_mm"], kw["max_iterations"]
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
    options = dict(method=IcpMethod(kw["method"]), max_iterations=max_iterations, tol_mm=kw["tol_mm"],
                   tol_deg=kw["tol_deg"], tol_loss=kw["tol_loss"], huber_mm=huber_mm,
                   n_keep=max(3, int(np.ceil((1.0 - trim_fraction) * n))))
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
        return kabsch(q, cp, weights=w)
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


def _icp_batch(src, surface, seeds, *, method, max_iterations, tol_mm, tol_deg, tol_loss, n_keep, huber_mm):
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
        cp = closest_points(surface, q.reshape(-1, 3))
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
