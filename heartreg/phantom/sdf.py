"""Signed distances (mm, negative inside) of the shapes the phantom's anatomy is made of.

Exact distances of spheres, capsules and round cones (iq's ``sdRoundCone``),
polynomial smooth union and intersection (``_smin``, ``_smax``), the distance
to a polyline tube. Used by :mod:`heartreg.phantom.anatomy` (the chambers) and
:mod:`heartreg.phantom.great_vessels`.
"""

from __future__ import annotations

from itertools import pairwise

import numpy as np


def _sphere(p, c, r):
    return np.linalg.norm(p - np.asarray(c, dtype=float), axis=-1) - r


def _round_cone(p, a, b, r1, r2):
    """Exact signed distance to the convex hull of two spheres (a, r1), (b, r2)."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    ba = b - a
    l2 = float(ba @ ba)
    rr = r1 - r2
    a2 = l2 - rr * rr
    il2 = 1.0 / l2
    pa = p - a
    y = pa @ ba
    z = y - l2
    q = pa * l2 - y[..., None] * ba
    x2 = np.einsum("...i,...i", q, q)
    y2 = y * y * l2
    z2 = z * z * l2
    k = np.sign(rr) * rr * rr * x2
    d_b = np.sqrt(x2 + z2) * il2 - r2
    d_a = np.sqrt(x2 + y2) * il2 - r1
    d_side = (np.sqrt(x2 * a2 * il2) + y * rr) * il2 - r1
    return np.where(np.sign(z) * a2 * z2 > k, d_b, np.where(np.sign(y) * a2 * y2 < k, d_a, d_side))


def _capsule(p, a, b, r):
    return _round_cone(p, a, b, r, r)


def _smin(a, b, k):
    """Polynomial smooth minimum (union) of two distances with blend radius k."""
    h = np.maximum(k - np.abs(a - b), 0.0) / k
    return np.minimum(a, b) - 0.25 * k * h * h


def _smax(a, b, k):
    return -_smin(-a, -b, k)


def _polyline_distance(p, points, radius):
    """Distance (mm, negative inside) to a tube of constant radius around a polyline."""
    d2 = np.full(p.shape[:-1], np.inf)
    for a, b in pairwise(points):
        ab = b - a
        t = np.clip(((p - a) @ ab) / max(float(ab @ ab), 1e-12), 0.0, 1.0)
        r = p - (a + t[..., None] * ab)
        d2 = np.minimum(d2, np.einsum("...i,...i->...", r, r))
    return np.sqrt(d2) - radius


def _lumen_beyond_valve(p, points, radius, valve, normal):
    """Distance (mm, negative inside) to an artery's lumen from its valve plane on.

    The tube of :func:`_polyline_distance` cut by the plane through ``valve``
    with unit ``normal`` (into the artery): the painted lumen and the truth's
    cut over its mouth are the same set.
    """
    return np.maximum(_polyline_distance(p, points, radius), (valve - p) @ normal)
