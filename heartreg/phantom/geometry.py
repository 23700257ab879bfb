"""The phantom's own 4x4 transform helpers: build, apply, invert, fit.

A documented copy of the basics of :mod:`hrcore.geometry`: the phantom is the
independent ground truth of the packages it tests, so it does not share their
code (tests/test_layering.py); ``tests/heartreg/test_phantom_geometry.py``
checks on random inputs that the two copies agree. Keep it this small.
"""

from __future__ import annotations

import numpy as np


def poses(R, t) -> np.ndarray:
    """Rigid transforms ``(..., 4, 4)`` from rotations ``(..., 3, 3)`` and translations ``(..., 3)`` mm."""
    R = np.asarray(R, dtype=float)
    T = np.zeros(R.shape[:-2] + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def apply(T, points) -> np.ndarray:
    """Points ``(..., 3)`` mm mapped through the 4x4 transform ``T``."""
    T = np.asarray(T, dtype=float)
    return np.asarray(points, dtype=float) @ T[:3, :3].T + T[:3, 3]


def invert(T) -> np.ndarray:
    """Inverse of rigid transforms ``(..., 4, 4)`` (transposed rotation)."""
    T = np.asarray(T, dtype=float)
    R = np.swapaxes(T[..., :3, :3], -1, -2)
    return poses(R, -np.einsum("...ij,...j->...i", R, T[..., :3, 3]))


def kabsch(source, target) -> np.ndarray:
    """Least-squares rigid ``T`` with ``T @ source[i] ~ target[i]``, ``(n, 3)`` each (reflection guarded)."""
    source, target = np.asarray(source, dtype=float), np.asarray(target, dtype=float)
    cs, ct = source.mean(axis=0), target.mean(axis=0)
    H = (source - cs).T @ (target - ct)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0])
    R = Vt.T @ D @ U.T
    return poses(R, ct - R @ cs)


def frozen(a, dtype=float) -> np.ndarray:
    """A read-only copy of ``a`` as ``dtype``."""
    a = np.array(a, dtype=dtype)
    a.setflags(write=False)
    return a
