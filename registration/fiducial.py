"""Point-based rigid registration (fiducials): SVD with the reflection guard.

The least-squares rigid transform between corresponding point sets (Arun et al.
1987, Umeyama 1991) is found from the SVD of the cross-covariance; the sign of
the last singular direction is flipped when the best orthogonal matrix would be
a reflection, so a rotation is always returned.

Correspondence is by the documented order (docs/CONTRACTS.md, "Fiducial
order": rows superior to inferior, within a row patient right to left).  When the
fit in that order is poor (the touched fiducials were listed in another order)
:func:`register_fiducials` searches the assignment itself: hypotheses from
rotation-invariant distance signatures (Hungarian assignment,
:func:`scipy.optimize.linear_sum_assignment`) and from congruent triangles, each
refined by re-assignment after alignment, and keeps the best.  A configuration
with symmetries (the 3 x 3 grid has a 180 degree one) can admit several
assignments that fit equally well: the result says so (``ambiguous``).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial.distance import cdist

from hrcore.errors import HeartregError
from hrcore.geometry import apply_to_points, kabsch

__all__ = [
    "FiducialError",
    "FiducialRegistration",
    "rigid_fit",
    "register_fiducials",
]

#: Smallest ratio of the second to the first singular value of the centred
#: points: below it the points are (nearly) collinear and the rotation about
#: their line is undetermined.
COLLINEAR_RATIO = 1e-3
#: another assignment replaces the documented order only when it fits at least
#: this many times better (a wrong order of staples 40 mm apart fits tens of
#: times worse; a noisy right order and its mirror fit alike).
ORDER_MARGIN = 2.0


class FiducialError(HeartregError, ValueError):
    """Fiducial sets that cannot be registered (count mismatch, degenerate layout)."""


@dataclass(frozen=True)
class FiducialRegistration:
    """Result of a point-based rigid registration.

    Attributes
    ----------
    T_heart_from_probe : (4, 4) float64
        Maps source points onto target points.
    fre_rms_mm : float
        Fiducial registration error, RMS of the residuals, mm.
    residuals_mm : (n,) float64
        Distance of each transformed source point from its target, mm, in the
        order of the source points.
    order : (n,) int
        ``target[order[i]]`` corresponds to ``source[i]``; ``arange(n)`` when the
        given order was used.
    reordered : bool
        True when the correspondence was found by search rather than taken from
        the given order.
    ambiguous : bool
        True when another assignment, with a different transform, fits within
        ``max_fre_mm`` as well (a symmetric layout): the order cannot be told
        from geometry alone.
    """

    T_heart_from_probe: np.ndarray
    fre_rms_mm: float
    residuals_mm: np.ndarray
    order: np.ndarray
    reordered: bool
    ambiguous: bool = False


def _check_pair(source, target):
    source = np.asarray(source, dtype=float)
    target = np.asarray(target, dtype=float)
    if source.ndim != 2 or source.shape[1] != 3:
        raise ValueError(f"source must have shape (n, 3), got {source.shape}")
    if target.ndim != 2 or target.shape[1] != 3:
        raise ValueError(f"target must have shape (n, 3), got {target.shape}")
    if source.shape[0] != target.shape[0]:
        raise FiducialError(
            f"source has {source.shape[0]} points but target has {target.shape[0]}: "
            "every fiducial in the model must be touched exactly once"
        )
    if source.shape[0] < 3:
        raise FiducialError(f"at least 3 points are needed, got {source.shape[0]}")
    if not (np.all(np.isfinite(source)) and np.all(np.isfinite(target))):
        raise ValueError("source and target must be finite")
    return source, target


def collinear(points) -> tuple[float, float] | None:
    """The two largest singular values (mm) of ``points`` about their centre when they lie on a line (the second
    below :data:`COLLINEAR_RATIO` of the first), else None."""
    points = np.asarray(points, dtype=np.float64)
    s = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
    return (float(s[0]), float(s[1])) if s[0] == 0 or s[1] / s[0] < COLLINEAR_RATIO else None


def _check_not_collinear(points, name):
    if (s := collinear(points)) is not None:
        raise FiducialError(
            f"{name} points are collinear (singular values {s[0]:.3g}, {s[1]:.3g}): "
            "the rotation about their line is undetermined; use non-collinear fiducials"
        )


def rigid_fit(source, target, *, weights=None) -> np.ndarray:
    """Least-squares rigid transform mapping ``source[i]`` onto ``target[i]``.

    Parameters
    ----------
    source, target : (n, 3) float, mm
        Corresponding points, n >= 3, not collinear.
    weights : (n,) float, optional
        Non-negative weights, not all zero.

    Returns
    -------
    (4, 4) float64
        ``T_heart_from_probe`` minimising ``sum w_i |T s_i - t_i|^2``, with a
        proper rotation (det +1) even when the points are coplanar or noisy.

    Raises
    ------
    FiducialError
        Mismatched counts, fewer than 3 points, or collinear points.
    """
    source, target = _check_pair(source, target)
    _check_not_collinear(source, "source")
    _check_not_collinear(target, "target")
    if weights is not None:
        weights = np.asarray(weights, dtype=float)
        if weights.shape != (source.shape[0],):
            raise ValueError(f"weights must have shape ({source.shape[0]},), got {weights.shape}")
        if np.any(weights < 0) or not weights.sum() > 0:
            raise ValueError("weights must be non-negative and not all zero")
    return kabsch(source, target, weights=weights)


def _residuals(T, source, target):
    return np.linalg.norm(apply_to_points(T, source) - target, axis=1)


def _refine_assignment(source, target, order, n_rounds=5):
    """Alternate rigid fit and Hungarian re-assignment until the order is stable."""
    for _ in range(n_rounds):
        T = kabsch(source, target[order])
        moved = apply_to_points(T, source)
        _, new = linear_sum_assignment(cdist(moved, target, "sqeuclidean"))
        if np.array_equal(new, order):
            break
        order = new
    T = kabsch(source, target[order])
    return order, T, float(np.sqrt(np.mean(_residuals(T, source, target[order]) ** 2)))


def _candidate_orders(source, target, *, max_triples=2000):
    """Assignments from distance signatures and from congruent triangles."""
    ds, dt = cdist(source, source), cdist(target, target)
    sig_s, sig_t = np.sort(ds, axis=1), np.sort(dt, axis=1)
    _, order = linear_sum_assignment(cdist(sig_s, sig_t))
    yield order
    # anchor triangle: the source triple with the largest area
    n = source.shape[0]
    best, anchor = -1.0, None
    for i, j, k in itertools.combinations(range(n), 3):
        area = np.linalg.norm(np.cross(source[j] - source[i], source[k] - source[i]))
        if area > best:
            best, anchor = area, (i, j, k)
    i, j, k = anchor
    d_ij, d_ik, d_jk = ds[i, j], ds[i, k], ds[j, k]
    scale = max(d_ij, d_ik, d_jk)
    triples = []
    for a, b, c in itertools.permutations(range(n), 3):
        err = abs(dt[a, b] - d_ij) + abs(dt[a, c] - d_ik) + abs(dt[b, c] - d_jk)
        triples.append((err, a, b, c))
    triples.sort()
    tol = max(0.15 * scale, 3 * triples[0][0])
    for err, a, b, c in triples[:max_triples]:
        if err > tol:
            break
        T = kabsch(source[[i, j, k]], target[[a, b, c]])
        moved = apply_to_points(T, source)
        _, order = linear_sum_assignment(cdist(moved, target, "sqeuclidean"))
        yield order


def register_fiducials(
    source,
    target,
    *,
    max_fre_mm: float = 3.0,
    allow_reorder: bool = True,
) -> FiducialRegistration:
    """Rigid registration of fiducials, by the documented order or by search.

    Parameters
    ----------
    source : (n, 3) float, mm
        Fiducials in the source frame (e.g. touched with the tracked probe, probe
        frame).
    target : (n, 3) float, mm
        The same fiducials in the target frame (e.g. model, heart or patient
        frame), nominally in the same order.
    max_fre_mm : float, mm
        An FRE above this in the given order means "wrong order" and starts the
        assignment search (when ``allow_reorder``); also the FRE within which a
        second, different solution makes the result ``ambiguous``.
    allow_reorder : bool
        Search the assignment when the given order fits badly.

    Returns
    -------
    FiducialRegistration

    Raises
    ------
    FiducialError
        Different counts, fewer than 3 points, collinear points.

    Examples
    --------
    Nine staples on a 3 x 3 grid (rows 40 mm apart, columns 50 mm, a few mm of
    relief), moved by a known rigid transform: the registration recovers it.

    >>> import numpy as np
    >>> from scipy.spatial.transform import Rotation
    >>> from registration import register_fiducials, rotation_distance_deg
    >>> probe_mm = np.array([[x, y, 0.0] for y in (40, 0, -40) for x in (50, 0, -50)])
    >>> probe_mm[:, 2] = [0, 8, 3, 5, 12, 4, 1, 9, 2]
    >>> T_true = np.eye(4)
    >>> T_true[:3, :3] = Rotation.from_euler("z", 20, degrees=True).as_matrix()
    >>> T_true[:3, 3] = [10.0, -5.0, 2.0]
    >>> heart_mm = probe_mm @ T_true[:3, :3].T + T_true[:3, 3]
    >>> reg = register_fiducials(probe_mm, heart_mm)
    >>> print(f"FRE {reg.fre_rms_mm:.3f} mm, reordered {reg.reordered}, ambiguous {reg.ambiguous}")
    FRE 0.000 mm, reordered False, ambiguous False
    >>> print(f"{float(rotation_distance_deg(reg.T_heart_from_probe, T_true)):.3f} deg")
    0.000 deg
    >>> reg.T_heart_from_probe[:3, 3].round(3).tolist()
    [10.0, -5.0, 2.0]
    """
    source, target = _check_pair(source, target)
    _check_not_collinear(source, "source")
    _check_not_collinear(target, "target")
    if not max_fre_mm > 0:
        raise ValueError(f"max_fre_mm must be positive, got {max_fre_mm}")
    n = source.shape[0]
    identity = np.arange(n)
    T = kabsch(source, target)
    res = _residuals(T, source, target)
    fre = float(np.sqrt(np.mean(res**2)))
    if fre <= max_fre_mm or not allow_reorder:
        return FiducialRegistration(T, fre, res, identity, False, False)

    solutions = {tuple(identity): (fre, T)}
    for order in _candidate_orders(source, target):
        order, T_o, fre_o = _refine_assignment(source, target, order)
        key = tuple(int(x) for x in order)
        if key not in solutions:
            solutions[key] = (fre_o, T_o)
    ranked = sorted(solutions.items(), key=lambda kv: kv[1][0])
    if ranked[0][1][0] * ORDER_MARGIN >= fre:
        # no assignment fits clearly better than the documented order: a symmetric
        # layout (the 3 x 3 grid turned by 180 degrees) fits about as well as the
        # true one, so keep the order the user recorded and flag the ambiguity
        ambiguous = any(np.abs(T_o[:3, :3] - T[:3, :3]).max() > 1e-2 and f <= ORDER_MARGIN * fre
                        for _, (f, T_o) in ranked)
        return FiducialRegistration(T, fre, res, identity, False, bool(ambiguous))
    (key, (fre_best, T_best)) = ranked[0]
    order = np.asarray(key)
    ambiguous = any(
        f <= max_fre_mm and np.abs(T_o[:3, :3] - T_best[:3, :3]).max() > 1e-2
        for _, (f, T_o) in ranked[1:]
    )
    res = _residuals(T_best, source, target[order])
    return FiducialRegistration(
        T_best, float(fre_best), res, order, not np.array_equal(order, identity), bool(ambiguous)
    )
