"""Tests of registration/closest.py: the compiled search of the bounding-volume hierarchy finds the
nearest face of a brute-force evaluation over all faces, bit for bit, with its tie rule."""

import numpy as np
import pytest

from registration.closest import SurfaceIndex, _build_bvh, _closest_barycentric, closest_points

from .conftest import icosphere


def brute_force_d2(surface, p):
    """Squared distance of p (3,) from every face (F,), the vectorised arithmetic."""
    s = surface
    v, w = _closest_barycentric(np.broadcast_to(p, s._a.shape), s._a, s._ab, s._ac, s._dots)
    diff = p - s._a - v[:, None] * s._ab - w[:, None] * s._ac
    d2 = np.einsum("ij,ij->i", diff, diff)
    return np.where(np.isnan(d2), np.inf, d2)


def expected_face(surface, p):
    """The nearest face of p; of exact ties the face with the nearest search site, then the lowest index."""
    d2 = brute_force_d2(surface, p)
    tied = np.flatnonzero(d2 == d2.min())
    site_d = np.sqrt(np.sum((p - surface.tree.data) ** 2, axis=1))
    key = np.array([site_d[surface._site_face == f].min() for f in tied])
    return tied[int(np.argmin(key))], d2.min(), tied.size  # argmin: the first (lowest index) of equal keys


def _points(vertices, faces, rng, n):
    """Points near and far (0.01 to 20 mm), plus points exactly off vertices and edge midpoints (ties)."""
    base = vertices[rng.choice(len(vertices), n)]
    scale = np.repeat([0.01, 0.5, 3.0, 20.0], -(-n // 4))[:n, None]
    f = faces[rng.choice(len(faces), n)]
    mid = 0.5 * (vertices[f[:, 0]] + vertices[f[:, 1]])
    return np.concatenate([base + rng.normal(0, 1, base.shape) * scale, 1.1 * vertices[f[:, 0]], 1.1 * mid,
                           vertices[f[:, 2]]])


@pytest.mark.parametrize("subdivisions", [0, 1, 3])
def test_the_search_finds_the_brute_force_face_bit_for_bit(subdivisions):
    # 20 faces (a one-level hierarchy), 80, 1280; on a sphere points pushed out from a vertex or an
    # edge's midpoint are exactly as near to all faces sharing it: the tie rule decides
    vertices, faces = icosphere(40.0, subdivisions=subdivisions)
    surface = SurfaceIndex(vertices, faces)
    q = _points(vertices, faces, np.random.default_rng(subdivisions), 40)
    cp = closest_points(surface, q)
    ties = 0
    for i, p in enumerate(q):
        face, d2, n_tied = expected_face(surface, p)
        ties += n_tied > 1
        assert cp.face_index[i] == face
        assert abs(cp.distances_mm[i] - np.sqrt(d2)) < 1e-12  # mm: the same point, a norm of its own
    assert ties >= 20  # the tie rule was exercised
    np.testing.assert_allclose(np.linalg.norm(cp.points - q, axis=1), cp.distances_mm, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(cp.normals, surface.normals[cp.face_index])


def test_the_search_on_the_heart(heart_index, heart_mesh):
    # the 20 000-face heart, points 0.01-20 mm off (inside and out), at vertices and edges: the same faces
    vertices, faces = heart_mesh
    q = _points(vertices, faces, np.random.default_rng(7), 24)
    cp = closest_points(heart_index, q)
    for i, p in enumerate(q):
        assert cp.face_index[i] == expected_face(heart_index, p)[0]


def test_one_face():
    # a single triangle: the hierarchy is one leaf
    tri = np.array([[0.0, 0, 0], [10, 0, 0], [0, 10, 0]])
    cp = closest_points((tri, np.array([[0, 1, 2]])), np.array([[2.0, 2, 5], [20.0, 0, 0], [-3.0, -4, 0]]))
    np.testing.assert_allclose(cp.points, [[2, 2, 0], [10, 0, 0], [0, 0, 0]], atol=1e-12)
    np.testing.assert_allclose(cp.distances_mm, [5, 10, 5], atol=1e-12)
    np.testing.assert_array_equal(cp.face_index, [0, 0, 0])


def test_the_hierarchy_holds_every_face_once_in_boxes_that_contain_them():
    vertices, faces = icosphere(40.0, subdivisions=3)
    tri = vertices[faces]
    lo, hi, centres = tri.min(axis=1), tri.max(axis=1), tri.mean(axis=1)
    node_lo, node_hi, leaf_ptr, order = _build_bvh(lo, hi, centres, leaf_size=4)
    n_leaves = leaf_ptr.size - 1
    assert n_leaves == 512 and node_lo.shape == (2 * n_leaves - 1, 3)  # 1280 faces: 2.5 a leaf
    np.testing.assert_array_equal(np.sort(order), np.arange(len(faces)))
    assert 2 <= np.diff(leaf_ptr).min() and np.diff(leaf_ptr).max() <= 4
    leaf_of = np.repeat(np.arange(n_leaves), np.diff(leaf_ptr))
    node = leaf_of + n_leaves - 1
    while True:  # each face inside its leaf's box and every ancestor's
        assert np.all(node_lo[node] <= lo[order]) and np.all(hi[order] <= node_hi[node])
        if node[0] == 0:
            break
        node = (node - 1) // 2
