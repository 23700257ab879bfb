"""Exact closest points of point sets that move a little between queries (the ICP of a sweep).

The ICP of a phase sweep asks for the closest surface points of the same
points again and again: each time every set (phase) has moved by one ICP
step, and the sets of neighbouring phases lie close to each other (a few
tenths of a mm apart).  :class:`PointSetTracker` answers these queries with
the exact answer of :func:`registration.closest.closest_points` (the same
face, the same point, the same tie rule) while evaluating few faces.

What a search proved
--------------------
A search at ``q0`` lists search sites, each with a lower bound on its face's
distance from ``q0`` (the exact distance where the face was evaluated, else
the distance from the disk around the site in the face's plane that holds
the site's part of the face), and proves every face with no listed
site at least ``excluded`` away.  Each bound is an affine function of the
query point: a point's distance from a triangle (or from a site's ball) is a
convex function (so is its distance from a disk) whose gradient at ``q0`` is
the unit vector from the closest point to ``q0``, so ``d(q) >= d(q0) + g . (q - q0)``.  At a nearby ``q``
(``delta = |q - q0|``) the closest point found at ``q0`` is at most
``U = |q - foot|`` away; only the listed faces whose bound at ``q`` is at
most ``U`` can be nearer, and no unlisted one when ``U <= excluded - delta``.
A point moved sideways far from the surface (where the distance changes by
the square of the move) evaluates one or two faces instead of the dozens
whose sites lie within ``d + delta``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from registration.closest import _SLACK_MM, ClosestPoints, SurfaceIndex, _face_d2, _finish, _lower_best, _search

__all__ = ["PointSetTracker"]


@dataclass
class _Bounds:
    """What searches proved about each of p points (module docstring)."""

    q0: np.ndarray  # (p, 3) mm, where the bounds were taken
    foot: np.ndarray  # (p, 3) mm, the closest surface point of q0
    excluded: np.ndarray  # (p,) mm; -inf: nothing proven
    sites: np.ndarray  # (p, w) listed search sites
    lower: np.ndarray  # (p, w) mm, bound on the site's face at q0
    grad: np.ndarray  # (p, w, 3) its gradient

    def take(self, rows) -> "_Bounds":
        return _Bounds(self.q0[rows], self.foot[rows], self.excluded[rows], self.sites[rows], self.lower[rows],
                       self.grad[rows])

    def put(self, rows, other: "_Bounds") -> None:
        self.q0[rows], self.foot[rows], self.excluded[rows] = other.q0, other.foot, other.excluded
        self.sites[rows], self.lower[rows], self.grad[rows] = other.sites, other.lower, other.grad


def _unit(v, norm):
    """v / norm, zero where the norm is zero (a subgradient of the distance there)."""
    return np.divide(v, norm[..., None], out=np.zeros_like(v), where=norm[..., None] > 0)


def _searched(surface: SurfaceIndex, q, k, width):
    """A fresh search of the points q: (best, _Bounds without the foot).

    Of the ``k`` listed sites the ``width`` with the lowest bounds are kept;
    the others only lower ``excluded`` to their lowest bound.
    """
    best, proof = _search(surface, q, k)
    sites, lower, excluded = proof["sites"], proof["lower"], proof["excluded"]
    offsets = proof["offsets"]
    if sites.shape[1] > width:
        order = np.argpartition(lower, width, axis=1)
        keep, drop = order[:, :width], order[:, width:]
        excluded = np.minimum(excluded, np.take_along_axis(lower, drop, axis=1).min(axis=1))
        sites, lower = (np.take_along_axis(x, keep, axis=1) for x in (sites, lower))
        offsets = np.take_along_axis(offsets, keep[:, :, None], axis=1)
    grad = _unit(offsets, lower)
    return best, _Bounds(q.copy(), np.zeros_like(q), excluded, sites, lower, grad)


def _reused(surface: SurfaceIndex, q, near: _Bounds):
    """The points q settled from earlier bounds where these prove it.

    Returns the settled rows ``ok``, their ``best`` (d2, face, key) and the
    bounds at q (without the foot).
    """
    step = q - near.q0
    delta = np.linalg.norm(step, axis=1)
    upper = np.linalg.norm(q - near.foot, axis=1)
    ok = np.flatnonzero(upper + _SLACK_MM <= near.excluded - delta)
    near, step, delta, upper, q = near.take(ok), step[ok], delta[ok], upper[ok], q[ok]
    lower = near.lower + np.einsum("pwi,pi->pw", near.grad, step)
    r, c = np.nonzero(lower <= (upper + _SLACK_MM)[:, None])
    sites = near.sites[r, c]
    faces = surface._site_face[sites]
    d2, offsets = _face_d2(surface, q, r, faces, offsets=True)
    d = np.sqrt(d2)
    lower[r, c] = d
    near.grad[r, c] = _unit(offsets, d)
    best = (np.full(ok.size, np.inf), np.zeros(ok.size, dtype=np.int64), np.full(ok.size, np.inf))
    _lower_best(best, r, faces, d2, np.linalg.norm(surface.tree.data[sites] - q[r], axis=1))
    return ok, best, _Bounds(q, near.foot, near.excluded - delta, near.sites, lower, near.grad)


class PointSetTracker:
    """Exact closest points of m point sets of n points each, queried again as they move.

    Each point keeps the bounds of its last answer (module docstring).  A
    query first settles the points those bounds prove; of the others it
    searches afresh (:func:`registration.closest.closest_points`' search) in
    every ``stride``-th active set, and settles the rest in waves outwards
    from those sets, each point from the same point of the neighbouring set
    just settled, searching afresh where that proves nothing.

    Parameters
    ----------
    surface : SurfaceIndex
    m, n : int
        Sets and points per set.
    k : int
        Nearest search sites of a fresh search: enough for the bounds to
        settle the neighbouring sets too (points 10 mm off the surface need
        about a hundred).
    stride : int
        Sets searched afresh: every this many of those needing it.
    width : int
        Listed sites kept per point (those with the lowest bounds).
    """

    def __init__(self, surface: SurfaceIndex, m: int, n: int, *, k: int = 128, stride: int = 8, width: int = 64):
        self.surface, self.n, self.k, self.stride = surface, n, k, stride
        self.width = w = int(min(k, width, surface._site_face.shape[0]))
        self.known = _Bounds(np.zeros((m * n, 3)), np.zeros((m * n, 3)), np.full(m * n, -np.inf),
                             np.zeros((m * n, w), dtype=np.int64), np.zeros((m * n, w)), np.zeros((m * n, w, 3)))

    def query(self, sets, q) -> ClosestPoints:
        """Closest points of ``q`` (a, n, 3), the points of the sets ``sets`` (a,), in that order."""
        n = self.n
        sets = np.asarray(sets, dtype=np.int64)
        q = np.asarray(q, dtype=float).reshape(-1, 3)
        slots = (sets[:, None] * n + np.arange(n)).ravel()
        out = ClosestPoints(np.zeros_like(q), np.zeros(q.shape[0]), np.zeros(q.shape[0], dtype=np.int64),
                            np.zeros_like(q))
        todo = self._reuse(out, q, np.arange(q.shape[0]), slots, slots)
        # waves outwards from every stride-th set: each set from its neighbour towards the nearest fresh one
        a = sets.size
        fresh = np.unique(np.r_[np.arange(0, a, self.stride), a - 1])
        pos = np.arange(a)
        j = np.clip(np.searchsorted(fresh, pos), 1, fresh.size - 1) if fresh.size > 1 else np.zeros(a, dtype=int)
        nearest = np.where(np.abs(pos - fresh[j - 1]) <= np.abs(pos - fresh[j]), fresh[j - 1], fresh[j])
        wave = np.abs(pos - nearest)
        donor = pos - np.sign(pos - nearest)
        todo_wave = wave[todo // n]
        for w in range(int(todo_wave.max()) + 1 if todo.size else 0):
            rows = todo[todo_wave == w]
            if w > 0 and rows.size:
                rows = self._reuse(out, q, rows, slots[donor[rows // n] * n + rows % n], slots[rows])
            if rows.size:
                best, found = _searched(self.surface, q[rows], self.k, self.width)
                self._settle(out, q, rows, best[1], found, slots[rows])
        return out

    def _settle(self, out, q, rows, face, found, dst):
        """The answers of ``rows`` into ``out``; their bounds, with the closest points, into ``dst``."""
        cp = _finish(self.surface, q[rows], face)
        out.points[rows], out.distances_mm[rows], out.face_index[rows], out.normals[rows] = \
            cp.points, cp.distances_mm, cp.face_index, cp.normals
        found.foot = cp.points
        self.known.put(dst, found)

    def _reuse(self, out, q, rows, src, dst):
        """Settle ``rows`` from the bounds of slots ``src``, kept in ``dst``; the rows left."""
        ok, best, found = _reused(self.surface, q[rows], self.known.take(src))
        self._settle(out, q, rows[ok], best[1], found, dst[ok])
        left = np.ones(rows.size, dtype=bool)
        left[ok] = False
        return rows[left]
