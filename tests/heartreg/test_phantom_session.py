"""The phantom's session writer against its own analytic truth.

These tests parse the CSV files with numpy directly (not with the registration
reader, which has its own tests) so that a writer bug and a reader bug cannot
cancel.  Sessions are small (5 points x 25 s) to stay fast.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from heartreg.phantom.config import PhantomConfig
from heartreg.phantom.layout import T_fiducial_shift, T_patient_from_probe, fiducials_patient_mm, make_heart
from heartreg.phantom.session import REACH_V, reachable_patch, write_session
from heartreg.phantom.session_format import FIDUCIAL_COLUMNS, POINT_COLUMNS, SESSION_FORMAT
from heartreg.phantom.signals import phase_from_events

N_POINTS, DURATION_S = 5, 25.0
CONFIG = PhantomConfig()


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    out = tmp_path_factory.mktemp("phantom")
    truth = write_session(out, CONFIG, seed=3, n_points=N_POINTS, duration_s=DURATION_S)
    return out / "session", truth


def _load(folder: Path, k: int) -> np.ndarray:
    return np.loadtxt(folder / f"points/point_{k:03d}.csv", delimiter=",", skiprows=1)


def _poses(cols: np.ndarray) -> np.ndarray:
    T = np.tile(np.eye(4), (len(cols), 1, 1))
    T[:, :3, :3] = Rotation.from_quat(cols[:, 3:7], scalar_first=True).as_matrix()
    T[:, :3, 3] = cols[:, :3]
    return T


def _measured(data):
    """Measured T_tracker_from_robot, T_tracker_from_probe and T_probe_from_robot."""
    Tr, Tp = _poses(data[:, 1:8]), _poses(data[:, 8:15])
    return Tr, Tp, np.linalg.inv(Tp) @ Tr


def _clean_probe_from_robot(truth, heart, k, time_s):
    """T_probe_from_robot from the analytic heart at the true phases."""
    point = truth.points[k]
    pc = phase_from_events(time_s, truth.r_peaks_s)
    pr = phase_from_events(time_s, truth.expiration_onsets_s)
    n = len(time_s)
    p, R = heart.surface_frames(np.full(n, point.u), np.full(n, point.v), pc, pr)
    yaw = Rotation.from_euler("z", point.yaw_deg, degrees=True).as_matrix()
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = R @ yaw
    T[:, :3, 3] = p
    return np.linalg.inv(truth.T_patient_from_probe) @ T, R


def _digest(folder: Path) -> dict[str, str]:
    return {
        str(f.relative_to(folder)): hashlib.sha256(f.read_bytes()).hexdigest()
        for f in sorted(folder.rglob("*"))
        if f.is_file()
    }


def test_folder_layout_and_metadata(written):
    folder, truth = written
    meta = json.loads((folder / "session.json").read_text())
    assert meta["format"] == SESSION_FORMAT and meta["version"] == 2
    assert meta["units"] == {"position": "mm", "time": "s", "ecg": "mV", "flow": "L/min"}
    assert meta["quaternion_order"] == "wxyz" and meta["frames"] == {"poses": "tracker"}
    assert meta["sample_rate_hz"] == 100
    assert [p["file"] for p in meta["points"]] == [f"points/point_{k:03d}.csv" for k in range(N_POINTS)]
    assert [p["surface_point"] for p in meta["points"]] == [p.point_id for p in truth.points]
    text = (folder / "session.json").read_text().lower()
    assert "patient" not in text.replace("patient right to left", "")  # no identity fields
    header = (folder / "points/point_000.csv").read_text().splitlines()[0]
    assert tuple(header.split(",")) == POINT_COLUMNS
    assert tuple((folder / "fiducials.csv").read_text().splitlines()[0].split(",")) == FIDUCIAL_COLUMNS
    assert not [p for p in folder.parent.iterdir() if p.name.startswith(".session")]  # no leftovers


def test_records_are_consecutive_on_one_clock(written):
    folder, truth = written
    times = [_load(folder, k)[:, 0] for k in range(N_POINTS)]
    for k, t in enumerate(times):
        assert len(t) == int(DURATION_S * 100)
        np.testing.assert_allclose(np.diff(t), 0.01, atol=1.5e-3)
        assert 0 < t[0] < 86400  # seconds after midnight
        assert t[0] == truth.points[k].start_s and t[-1] == truth.points[k].end_s
    gaps = np.array([b[0] - a[-1] for a, b in zip(times, times[1:])])
    assert np.all((gaps >= 5.0) & (gaps <= 20.01))
    # events cover the whole surgery, so phases exist at every sample
    assert truth.r_peaks_s[0] < times[0][0] and truth.r_peaks_s[-1] > times[-1][-1]
    assert truth.expiration_onsets_s[0] < times[0][0] and truth.expiration_onsets_s[-1] > times[-1][-1]


def test_robot_follows_surface_and_z_is_outward_normal(written):
    """Measured poses equal the analytic surface frames up to tracker noise: the
    z axis within ~1 deg of the surface normal (noise RMS ~0.37 deg)."""
    folder, truth = written
    heart = make_heart(CONFIG)
    for k in range(N_POINTS):
        data = _load(folder, k)
        _, _, T_meas = _measured(data)
        T_clean, R_surface = _clean_probe_from_robot(truth, heart, k, data[:, 0])
        z_patient = (truth.T_patient_from_probe[:3, :3] @ T_meas[:, :3, 2].T).T
        angle = np.degrees(np.arccos(np.clip(np.sum(z_patient * R_surface[..., 2], axis=1), -1, 1)))
        assert np.sqrt(np.mean(angle**2)) < 1.0
        assert np.sqrt(np.mean((T_meas[:, :3, 3] - T_clean[:, :3, 3]) ** 2)) < 0.6


def test_probe_motion_cancels_and_noise_matches_the_model(written):
    """The probe moves by millimetres in the tracker frame, yet the relative pose
    differs from the clean one only by tracker noise.  With independent noise
    sigma_p per axis on both positions and rotation vectors ~ N(0, sigma_r) on
    both rotations, first-order propagation gives for the relative pose
    E|dt|^2 = 6 sigma_p^2 + 2 sigma_r^2 |r|^2 (r: robot from probe, the lever
    arm of the probe's rotation noise) and E|dtheta|^2 = 6 sigma_r^2.  The
    estimates from 2500 samples are within a few % of these."""
    folder, truth = written
    heart = make_heart(CONFIG)
    sp = CONFIG.noise.tracker_position_mm
    sr = np.radians(CONFIG.noise.tracker_rotation_deg)
    for k in range(N_POINTS):
        data = _load(folder, k)
        _, Tp, T_meas = _measured(data)
        probe_xyz = Tp[:, :3, 3]
        assert np.ptp(probe_xyz @ Tp[0, :3, 2]) > 2.0  # breathing along its z (2-4 mm)
        T_clean, _ = _clean_probe_from_robot(truth, heart, k, data[:, 0])
        d_pos = T_meas[:, :3, 3] - T_clean[:, :3, 3]
        d_rot = Rotation.from_matrix(np.swapaxes(T_clean[:, :3, :3], 1, 2) @ T_meas[:, :3, :3]).magnitude()
        lever2 = np.mean(np.sum(T_clean[:, :3, 3] ** 2, axis=1))
        expected_pos = np.sqrt(6 * sp**2 + 2 * sr**2 * lever2)
        assert np.sqrt(np.mean(np.sum(d_pos**2, axis=1))) == pytest.approx(expected_pos, rel=0.06)
        assert np.sqrt(np.mean(d_rot**2)) == pytest.approx(np.sqrt(6) * sr, rel=0.06)
        # the truth records the same effective noise
        point = truth.points[k]
        np.testing.assert_allclose(point.position_noise_rms_mm, np.sqrt(np.mean(d_pos**2, axis=0)), rtol=1e-3)
        assert point.rotation_noise_rms_deg == pytest.approx(np.degrees(np.sqrt(np.mean(d_rot**2))), rel=1e-3)


def test_fiducials_map_to_the_shifted_ct_fiducials(written):
    """T* @ f_probe = T_shift @ (f_ct + chest wall at the touch's phase) + touch
    noise (sigma 1 mm per axis, and the tracker's 0.2 mm; the RMS over 27 values
    lies in [0.5, 1.6] sigma with probability > 0.999)."""
    from heartreg.phantom.session_motion import chest_wall_displacement

    folder, truth = written
    table = np.loadtxt(folder / "fiducials.csv", delimiter=",", skiprows=1)
    np.testing.assert_array_equal(table[:, 0], np.arange(1, 10))
    f_probe = table[:, 1:]
    f_ct = fiducials_patient_mm()
    T_star, T_shift = T_patient_from_probe(), T_fiducial_shift(CONFIG)
    lhs = f_probe @ T_star[:3, :3].T + T_star[:3, 3]
    chest = chest_wall_displacement(CONFIG, truth.fiducial_touch_phase_r)[np.arange(9), np.arange(9)]
    rhs = (f_ct + chest) @ T_shift[:3, :3].T + T_shift[:3, 3]
    rms = np.sqrt(np.mean((lhs - rhs) ** 2))
    sigma = CONFIG.noise.fiducial_touch_mm
    assert 0.5 * sigma < rms < 1.6 * sigma
    # T0 registers touched onto CT fiducials, close to inv(T_shift) @ T*
    T0 = truth.T0_patient_from_probe
    np.testing.assert_allclose(T0[:3, :3] @ T0[:3, :3].T, np.eye(3), atol=1e-12)
    assert np.linalg.det(T0[:3, :3]) == pytest.approx(1.0)
    mapped = f_probe @ T0[:3, :3].T + T0[:3, 3]
    # the chest's breathing (up to chest_wall_ap_mm) adds to the touch noise
    assert np.sqrt(np.mean((mapped - f_ct) ** 2)) < 1.6 * sigma + 0.5 * CONFIG.chest_wall_ap_mm
    expected = np.linalg.inv(T_shift) @ T_star
    assert np.linalg.norm(T0[:3, 3] - expected[:3, 3]) < 3.0 * sigma + 2 * CONFIG.chest_wall_ap_mm


def test_ecg_maxima_at_true_r_peaks(written):
    """The clean ECG peaks exactly at each R time; sampled at 100 Hz with 0.03 mV
    noise the largest sample lies within one sample (10 ms) of it."""
    folder, truth = written
    for k in range(N_POINTS):
        data = _load(folder, k)
        t, ecg = data[:, 0], data[:, 15]
        inside = truth.r_peaks_s[(truth.r_peaks_s > t[0] + 0.15) & (truth.r_peaks_s < t[-1] - 0.15)]
        assert len(inside) >= 20
        for r in inside:
            window = np.flatnonzero(np.abs(t - r) <= 0.1)
            t_max = t[window[np.argmax(ecg[window])]]
            assert abs(t_max - r) <= 0.01 + 1e-9


def test_airflow_and_rates(written):
    folder, truth = written
    data = _load(folder, 0)
    assert np.all(data[:, 16:18] >= 0)
    assert data[:, 17].max() > 20  # expiratory peak ~30 L/min
    assert truth.heart_rate_hz == pytest.approx(CONFIG.heart_rate_hz, rel=0.1)
    assert truth.resp_rate_hz == pytest.approx(CONFIG.resp_rate_hz, rel=0.03)


def test_points_lie_on_the_subxiphoid_reach(written):
    _, truth = written
    heart = make_heart(CONFIG)
    u_c, half, _ = reachable_patch(heart)
    d = np.array([0.0, -1.0, -0.6]) / np.linalg.norm([0.0, -1.0, -0.6])
    for p in truth.points:
        assert REACH_V[0] <= p.v <= REACH_V[1]
        assert abs((p.u - u_c + 0.5) % 1.0 - 0.5) <= half + 1e-12
        assert p.normal_patient @ d > -0.4  # never the posterior wall
    normals = np.array([p.normal_patient for p in truth.points])
    assert normals.mean(axis=0) @ d > 0.2
    # well spread: no two points closer than 15 mm on a ~120 mm heart
    ref = np.array([p.reference_heart_mm for p in truth.points])
    dist = np.linalg.norm(ref[:, None] - ref[None], axis=-1) + 1e3 * np.eye(len(ref))
    assert dist.min() > 15.0


def test_positions_at_matches_recorded_image_positions(written):
    _, truth = written
    heart = make_heart(CONFIG)
    p = truth.positions_at(heart, CONFIG.gating_target_phase, CONFIG.image_resp_phase)
    np.testing.assert_allclose(p, [q.position_patient_mm for q in truth.points], atol=1e-9)
    pos, R = truth.frames_at(heart, CONFIG.gating_target_phase, CONFIG.image_resp_phase)
    np.testing.assert_allclose(R[..., 2], [q.normal_patient for q in truth.points], atol=1e-9)
    moved = truth.positions_at(heart, 0.2, 0.8)
    assert np.all(np.linalg.norm(moved - p, axis=1) > 0.5)  # the heart moves


def test_truth_is_json_ready(written):
    _, truth = written
    d = json.loads(json.dumps(truth.to_dict()))
    assert len(d["points"]) == N_POINTS
    np.testing.assert_array_equal(d["T_patient_from_probe"], truth.T_patient_from_probe)
    assert set(d["points"][0]) >= {"id", "u", "v", "position_patient_mm", "normal_patient"}


def test_same_seed_same_bytes_and_rewrite_replaces(tmp_path, written):
    folder, _ = written
    write_session(tmp_path / "a", CONFIG, seed=3, n_points=N_POINTS, duration_s=DURATION_S)
    assert _digest(tmp_path / "a" / "session") == _digest(folder)
    # writing again into the same place replaces the session atomically
    write_session(tmp_path / "a", CONFIG, seed=4, n_points=2, duration_s=12.0)
    again = _digest(tmp_path / "a" / "session")
    assert len([f for f in again if f.startswith("points")]) == 2
    assert [p.name for p in (tmp_path / "a").iterdir()] == ["session"]


def test_refuses_bad_arguments(tmp_path):
    with pytest.raises(ValueError, match="n_points must be at least 1"):
        write_session(tmp_path, CONFIG, n_points=0)
    with pytest.raises(TypeError, match="config must be a PhantomConfig"):
        write_session(tmp_path, {"n_points": 3})
    (tmp_path / "session").mkdir()
    (tmp_path / "session" / "notes.txt").write_text("mine")
    with pytest.raises(FileExistsError, match="not a heartreg session"):
        write_session(tmp_path, CONFIG, n_points=1, duration_s=12.0)
    assert (tmp_path / "session" / "notes.txt").read_text() == "mine"
