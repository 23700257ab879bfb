"""Tests of registration/tracking.py: the reused searches give the exact closest points, and the sweep
through them equals the sweep that searches afresh at every iteration."""

import numpy as np
import pytest

from registration.closest import SurfaceIndex, closest_points
from registration.tracking import PointSetTracker

from .conftest import icosphere
from .test_icp import brute_force_closest


def _moves(rng, m, n, steps, scale_mm):
    """Point sets that drift (each set a little off its neighbour) and jump now and then."""
    base = rng.normal(0, 1, (n, 3))
    base = 44.0 * base / np.linalg.norm(base, axis=1, keepdims=True)  # 0-10 mm outside a 40 mm sphere
    base *= 1.0 + rng.uniform(0, 0.2, (n, 1))
    q = base[None] + np.linspace(0, 1, m)[:, None, None] * rng.normal(0, scale_mm, (1, n, 3))
    out = [q.copy()]
    for t in range(steps):
        step = rng.normal(0, scale_mm / (t + 1), (m, n, 3))
        step[rng.random(m) < 0.2] *= 20.0  # some sets jump (an early ICP step)
        q = q + step
        out.append(q.copy())
    return out


@pytest.mark.parametrize("seed", [0, 1])
def test_tracker_equals_brute_force_on_a_small_mesh(seed):
    # every answer, whether reused from its own last search, from a neighbouring set or searched afresh,
    # is the exact nearest face of all of them (brute force), with its point
    vertices, faces = icosphere(40.0, subdivisions=2)  # 320 faces
    surface = SurfaceIndex(vertices, faces)
    rng = np.random.default_rng(seed)
    m, n = 9, 12
    tracker = PointSetTracker(surface, m, n, k=24, stride=4, width=12)
    for t, q in enumerate(_moves(rng, m, n, 5, 0.4)):
        sets = np.arange(m) if t < 2 else np.sort(rng.choice(m, 6, replace=False))
        got = tracker.query(sets, q[sets])
        flat = q[sets].reshape(-1, 3)
        expected = brute_force_closest(vertices, faces, flat)
        np.testing.assert_allclose(got.distances_mm, np.linalg.norm(expected - flat, axis=1), rtol=0, atol=1e-9)
        np.testing.assert_allclose(got.points, expected, rtol=0, atol=1e-9)


def test_tracker_equals_closest_points_on_the_heart(heart_index, heart_mesh):
    # the same faces as closest_points (its tie rule too: on a shared edge the face with the nearest site)
    vertices, _ = heart_mesh
    rng = np.random.default_rng(3)
    m, n = 12, 40
    base = vertices[rng.choice(len(vertices), n)] + rng.normal(0, 4.0, (n, 3))
    q = base[None] + np.linspace(0, 3.0, m)[:, None, None] * rng.normal(0, 1, (1, n, 3))
    tracker = PointSetTracker(heart_index, m, n)
    for t in range(4):
        got = tracker.query(np.arange(m), q)
        ref = closest_points(heart_index, q.reshape(-1, 3))
        np.testing.assert_array_equal(got.face_index, ref.face_index)
        np.testing.assert_array_equal(got.points, ref.points)
        q = q + rng.normal(0, 0.3 / (t + 1), q.shape)
