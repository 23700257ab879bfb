"""The map's known error modes at the registered points: the basis the heart term removes.

A surface segmented from a CT is offset from the true one by an amount that is
the same at every respiration phase: the CT's blur (its point-spread function
and voxels, sigma ~ 1-2 mm on a 2 mm CT) shifts the isosurface of a curved
surface along its normal by about ``sigma^2 H`` (``H`` the mean curvature),
and a threshold shifts the whole surface in or out.  Those per-point offsets
carry no phase information, yet the heart term of
:func:`registration.temporal.estimate_phase` reads them as shape: on the
phantom's sample-size CT (1.95 x 1.95 x 2.5 mm) the map's surface is 0.2-0.3
mm RMS off the true epicardium at the registered points (the motion models'
predictions 0.06 mm), the points' signed distances follow the curvature
(correlation 0.6), and where breathing barely changes the heart's shape a
dozen such points pick a phase 0.1 cycle off.  The heart term therefore fits,
at each phase, the signed distances by ``a + k H`` (least squares, the size
``k`` unknown and left to the data) and keeps the rest, when given the
curvature (``estimate_phase(..., curvature_per_mm=...)``; ``register`` does
not pass it yet, see docs/reproduction.md; ``heartreg evaluate-temporal``
saves it with each case's evidence for re-scoring).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from hrcore.geometry import apply_to_points
from modeling.mesh import vertex_normals

__all__ = ["vertex_mean_curvature", "curvature_at_points"]


def vertex_mean_curvature(vertices_mm, faces) -> np.ndarray:
    """Mean curvature (1/mm) at each vertex of a closed triangle mesh (umbrella estimate).

    ``2 (mean(neighbours) - v) . n / l^2`` with ``n`` the area-weighted outward
    vertex normal and ``l`` the mean length of the vertex's edges: positive
    where the surface is concave seen from outside (a groove), negative
    where convex; about the mean curvature on a regular mesh.

    Parameters
    ----------
    vertices_mm : (V, 3) float, mm
    faces : (F, 3) int
        Counter-clockwise seen from outside.

    Returns
    -------
    (V,) float64, 1/mm
    """
    v = np.asarray(vertices_mm, dtype=float)
    f = np.asarray(faces, dtype=np.int64)
    normals = vertex_normals(v, f)
    edges = np.unique(np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1), axis=0)
    length = np.linalg.norm(v[edges[:, 0]] - v[edges[:, 1]], axis=1)
    total, count, length_sum = np.zeros_like(v), np.zeros(v.shape[0]), np.zeros(v.shape[0])
    for a, b in ((0, 1), (1, 0)):
        np.add.at(total, edges[:, a], v[edges[:, b]])
        np.add.at(count, edges[:, a], 1.0)
        np.add.at(length_sum, edges[:, a], length)
    used = count > 0
    out = np.zeros(v.shape[0])
    umbrella = total[used] / count[used, None] - v[used]
    mean_length = length_sum[used] / count[used]
    out[used] = 2.0 * np.einsum("ij,ij->i", umbrella, normals[used]) / mean_length**2
    return out


def curvature_at_points(points_probe_mm, T_heart_from_probe, vertices_mm, curvature_per_mm) -> np.ndarray:
    """The map's curvature at each point's nearest vertex, at each phase of a sweep.

    Parameters
    ----------
    points_probe_mm : (m, n, 3) float, mm
        Predicted points at each swept phase (probe frame).
    T_heart_from_probe : (m, 4, 4) float
        The sweep's registration at each phase.
    vertices_mm : (V, 3) float, mm
        The map's vertices.
    curvature_per_mm : (V,) float, 1/mm
        From :func:`vertex_mean_curvature`.

    Returns
    -------
    (m, n) float64, 1/mm
    """
    pts = np.asarray(points_probe_mm, dtype=float)
    Ts = np.asarray(T_heart_from_probe, dtype=float)
    mapped = np.stack([apply_to_points(Ts[i], pts[i]) for i in range(pts.shape[0])])
    _, nearest = cKDTree(np.asarray(vertices_mm, dtype=float)).query(mapped.reshape(-1, 3))
    return np.asarray(curvature_per_mm, dtype=float)[nearest].reshape(pts.shape[:2])
