"""Shared fixtures for the modeling tests: the phantom heart as truth.

The phantom (``heartreg.phantom``) is the independent ground truth: its
``signed_distance`` is exact in sign and, at the surface, in value; its
``surface_points(u, v, ...)`` parameterises the exact surface.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest
from scipy import ndimage
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from heartreg.phantom import config, layout

PHASE_C = 0.65
WOOD_PRESETS = [f"wood2018-trial{k}" for k in range(1, 7)]


@functools.lru_cache(maxsize=None)
def heart_of(preset: str):
    return layout.make_heart(config.PRESETS[preset])


def phase_r_image(heart) -> float:
    return heart.image_resp_phase


@functools.lru_cache(maxsize=8)
def dense_surface(preset: str, phase_c: float = PHASE_C, n_u: int = 720, n_v: int = 600):
    """Dense exact surface samples, their outward normals and the true volume.

    720 x 600 samples (~0.35 mm apart): against 1440 x 1200 the 1 mm mesh's errors agree to 1e-4 mm (mean
    0.0757 mm, p95 0.182 mm) and the volume to 0.002 %, in 0.4 s instead of 10 (with the tree).

    Returns
    -------
    points : (N, 3) mm, patient
    normals : (N, 3) unit outward normals
    volume_mm3 : float, divergence theorem on the closed (u, v) grid mesh
    """
    heart = heart_of(preset)
    u = np.arange(n_u) / n_u
    v = np.linspace(0.0, 1.0, n_v)
    uu, vv = np.meshgrid(u, v, indexing="ij")
    pts = heart.surface_points(uu.ravel(), vv.ravel(), phase_c, heart.image_resp_phase)
    grid = pts.reshape(n_u, n_v, 3)
    # closed quad grid (u periodic, poles at v = 0 and 1) -> triangles
    a = grid[:, :-1]
    b = np.roll(grid, -1, axis=0)[:, :-1]
    c = np.roll(grid, -1, axis=0)[:, 1:]
    d = grid[:, 1:]
    vol = (
        np.einsum("...i,...i", a, np.cross(b, c)).sum()
        + np.einsum("...i,...i", a, np.cross(c, d)).sum()
    ) / 6.0
    # normals by central differences of the parameterisation
    du = np.roll(grid, -1, axis=0) - np.roll(grid, 1, axis=0)
    dv = np.gradient(grid, axis=1)
    n = np.cross(du, dv).reshape(-1, 3)
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 1e-12  # poles have no normal
    n = n[ok] / norm[ok, None]
    pts = pts[ok]
    if vol < 0:
        n = -n
    # orient normals outward using the exact sign of the implicit function
    probe = heart.signed_distance(pts + 0.05 * n, phase_c)
    n[probe < 0] *= -1
    return pts, n, abs(vol)


@functools.lru_cache(maxsize=8)
def _surface_tree(preset: str, phase_c: float = PHASE_C):
    pts, n, _ = dense_surface(preset, phase_c)
    return cKDTree(pts), pts, n


def distance_to_truth(preset: str, points: np.ndarray, phase_c: float = PHASE_C) -> np.ndarray:
    """Signed point-to-surface distance (mm, > 0 outside) via the nearest dense
    sample's tangent plane: O(h^2 / R) accurate for sample spacing h."""
    tree, pts, n = _surface_tree(preset, phase_c)
    _, idx = tree.query(points, k=1)
    return np.einsum("ij,ij->i", points - pts[idx], n[idx])


def grid_around_heart(
    preset: str,
    spacing_mm=(1.0, 1.0, 1.0),
    *,
    rotation_xyz_deg=(0.0, 0.0, 0.0),
    margin_mm: float = 5.0,
    phase_c: float = PHASE_C,
):
    """A voxel grid (T_patient_from_voxel, shape (k, j, i)) that covers the heart.

    Grid axes are the columns of the rotation, scaled by ``spacing_mm``
    (i, j, k order).
    """
    heart = heart_of(preset)
    uu, vv = np.meshgrid(np.arange(240) / 240, np.linspace(0, 1, 240), indexing="ij")
    pts = heart.surface_points(uu.ravel(), vv.ravel(), phase_c, heart.image_resp_phase)
    R = Rotation.from_euler("XYZ", rotation_xyz_deg, degrees=True).as_matrix()
    local = pts @ R  # coordinates along the grid axes
    lo = local.min(axis=0) - margin_mm
    hi = local.max(axis=0) + margin_mm
    sp = np.asarray(spacing_mm, float)
    n_ijk = np.ceil((hi - lo) / sp).astype(int) + 1
    T = np.eye(4)
    T[:3, :3] = R * sp
    T[:3, 3] = R @ lo
    return T, (int(n_ijk[2]), int(n_ijk[1]), int(n_ijk[0]))


def rasterize(preset: str, T_patient_from_voxel, shape_kji, phase_c: float = PHASE_C):
    """Exact inside mask (signed_distance < 0 at voxel centres), narrow-band fast.

    A coarse grid (every 4th voxel) decides voxels far from the surface by
    linear interpolation; voxels within two coarse diagonals are evaluated exactly.
    """
    heart = heart_of(preset)
    T = np.asarray(T_patient_from_voxel, float)
    nk, nj, ni = shape_kji
    step = 4
    ck, cj, ci = (np.arange(0, n + step, step) for n in (nk, nj, ni))
    K, J, I = np.meshgrid(ck, cj, ci, indexing="ij")
    ijk = np.stack([I.ravel(), J.ravel(), K.ravel()], axis=1).astype(float)
    coarse = heart.signed_distance(ijk @ T[:3, :3].T + T[:3, 3], phase_c).reshape(K.shape)
    fk, fj, fi = np.meshgrid(
        np.arange(nk) / step, np.arange(nj) / step, np.arange(ni) / step, indexing="ij"
    )
    approx = ndimage.map_coordinates(coarse, [fk, fj, fi], order=1, mode="nearest")
    del fk, fj, fi
    diag = step * np.linalg.norm(T[:3, :3], axis=0).max() * np.sqrt(3)
    band = np.abs(approx) < 2 * diag
    mask = approx < 0
    kk, jj, ii = np.nonzero(band)
    p = np.stack([ii, jj, kk], axis=1).astype(float) @ T[:3, :3].T + T[:3, 3]
    mask[kk, jj, ii] = heart.signed_distance(p, phase_c) < 0
    return mask


@pytest.fixture(scope="session")
def trial1_mask_1mm():
    T, shape = grid_around_heart("wood2018-trial1", (1.0, 1.0, 1.0))
    return T, rasterize("wood2018-trial1", T, shape)


@pytest.fixture(scope="session")
def phantom_meshes():
    """Phantom meshes (patient frame) of the six presets at 1.0 mm voxels."""
    from modeling.surface import mask_to_mesh

    out = {}
    for preset in WOOD_PRESETS:
        T, shape = grid_around_heart(preset, (1.0, 1.0, 1.0))
        out[preset] = mask_to_mesh(rasterize(preset, T, shape), T, target_faces=20000)
    return out
