"""Motion and noise of the phantom's intra-operative session.

The tracker's pose over the patient, the patient's slow drift on the table,
the probe's chest-wall breathing, the 3 x 3 staples' breathing
(:func:`chest_wall_displacement`), tracker noise on each measured pose, and the
stylus held on each staple over a breath (format 2's fiducial trace).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from heartreg.phantom.config import PhantomConfig
from heartreg.phantom.geometry import apply, poses
from heartreg.phantom.heart import respiratory_waveform
from heartreg.phantom.layout import T_fiducial_shift, fiducials_patient_mm
from heartreg.phantom.session_format import (
    FIDUCIAL_TRACE_COLUMNS,
    FIDUCIAL_TRACE_FILE,
    _TRACE_ROW_FORMAT,
    _as_written,
    _format_rows,
    _parse_pose_columns,
    _pose_columns,
)
from heartreg.phantom.signals import phase_from_events, synthesize_airflow

#: slow drift of the patient on the table: amplitudes and periods.
_DRIFT_MM = 1.5
_DRIFT_DEG = 0.3
_DRIFT_PERIOD_S = (600.0, 2400.0)
#: stylus moves between staples in this long (s); a breath of lead-in and -out.
_TRANSIT_S = 1.5
#: chest-wall breathing of the 3 x 3 staples: excursion per row (superior to
#: inferior) relative to the mid-sternum staple, the lateral columns' share, the
#: lag of each row (in units of ``chest_wall_lag``), the lateral "bucket handle"
#: and superior "pump handle" parts of the motion relative to the anterior one.
_CHEST_ROW_GAIN = (0.7, 1.0, 1.25)
_CHEST_LATERAL_GAIN = 0.75
_CHEST_ROW_LAG = (0.0, 0.5, 1.0)
_CHEST_LATERAL_SHARE = 0.3
_CHEST_SUPERIOR_SHARE = 0.25


def _T_tracker_from_patient() -> np.ndarray:
    """Tracker field generator ~300 mm from the chest, right-inferior-anterior
    of the probe, axes turned against the patient's."""
    T = np.eye(4)
    R = Rotation.from_euler("xyz", [160.0, 20.0, -35.0], degrees=True)
    origin_patient = np.array([-150.0, -330.0, -160.0])
    T[:3, :3] = R.as_matrix().T
    T[:3, 3] = -R.as_matrix().T @ origin_patient
    return T


def _drift_params(rng):
    periods = rng.uniform(*_DRIFT_PERIOD_S, size=(2, 6))
    phases = rng.uniform(0.0, 2 * np.pi, size=(2, 6))
    return periods, phases


def _T_drift(time_s, params) -> np.ndarray:
    """Slow rigid drift of the patient in the tracker frame, (n, 4, 4)."""
    periods, phases = params  # (2, 6): two sinusoids for each of 6 DOF
    w = np.sin(2 * np.pi * time_s[:, None, None] / periods + phases).mean(axis=1)
    shift = _DRIFT_MM * w[:, :3]
    rotvec = np.deg2rad(_DRIFT_DEG) * w[:, 3:]
    return poses(Rotation.from_rotvec(rotvec).as_matrix(), shift)


def _add_noise(rng, T, position_mm, rotation_deg):
    """Independent tracker noise: position per tracker axis, rotation vector per
    component, applied on the left (tracker frame)."""
    n = T.shape[0]
    dR = Rotation.from_rotvec(np.deg2rad(rotation_deg) * rng.standard_normal((n, 3))).as_matrix()
    return poses(dR @ T[:, :3, :3], T[:, :3, 3] + position_mm * rng.standard_normal((n, 3)))


def chest_wall_displacement(config: PhantomConfig, phase_r) -> np.ndarray:
    """Breathing motion of the 9 staples relative to where the CT saw them.

    Staple ``j`` (documented order) moves by ``A a_j (g(phi_R - l_j) -
    g(phi_R* - l_j)) e_j``: ``A = config.chest_wall_ap_mm``, ``a_j`` its row's
    and column's share (:data:`_CHEST_ROW_GAIN`, :data:`_CHEST_LATERAL_GAIN`),
    ``l_j`` its row's lag (inferior rows lag: abdominal breathing), ``g`` the
    inspiration depth and ``e_j`` anterior with a lateral (outer columns) and a
    superior (top row) part.  The motion is not rigid, so the staples' shape
    changes over the breath and is that of the CT only at phi_R*.

    Parameters
    ----------
    config : PhantomConfig
    phase_r : (n,) float
        Respiration phases.

    Returns
    -------
    (n, 9, 3) float64, mm, patient frame (LPS)
    """
    phase_r = np.atleast_1d(np.asarray(phase_r, dtype=float))
    out = np.zeros(phase_r.shape + (9, 3))
    if config.chest_wall_ap_mm == 0.0:
        return out
    for j in range(9):
        row, col = divmod(j, 3)
        gain = _CHEST_ROW_GAIN[row] * (1.0 if col == 1 else _CHEST_LATERAL_GAIN)
        lag = config.chest_wall_lag * _CHEST_ROW_LAG[row]
        g = respiratory_waveform(phase_r - lag) - respiratory_waveform(config.image_resp_phase - lag)
        direction = np.array(
            [_CHEST_LATERAL_SHARE * (col - 1), -1.0, _CHEST_SUPERIOR_SHARE * (row == 0)]
        )
        out[:, j] = config.chest_wall_ap_mm * gain * g[:, None] * direction
    return out


def _fiducial_schedule(config: PhantomConfig, start_s: float, rate: float):
    """Times and staple of the fiducial trace: a breath of lead-in, each staple
    held ``fiducial_trace_breaths`` breaths with a transit between, a breath out.

    Returns time_s (n,) and fiducial (n,) int (0 while the stylus is in transit).
    """
    period = 1.0 / config.resp_rate_hz
    hold = config.fiducial_trace_breaths * period
    spans = [(0, period + 1.0)]
    for k in range(1, 10):
        spans.append((k, hold))
        spans.append((0, _TRANSIT_S if k < 9 else period + 1.0))
    labels = np.concatenate([np.full(int(round(d * rate)), k) for k, d in spans])
    time_s = np.round(start_s + np.arange(labels.size) / rate, 3)
    return time_s, labels


def _write_fiducial_trace(folder, rng, config, T_star, T_tracker_from_patient, drift, breathing_mm,
                          r_peaks, onsets, time_s, labels, offsets_mm):
    """Write the stylus trace; return the staples as measured, probe frame, (n, 3) mm."""
    noise = config.noise
    rate = config.session_rate_hz
    T_probe_from_patient = np.linalg.inv(T_star)
    phase_r = phase_from_events(time_s, onsets)
    f_ct = fiducials_patient_mm()
    disp = chest_wall_displacement(config, phase_r)  # (n, 9, 3)
    staples = f_ct[None] + disp  # patient frame at the CT's placement of the skin
    shift = T_fiducial_shift(config)
    staples = apply(shift, staples)
    # between staples (and before / after) the stylus glides 20 mm above the skin
    target = np.zeros((labels.size, 3))
    idx = np.clip(labels - 1, 0, 8)
    held = labels > 0
    # in transit: from the last staple held to the next one
    last = np.maximum.accumulate(np.where(held, np.arange(labels.size), 0))
    prev = np.where(held, labels, labels[last])
    prev = np.where(prev == 0, 1, prev)
    target[held] = staples[np.flatnonzero(held), idx[held]]
    free = ~held
    nxt = np.minimum(prev + 1, 9)
    rows = np.flatnonzero(free)
    target[free] = 0.5 * (staples[rows, prev[free] - 1] + staples[rows, nxt[free] - 1]) + [0.0, -20.0, 0.0]
    tip_probe = apply(T_probe_from_patient, target)
    tip_probe[held] += offsets_mm[idx[held]]
    breath = np.zeros((time_s.size, 4, 4))
    breath[:] = np.eye(4)
    breath[:, 2, 3] = breathing_mm * respiratory_waveform(np.nan_to_num(phase_r))
    T_tracker_from_probe = _T_drift(time_s, drift) @ (T_tracker_from_patient @ T_star) @ breath
    tip_tracker = np.einsum("nij,nj->ni", T_tracker_from_probe[:, :3, :3], tip_probe) + T_tracker_from_probe[:, :3, 3]
    tip_meas = tip_tracker + noise.tracker_position_mm * rng.standard_normal(tip_tracker.shape)
    probe_meas = _add_noise(rng, T_tracker_from_probe, noise.tracker_position_mm, noise.tracker_rotation_deg)
    insp, expi = synthesize_airflow(
        rng, onsets, r_peaks, start_s=time_s[0], duration_s=time_s.size / rate, rate_hz=rate,
        noise_lpm=noise.flow_noise_lpm,
    )
    probe_cols = _pose_columns(probe_meas)
    table = np.column_stack([time_s, labels, tip_meas, probe_cols, insp, expi])
    with open(folder / FIDUCIAL_TRACE_FILE, "w", newline="") as fh:
        fh.write(",".join(FIDUCIAL_TRACE_COLUMNS) + "\n")
        fh.write(_format_rows(table, _TRACE_ROW_FORMAT))
    # as a reader sees them: tip in the measured probe frame
    Tp = _parse_pose_columns(_as_written(probe_cols))
    tip_w = np.round(tip_meas, 4)
    measured = np.einsum("nji,nj->ni", Tp[:, :3, :3], tip_w - Tp[:, :3, 3])
    return measured, phase_r
