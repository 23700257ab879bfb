"""Shared phantom fixtures for the registration tests.

The phantom mesh is the analytic heart triangulated on a (u, v) grid closed at
both poles, so its vertices lie exactly on the analytic surface (the mesh is a
chordal approximation: for ~2.5 mm edges on >= 20 mm radii of curvature the
sagitta is < 0.05 mm).
"""

from __future__ import annotations

import numpy as np
import pytest

from heartreg.phantom import config as phantom_config
from heartreg.phantom import layout


def heart_grid_mesh(heart, phase_c, phase_r, *, n_u=100, n_v=100):
    """Triangulate the heart at (phase_c, phase_r) in the patient frame.

    Returns
    -------
    vertices : (n_u * n_v + 2, 3) float64, mm
    faces : (2 * n_u * n_v, 3) int64, counter-clockwise from outside.
    """
    u = np.arange(n_u) / n_u
    v = (np.arange(n_v) + 1.0) / (n_v + 1.0)
    uu, vv = np.meshgrid(u, v, indexing="ij")  # [i_u, j_v]
    ring = heart.surface_points(uu.ravel(), vv.ravel(), phase_c, phase_r)
    poles = heart.surface_points(np.zeros(2), np.array([0.0, 1.0]), phase_c, phase_r)
    vertices = np.concatenate([ring, poles])
    apex, base = n_u * n_v, n_u * n_v + 1

    def vid(i, j):
        return (i % n_u) * n_v + j

    i, j = np.meshgrid(np.arange(n_u), np.arange(n_v - 1), indexing="ij")
    i, j = i.ravel(), j.ravel()
    # du x dv is outward: (p(i,j), p(i+1,j), p(i,j+1)) is counter-clockwise from outside.
    quads_a = np.stack([vid(i, j), vid(i + 1, j), vid(i, j + 1)], axis=1)
    quads_b = np.stack([vid(i + 1, j), vid(i + 1, j + 1), vid(i, j + 1)], axis=1)
    ii = np.arange(n_u)
    apex_fan = np.stack([vid(ii + 1, 0), vid(ii, 0), np.full(n_u, apex)], axis=1)
    base_fan = np.stack([vid(ii, n_v - 1), vid(ii + 1, n_v - 1), np.full(n_u, base)], axis=1)
    faces = np.concatenate([quads_a, quads_b, apex_fan, base_fan]).astype(np.int64)
    return vertices, faces


def icosphere(radius_mm=40.0, subdivisions=4):
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius_mm)
    return np.asarray(mesh.vertices), np.asarray(mesh.faces, dtype=np.int64)


@pytest.fixture(scope="session")
def trial1_config():
    return phantom_config.PRESETS["wood2018-trial1"]


@pytest.fixture(scope="session")
def trial1_heart(trial1_config):
    return layout.make_heart(trial1_config)


@pytest.fixture(scope="session")
def image_phase_c():
    """The map's cardiac phase phi_C* used throughout these tests."""
    return 0.65


@pytest.fixture(scope="session")
def heart_mesh(trial1_heart, trial1_config, image_phase_c):
    """(vertices, faces) of the trial-1 heart at (phi_C*, phi_R*), patient frame, 20k faces."""
    return heart_grid_mesh(trial1_heart, image_phase_c, trial1_config.image_resp_phase)


@pytest.fixture(scope="session")
def heart_index(heart_mesh):
    from registration.icp import SurfaceIndex

    return SurfaceIndex(*heart_mesh)


def simulate_traces(heart, config, uv, *, rng, duration_s=30.0, rate_hz=50.0,
                    noise_mm=0.3, noise_deg=0.2, T_probe_from_patient=None):
    """Robot pose traces of attachment points (u, v), as the tracker would see them.

    Each point gets its own 30 s recording (own R-peaks and breaths, as in the
    paper).  Returns a list of (phase_c, phase_r, T_probe_from_robot) and the
    matching list of noise-free (position, frame) arrays in the patient frame.
    """
    from scipy.spatial.transform import Rotation

    from heartreg.phantom import signals

    if T_probe_from_patient is None:
        T_probe_from_patient = np.linalg.inv(layout.T_patient_from_probe())
    traces, truth = [], []
    for k, (u, v) in enumerate(uv):
        start = 1000.0 + 40.0 * k
        t = start + np.arange(int(round(duration_s * rate_hz))) / rate_hz
        peaks = signals.r_peak_times(
            rng, start_s=start, end_s=t[-1], heart_rate_hz=config.heart_rate_hz,
            hrv_fraction=config.hrv_fraction, ectopic_probability=config.ectopic_probability,
            resp_rate_hz=config.resp_rate_hz,
        )
        onsets = signals.expiration_onsets(rng, start_s=start, end_s=t[-1], resp_rate_hz=config.resp_rate_hz)
        pc = signals.phase_from_events(t, peaks)
        pr = signals.phase_from_events(t, onsets)
        pos, R = heart.surface_frames(np.full(t.shape, u), np.full(t.shape, v), pc, pr)
        truth.append((pos, R))
        T = np.zeros((t.size, 4, 4))
        T[:, :3, :3] = T_probe_from_patient[:3, :3] @ R
        T[:, :3, 3] = pos @ T_probe_from_patient[:3, :3].T + T_probe_from_patient[:3, 3]
        T[:, 3, 3] = 1.0
        T[:, :3, 3] += rng.normal(0.0, noise_mm, (t.size, 3))
        dR = Rotation.from_rotvec(rng.normal(0.0, np.radians(noise_deg), (t.size, 3))).as_matrix()
        T[:, :3, :3] = T[:, :3, :3] @ dR
        traces.append((pc, pr, T))
    return traces, truth


def spread_uv(n, *, seed=0, v_range=(0.12, 0.88)):
    """n surface coordinates spread over the heart (golden-angle spiral in v)."""
    k = np.arange(n)
    u = np.mod(k * 0.6180339887 + 0.1 * seed, 1.0)
    v = v_range[0] + (v_range[1] - v_range[0]) * (k + 0.5) / n
    return np.stack([u, v], axis=1)
