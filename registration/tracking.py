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
query point: a point's distance from a triangle (or from a disk) is a convex
function whose gradient at ``q0`` is the unit vector from the closest point
to ``q0``, so ``d(q) >= d(q0) + g . (q - q0)``.  At a nearby ``q``
(``delta = |q - q0|``) the point's last closest point ``foot`` (any surface
point would do) is ``U = |q - foot|`` away; only the listed faces whose bound
at ``q`` is at most ``U`` can be nearer, and no unlisted one when
``U <= excluded - delta``.  A point moved sideways far from the surface (where
the distance changes by the square of the move) evaluates one or two faces
instead of the dozens whose sites lie within ``d + delta``.

The bounds hold everywhere, whoever asks: a search's row stays anchored at
its ``q0`` and serves the point's later positions and the same point of the
neighbouring sets alike (a face evaluated again gets the bound tight where it
was evaluated), so a query touches only the rows' few sites near their bound,
never copies them.
"""

from __future__ import annotations

import numpy as np

from registration.closest import (
    _SLACK_MM,
    ClosestPoints,
    SurfaceIndex,
    _face_d2,
    _finish,
    _lower_best,
    _search,
)

__all__ = ["PointSetTracker"]


class _Anchors:
    """What the fresh searches proved, one row per searched point (module docstring), growing.

    A row's bounds are affine lower bounds on its listed faces' distances,
    anchored at the point ``q0`` it was searched at: valid everywhere, so a row
    serves every point that comes near, its own later positions and the same
    point of the neighbouring sets alike, and a face evaluated again replaces
    its bound by the one tight where it was evaluated.
    """

    def __init__(self, width: int):
        self.size, self.width = 0, width
        self.q0, self.excluded = np.zeros((0, 3)), np.zeros(0)
        self.sites, self.lower, self.grad = np.zeros((0, width), dtype=np.int64), np.zeros((0, width)), \
            np.zeros((0, width, 3))

    def add(self, q0, excluded, sites, lower, grad) -> np.ndarray:
        """Append rows; their indices."""
        p = q0.shape[0]
        if self.size + p > self.q0.shape[0]:
            cap = max(2 * self.q0.shape[0], self.size + p)
            for name in ("q0", "excluded", "sites", "lower", "grad"):
                old = getattr(self, name)
                new = np.zeros((cap,) + old.shape[1:], dtype=old.dtype)
                new[: self.size] = old[: self.size]
                setattr(self, name, new)
        rows = np.arange(self.size, self.size + p)
        self.q0[rows], self.excluded[rows], self.sites[rows], self.lower[rows], self.grad[rows] = \
            q0, excluded, sites, lower, grad
        self.size += p
        return rows


def _unit(v, norm):
    """v / norm, zero where the norm is zero (a subgradient of the distance there)."""
    return np.divide(v, norm[..., None], out=np.zeros_like(v), where=norm[..., None] > 0)


def _searched(surface: SurfaceIndex, q, k, width, anchors: _Anchors):
    """A fresh search of the points q: (best, their new rows of ``anchors``).

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
    return best, anchors.add(q, excluded, sites, lower, _unit(offsets, lower))


def _reused(surface: SurfaceIndex, q, foot, rows, anchors: _Anchors):
    """The points q settled from the anchor ``rows`` where these prove it, ``foot`` a surface point each.

    Returns the settled points ``ok`` and their ``best`` (d2, face, key); the
    faces evaluated get their bounds tight at q.
    """
    delta = np.linalg.norm(q - anchors.q0[rows], axis=1)
    upper = np.linalg.norm(q - foot, axis=1) + _SLACK_MM
    ok = np.flatnonzero(upper <= anchors.excluded[rows] - delta)
    rows, q, delta, upper = rows[ok], q[ok], delta[ok], upper[ok]
    # |grad| <= 1: only the sites whose bound at q0 is within delta of the upper bound can be nearer
    r, c = np.nonzero(anchors.lower[rows] <= (upper + delta)[:, None])
    a = rows[r]
    step = q[r] - anchors.q0[a]
    near = anchors.lower[a, c] + np.einsum("pi,pi->p", anchors.grad[a, c], step) <= upper[r]
    r, c, a, step = r[near], c[near], a[near], step[near]
    sites = anchors.sites[a, c]
    faces = surface._site_face[sites]
    d2, offsets = _face_d2(surface, q, r, faces, offsets=True)
    d = np.sqrt(d2)
    grad = _unit(offsets, d)
    anchors.lower[a, c] = d - np.einsum("pi,pi->p", grad, step)  # the bound tight at q, anchored at q0
    anchors.grad[a, c] = grad
    best = (np.full(ok.size, np.inf), np.zeros(ok.size, dtype=np.int64), np.full(ok.size, np.inf))
    _lower_best(best, r, faces, d2, np.linalg.norm(surface.tree.data[sites] - q[r], axis=1))
    return ok, best


class PointSetTracker:
    """Exact closest points of m point sets of n points each, queried again as they move.

    Each point keeps the anchor row of its last answer and its closest point
    (module docstring).  A query first settles the points their rows prove;
    of the others it searches afresh (:func:`registration.closest.closest_points`'
    search) in every ``stride``-th active set, and settles the rest in waves
    outwards from those sets, each point from the row and the closest point of
    the same point of the neighbouring set just settled, searching afresh
    where that proves nothing.

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
        self._stride = stride  # the current stride: widened while the waves settle every set
        self.width = int(min(k, width, surface._site_face.shape[0]))
        self.anchors = _Anchors(self.width)
        self.row = np.full(m * n, -1, dtype=np.int64)  # each slot's anchor row; -1: none yet
        self.foot = np.zeros((m * n, 3))  # each slot's last closest point

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
        fresh = np.unique(np.r_[np.arange(0, a, self._stride), a - 1])
        pos = np.arange(a)
        j = np.clip(np.searchsorted(fresh, pos), 1, fresh.size - 1) if fresh.size > 1 else np.zeros(a, dtype=int)
        nearest = np.where(np.abs(pos - fresh[j - 1]) <= np.abs(pos - fresh[j]), fresh[j - 1], fresh[j])
        wave = np.abs(pos - nearest)
        donor = pos - np.sign(pos - nearest)
        todo_wave = wave[todo // n]
        tried = failed = 0  # points of the waves, and those their neighbours did not settle
        for w in range(int(todo_wave.max()) + 1 if todo.size else 0):
            rows = todo[todo_wave == w]
            if w > 0 and rows.size:
                tried += rows.size
                rows = self._reuse(out, q, rows, slots[donor[rows // n] * n + rows % n], slots[rows])
                failed += rows.size
            if rows.size:
                best, found = _searched(self.surface, q[rows], self.k, self.width, self.anchors)
                self._settle(out, q, rows, best[1], found, slots[rows])
        wide = failed <= 0.01 * tried
        self._stride = min(4 * self.stride, 2 * self._stride) if wide else max(self.stride, self._stride // 2)
        return out

    def _settle(self, out, q, rows, face, anchor_rows, dst):
        """The answers of ``rows`` into ``out``; their anchor rows and closest points into slots ``dst``."""
        cp = _finish(self.surface, q[rows], face)
        out.points[rows], out.distances_mm[rows], out.face_index[rows], out.normals[rows] = \
            cp.points, cp.distances_mm, cp.face_index, cp.normals
        self.row[dst], self.foot[dst] = anchor_rows, cp.points

    def _reuse(self, out, q, rows, src, dst):
        """Settle ``rows`` from the anchor rows and closest points of slots ``src`` into ``dst``; the rows left."""
        anchor = self.row[src]
        has = np.flatnonzero(anchor >= 0)
        ok, best = _reused(self.surface, q[rows[has]], self.foot[src[has]], anchor[has], self.anchors)
        done = has[ok]
        self._settle(out, q, rows[done], best[1], anchor[done], dst[done])
        left = np.ones(rows.size, dtype=bool)
        left[done] = False
        return rows[left]
