"""The map's curvature at the points, and the heart term without the map's own offsets."""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull

from registration.mesh_bias import curvature_at_points, vertex_mean_curvature
from registration.temporal import estimate_phase

PHASES = np.linspace(0.0, 1.0, 101)


def _sphere(radius_mm, n=2000):
    """A closed triangle mesh of a sphere (Fibonacci points), faces outward."""
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    r = np.sqrt(1 - z**2)
    a = np.pi * (1 + 5**0.5) * i
    v = radius_mm * np.stack([r * np.cos(a), r * np.sin(a), z], axis=1)
    faces = ConvexHull(v).simplices
    n_f = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
    inward = np.einsum("ij,ij->i", n_f, v[faces].mean(axis=1)) < 0
    faces[inward] = faces[inward][:, ::-1]
    return v, faces


def test_a_sphere_has_mean_curvature_minus_one_over_its_radius():
    for radius in (20.0, 50.0):
        v, f = _sphere(radius)
        H = vertex_mean_curvature(v, f)
        assert np.allclose(np.median(H), -1.0 / radius, rtol=0.1)  # convex seen from outside: negative
        assert np.quantile(np.abs(H * radius + 1), 0.9) < 0.3


def test_curvature_at_points_is_that_of_the_nearest_vertex_after_each_phase_transform():
    v, f = _sphere(30.0, n=500)
    H = np.arange(v.shape[0], dtype=float)  # a label per vertex
    T = np.broadcast_to(np.eye(4), (2, 4, 4)).copy()
    T[1, :3, 3] = [5.0, 0.0, 0.0]
    pts = np.stack([v[[3, 7]], v[[3, 7]] - [5.0, 0.0, 0.0]])  # the second phase's transform brings them back
    assert np.array_equal(curvature_at_points(pts, T, v, H), [[3.0, 7.0], [3.0, 7.0]])


def test_offsets_that_follow_the_maps_curvature_no_longer_pull_the_phase():
    rng = np.random.default_rng(3)
    n, phase_true = 80, 0.7
    H = rng.normal(-0.04, 0.02, n)  # 1/mm at each point
    offset = 8.0 * H  # a CT's blur shifts the surface by ~sigma^2 H (here 8 mm^2), -0.3 mm on average
    a = rng.uniform(0.5, 2.0, n)  # each point moves outward of the map away from the CT's phase
    x = (PHASES - phase_true + 0.5) % 1.0 - 0.5
    signed = offset + a * (1 - np.cos(2 * np.pi * x))[:, None] + 0.03 * rng.standard_normal((PHASES.size, n))
    vertices = rng.normal(0, 40, (500, 3))
    Ts = np.broadcast_to(np.eye(4), (PHASES.size, 4, 4)).copy()
    plain = estimate_phase(PHASES, signed, Ts, vertices)
    assert abs(plain.respiration_phase - phase_true) >= 0.1  # the offsets pull it to where a * u = -offset
    fixed = estimate_phase(PHASES, signed, Ts, vertices, curvature_per_mm=H)
    assert abs(fixed.respiration_phase - phase_true) <= 0.03 and fixed.contains(phase_true)
    # (m, n) curvature (each phase's nearest vertex) is used the same way
    again = estimate_phase(PHASES, signed, Ts, vertices, curvature_per_mm=np.broadcast_to(H, signed.shape))
    assert again.respiration_phase == fixed.respiration_phase
