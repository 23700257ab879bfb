"""The compiled loop of :func:`registration.closest.closest_points`: a depth-first search of the
faces' bounding-volume hierarchy (:func:`registration.closest._build_bvh`) for each point.

Its own module so that numba is imported on the first search only
(:func:`registration.closest._nearest`).  ``cache=True``: the first search in
a process loads the compiled code from ``__pycache__`` next to this file
(about 0.2 s, numba's own start-up); the very first compiles it (~1.5 s).
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["nearest_faces"]

#: Slack (mm) on the pruning bound: a box as near as the best face within
#: rounding is opened, so a face tied with the best is always evaluated.
_SLACK_MM = 1e-9


@numba.njit(cache=True, inline="always")
def _box_d2(lo, hi, node, x, y, z):
    """Squared distance of (x, y, z) from the node's box."""
    dx = max(lo[node, 0] - x, 0.0, x - hi[node, 0])
    dy = max(lo[node, 1] - y, 0.0, y - hi[node, 1])
    dz = max(lo[node, 2] - z, 0.0, z - hi[node, 2])
    return dx * dx + dy * dy + dz * dz


@numba.njit(cache=True, inline="always")
def _face_d2(a, ab, ac, dots, f, x, y, z):
    """Squared distance of (x, y, z) from face f (inf for a degenerate face), and the closest point's (v, w).

    Ericson's regions in the same operations as
    :func:`registration.closest._closest_barycentric`, so that the distances
    (and their ties) are those of the vectorised code bit for bit.  The
    closest point is ``a + v ab + w ac``.
    """
    p0, p1, p2 = x - a[f, 0], y - a[f, 1], z - a[f, 2]
    d1 = (ab[f, 0] * p0 + ab[f, 2] * p2) + ab[f, 1] * p1  # numpy's einsum sums three products in this order
    d2 = (ac[f, 0] * p0 + ac[f, 2] * p2) + ac[f, 1] * p1
    ab_ab, ab_ac, ac_ac = dots[f, 0], dots[f, 1], dots[f, 2]
    d3, d4, d5, d6 = d1 - ab_ab, d2 - ab_ac, d1 - ab_ac, d2 - ac_ac
    if d1 <= 0 and d2 <= 0:
        v, w = 0.0, 0.0
    elif d3 >= 0 and d4 <= d3:
        v, w = 1.0, 0.0
    else:
        va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
        if vc <= 0 and d1 >= 0 and d3 <= 0:
            e = d1 - d3
            v, w = d1 / (e if e != 0 else 1.0), 0.0
        elif d6 >= 0 and d5 <= d6:
            v, w = 0.0, 1.0
        elif vb <= 0 and d2 >= 0 and d6 <= 0:
            e = d2 - d6
            v, w = 0.0, d2 / (e if e != 0 else 1.0)
        elif va <= 0 and d4 >= d3 and d5 >= d6:
            e = (d4 - d3) + (d5 - d6)
            w = (d4 - d3) / (e if e != 0 else 1.0)
            v = 1.0 - w
        else:
            denom = va + vb + vc
            denom = denom if denom != 0 else 1.0
            v, w = vb / denom, vc / denom
    r0 = p0 - v * ab[f, 0] - w * ac[f, 0]
    r1 = p1 - v * ab[f, 1] - w * ac[f, 1]
    r2 = p2 - v * ab[f, 2] - w * ac[f, 2]
    out = (r0 * r0 + r2 * r2) + r1 * r1
    return (out if out == out else np.inf), v, w


@numba.njit(cache=True, inline="always")
def _site_key(site_ptr, sites, f, x, y, z):
    """Distance of (x, y, z) from face f's nearest search site (the tie rule)."""
    key = np.inf
    for s in range(site_ptr[f], site_ptr[f + 1]):
        dx, dy, dz = x - sites[s, 0], y - sites[s, 1], z - sites[s, 2]
        key = min(key, np.sqrt(dx * dx + dy * dy + dz * dz))
    return key


@numba.njit(cache=True)
def nearest_faces(q, node_lo, node_hi, leaf_ptr, order, a, ab, ac, dots, site_ptr, sites):
    """The nearest face of each point q (n, 3): a depth-first search of the hierarchy, nearer child first.

    A box is opened only when it lies within the best distance so far (plus
    ``_SLACK_MM``).  Of faces equally near (a point nearest to a shared edge
    or vertex) the one with the nearest search site wins, then the lowest
    index: the answer does not depend on the order of the search.  ``a``,
    ``ab``, ``ac``, ``dots`` are in leaf order.  Returns the faces (n,) and
    the (v, w) (n, 2) of their closest points (:func:`_face_d2`).
    """
    n = q.shape[0]
    n_inner = leaf_ptr.shape[0] - 2
    out = np.empty(n, dtype=np.int64)
    out_vw = np.empty((n, 2))
    stack = np.empty(128, dtype=np.int64)  # at most one pending sibling per level
    stack_d2 = np.empty(128)
    for i in range(n):
        x, y, z = q[i, 0], q[i, 1], q[i, 2]
        best, best_face, best_key = np.inf, -1, -1.0  # best_key < 0: not computed yet
        best_v = best_w = 0.0
        limit = np.inf
        stack[0], stack_d2[0] = 0, 0.0
        top = 1
        while top:
            top -= 1
            node = stack[top]
            if stack_d2[top] > limit:
                continue
            if node >= n_inner:
                leaf = node - n_inner
                for j in range(leaf_ptr[leaf], leaf_ptr[leaf + 1]):
                    d2, v, w = _face_d2(a, ab, ac, dots, j, x, y, z)
                    if d2 > best:
                        continue
                    f = order[j]
                    if d2 == best and best_face >= 0:
                        if best_key < 0:
                            best_key = _site_key(site_ptr, sites, best_face, x, y, z)
                        key = _site_key(site_ptr, sites, f, x, y, z)
                        if key > best_key or (key == best_key and f > best_face):
                            continue
                        best_key = key
                    else:
                        best_key = -1.0
                    best, best_face, best_v, best_w = d2, f, v, w
                    limit = (np.sqrt(best) + _SLACK_MM) ** 2
                continue
            near, far = 2 * node + 1, 2 * node + 2
            d_near = _box_d2(node_lo, node_hi, near, x, y, z)
            d_far = _box_d2(node_lo, node_hi, far, x, y, z)
            if d_far < d_near:
                near, far, d_near, d_far = far, near, d_far, d_near
            if d_far <= limit:
                stack[top], stack_d2[top] = far, d_far
                top += 1
            if d_near <= limit:
                stack[top], stack_d2[top] = near, d_near
                top += 1
        out[i], out_vw[i, 0], out_vw[i, 1] = best_face, best_v, best_w
    return out, out_vw
