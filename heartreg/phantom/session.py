"""The phantom's intra-operative session: a ``heartreg-session`` v2 (or v1) folder.

The robot is attached in turn to ``n_points`` points of the epicardium that a
subxiphoid approach reaches (paper section 2.2.4) and logs 30 s of 6-DOF poses
of itself and of the reference probe on the chest (tracker frame, 100 Hz), ECG
and inspiratory/expiratory airflow.  The 9 chest staples are touched with the
tracked stylus.  The format is documented in ``docs/formats.md`` (section
*Session folder*); the reader is :func:`registration.session.read_session`.

Physics and frames:

- one clock (seconds after midnight of the surgery) carries continuous R-peaks
  (heart rate, HRV, ectopic beats) and ventilator expiration onsets; the true
  phases are :func:`~heartreg.phantom.signals.phase_from_events` of them;
- the robot sits on the surface point ``(u, v)`` with its z axis along the
  outward normal and a fixed random yaw about it:
  ``T_patient_from_robot(t)`` from :meth:`AnalyticHeart.surface_frames` at
  ``(phi_C(t), phi_R(t))``;
- the heart's respiratory motion is relative to the reference probe, so
  ``T_probe_from_robot(t) = inv(T*) @ T_patient_from_robot(t)`` with ``T*`` =
  :func:`~heartreg.phantom.layout.T_patient_from_probe`;
- the probe moves in the tracker frame (chest-wall breathing along its z and a
  slow drift of the patient on the table): ``T_tracker_from_robot =
  T_tracker_from_probe(t) @ T_probe_from_robot(t)``, so the probe motion cancels
  exactly in the relative pose;
- each measured pose gets independent tracker noise: position
  ``N(0, tracker_position_mm)`` per tracker axis, rotation ``exp([w]) R`` with
  the rotation vector ``w ~ N(0, tracker_rotation_deg)`` per component;
- fiducials ``f_probe = inv(T*) @ T_fiducial_shift @ (f_ct + c(phi_R)) + o``:
  the CT-to-surgery skin shift, the chest wall's breathing ``c``
  (:func:`chest_wall_displacement`, zero at the CT's phi_R*) and a touch offset
  ``o ~ N(0, fiducial_touch_mm)`` per staple; format 2 records the stylus held on
  each staple over ``fiducial_trace_breaths`` breaths (``fiducial_trace.csv``,
  tracker noise per sample), ``fiducials.csv`` its mid-hold sample.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from heartreg import __version__
from heartreg.phantom.config import PhantomConfig
from heartreg.phantom.geometry import apply, invert, kabsch, poses
from heartreg.phantom.heart import AnalyticHeart, respiratory_waveform
from heartreg.phantom.layout import (
    T_fiducial_shift,
    T_patient_from_probe,
    fiducials_patient_mm,
    make_heart,
)
from heartreg.phantom.signals import (
    expiration_onsets,
    phase_from_events,
    r_peak_times,
    synthesize_airflow,
    synthesize_ecg,
)

__all__ = [
    "SESSION_FORMAT",
    "SESSION_VERSION",
    "SESSION_UNITS",
    "POINT_COLUMNS",
    "FIDUCIAL_COLUMNS",
    "FIDUCIAL_TRACE_COLUMNS",
    "FIDUCIAL_ORDER",
    "chest_wall_displacement",
    "SessionPointTruth",
    "SessionTruth",
    "reachable_patch",
    "write_session",
]

SESSION_FORMAT = "heartreg-session"
SESSION_VERSION = 2
SESSION_UNITS = {"position": "mm", "time": "s", "ecg": "mV", "flow": "L/min"}
POINT_COLUMNS = (
    "time_s",
    "robot_x_mm", "robot_y_mm", "robot_z_mm",
    "robot_qw", "robot_qx", "robot_qy", "robot_qz",
    "probe_x_mm", "probe_y_mm", "probe_z_mm",
    "probe_qw", "probe_qx", "probe_qy", "probe_qz",
    "ecg_mv", "flow_insp_lpm", "flow_exp_lpm",
)  # fmt: skip
FIDUCIAL_COLUMNS = ("fiducial", "x_mm", "y_mm", "z_mm")
#: format 2: the stylus held on each staple over a breath, one continuous record.
FIDUCIAL_TRACE_COLUMNS = (
    "time_s", "fiducial",
    "stylus_x_mm", "stylus_y_mm", "stylus_z_mm",
    "probe_x_mm", "probe_y_mm", "probe_z_mm",
    "probe_qw", "probe_qx", "probe_qy", "probe_qz",
    "flow_insp_lpm", "flow_exp_lpm",
)  # fmt: skip
FIDUCIAL_TRACE_FILE = "fiducial_trace.csv"
FIDUCIAL_ORDER = "rows superior to inferior, within a row patient right to left"

#: written number formats: time, position, quaternion, ECG, flow.
_FMT_TIME, _FMT_POS, _FMT_QUAT, _FMT_ECG, _FMT_FLOW = "%.3f", "%.4f", "%.9f", "%.4f", "%.3f"
_ROW_FORMAT = ",".join(
    [_FMT_TIME] + [_FMT_POS] * 3 + [_FMT_QUAT] * 4 + [_FMT_POS] * 3 + [_FMT_QUAT] * 4
    + [_FMT_ECG, _FMT_FLOW, _FMT_FLOW]
)  # fmt: skip

#: the subxiphoid reach: heart-frame latitude band and arc of u around the
#: direction that faces anterior-inferior (patient LPS: -y and -z).
REACH_V = (0.08, 0.62)
REACH_ARC_DEG = 220.0
_ANTERIOR_INFERIOR = np.array([0.0, -1.0, -0.6]) / np.linalg.norm([0.0, -1.0, -0.6])
#: surgery starts between 08:00 and 10:00; the robot moves 5-20 s between points.
_START_WINDOW_S = (8 * 3600.0, 10 * 3600.0)
_GAP_S = (5.0, 20.0)
#: chest-wall breathing of the probe along its z (mm), and slow drift amplitudes.
_PROBE_BREATHING_MM = (2.0, 4.0)
_DRIFT_MM = 1.5
_DRIFT_DEG = 0.3
_DRIFT_PERIOD_S = (600.0, 2400.0)
_TRACE_ROW_FORMAT = ",".join(
    [_FMT_TIME, "%d"] + [_FMT_POS] * 3 + [_FMT_POS] * 3 + [_FMT_QUAT] * 4 + [_FMT_FLOW, _FMT_FLOW]
)
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
#: separate random stream from the CT writer's, same user seed.
_STREAM = 0x5E55


# --------------------------------------------------------------------- truth
@dataclass(frozen=True, eq=False)
class SessionPointTruth:
    """Ground truth of one attachment point.

    Attributes
    ----------
    point_id : int
        Record id and surface-point id in ``session.json``.
    u, v : float
        Surface coordinates of :meth:`AnalyticHeart.reference_points`.
    yaw_deg : float
        Fixed rotation of the robot about the surface normal.
    reference_heart_mm : (3,) float64
        End-diastolic reference point, heart construction frame.
    position_patient_mm, normal_patient : (3,) float64
        Position (mm) and outward unit normal in the patient frame at
        ``(config.gating_target_phase, config.image_resp_phase)``.
    start_s, end_s : float
        Times of the record's first and last sample, s after midnight.
    heart_rate_hz, resp_rate_hz : float
        Mean rates over the record.
    position_noise_rms_mm : (3,) float64
        RMS per probe axis of measured minus clean ``T_probe_from_robot``
        translation (as written to the file).
    rotation_noise_rms_deg : float
        RMS angle of measured relative to clean ``T_probe_from_robot`` rotation.
    """

    point_id: int
    u: float
    v: float
    yaw_deg: float
    reference_heart_mm: np.ndarray
    position_patient_mm: np.ndarray
    normal_patient: np.ndarray
    start_s: float
    end_s: float
    heart_rate_hz: float
    resp_rate_hz: float
    position_noise_rms_mm: np.ndarray
    rotation_noise_rms_deg: float

    def to_dict(self) -> dict:
        return {
            "id": self.point_id,
            "u": self.u,
            "v": self.v,
            "yaw_deg": self.yaw_deg,
            "reference_heart_mm": self.reference_heart_mm.tolist(),
            "position_patient_mm": self.position_patient_mm.tolist(),
            "normal_patient": self.normal_patient.tolist(),
            "start_s": self.start_s,
            "end_s": self.end_s,
            "heart_rate_hz": self.heart_rate_hz,
            "resp_rate_hz": self.resp_rate_hz,
            "position_noise_rms_mm": self.position_noise_rms_mm.tolist(),
            "rotation_noise_rms_deg": self.rotation_noise_rms_deg,
        }


@dataclass(frozen=True, eq=False)
class SessionTruth:
    """What the session generator knows and the registration must recover.

    Attributes
    ----------
    T_patient_from_probe : (4, 4) float64
        T*, the reference probe in the CT patient frame.
    T_fiducial_shift : (4, 4) float64
        CT-to-surgery skin motion (patient frame): staples in surgery are
        ``T_fiducial_shift @ f_ct``.
    T0_patient_from_probe : (4, 4) float64
        The fiducial registration a correct SVD of the touched (probe frame)
        onto the CT fiducials gives; ~ ``inv(T_fiducial_shift) @ T*``.
    T_tracker_from_patient : (4, 4) float64
        Nominal placement of the tracker (before drift and breathing).
    fiducials_ct_mm, fiducials_probe_mm : (9, 3) float64
        CT staple centres (patient frame) and the touched staples as written
        (probe frame), documented order.
    r_peaks_s, expiration_onsets_s : (n,) float64
        Event times on the session clock, s after midnight.
    image_phase_c, image_phase_r : float
        Phases of ``position_patient_mm`` (the gating target and the CT
        breath-hold phase of the config; the true image phase phi_C* is the
        CT writer's business).
    points : tuple of SessionPointTruth
    probe_breathing_mm : float
        Chest-wall excursion of the probe along its z, full breath.
    position_noise_rms_mm : (3,) float64
        RMS per probe axis over all samples of all points.
    rotation_noise_rms_deg : float
    fiducial_touch_rms_mm : float
        RMS per axis of touched minus true staples (true: where the CT saw them,
        moved by the CT-to-surgery shift; the chest wall's breathing included).
    chest_wall_ap_mm : float
        Sternal anterior excursion over a breath.
    fiducial_touch_phase_r : (9,) float64
        Respiration phase of each single touch (``fiducials.csv``).
    fiducial_trace_file : str
        The stylus trace (format 2), or "" (format 1).
    heart_rate_hz, resp_rate_hz : float
        Means over points of the per-record rates (as the paper's Table 1).
    """

    T_patient_from_probe: np.ndarray
    T_fiducial_shift: np.ndarray
    T0_patient_from_probe: np.ndarray
    T_tracker_from_patient: np.ndarray
    fiducials_ct_mm: np.ndarray
    fiducials_probe_mm: np.ndarray
    r_peaks_s: np.ndarray
    expiration_onsets_s: np.ndarray
    image_phase_c: float
    image_phase_r: float
    points: tuple[SessionPointTruth, ...]
    probe_breathing_mm: float
    position_noise_rms_mm: np.ndarray
    rotation_noise_rms_deg: float
    fiducial_touch_rms_mm: float
    heart_rate_hz: float
    resp_rate_hz: float
    chest_wall_ap_mm: float = 0.0
    fiducial_touch_phase_r: np.ndarray | None = None
    fiducial_trace_file: str = ""

    @property
    def u(self) -> np.ndarray:
        """(n,) float64 surface coordinate u of every point, in point order."""
        return np.array([p.u for p in self.points])

    @property
    def v(self) -> np.ndarray:
        """(n,) float64 surface coordinate v of every point, in point order."""
        return np.array([p.v for p in self.points])

    def positions_at(self, heart: AnalyticHeart, phase_c: float, phase_r: float) -> np.ndarray:
        """Patient-frame positions of all points at ``(phase_c, phase_r)``.

        Parameters
        ----------
        heart : AnalyticHeart
            The phantom heart (``layout.make_heart(config)``).
        phase_c, phase_r : float
            Cardiac and respiration phases in [0, 1).

        Returns
        -------
        (n, 3) float64, mm, patient frame
        """
        u, v = self.u, self.v
        return heart.surface_points(u, v, np.full(u.shape, phase_c), np.full(u.shape, phase_r))

    def frames_at(self, heart: AnalyticHeart, phase_c: float, phase_r: float):
        """Positions (n, 3) mm and surface frames (n, 3, 3) (z the outward normal)
        of all points at ``(phase_c, phase_r)``, patient frame."""
        u, v = self.u, self.v
        return heart.surface_frames(u, v, np.full(u.shape, phase_c), np.full(u.shape, phase_r))

    def to_dict(self) -> dict:
        """JSON-ready dictionary (lists and floats)."""
        return {
            "T_patient_from_probe": self.T_patient_from_probe.tolist(),
            "T_fiducial_shift": self.T_fiducial_shift.tolist(),
            "T0_patient_from_probe": self.T0_patient_from_probe.tolist(),
            "T_tracker_from_patient": self.T_tracker_from_patient.tolist(),
            "fiducials_ct_mm": self.fiducials_ct_mm.tolist(),
            "fiducials_probe_mm": self.fiducials_probe_mm.tolist(),
            "r_peaks_s": self.r_peaks_s.tolist(),
            "expiration_onsets_s": self.expiration_onsets_s.tolist(),
            "image_phase_c": self.image_phase_c,
            "image_phase_r": self.image_phase_r,
            "points": [p.to_dict() for p in self.points],
            "probe_breathing_mm": self.probe_breathing_mm,
            "position_noise_rms_mm": self.position_noise_rms_mm.tolist(),
            "rotation_noise_rms_deg": self.rotation_noise_rms_deg,
            "fiducial_touch_rms_mm": self.fiducial_touch_rms_mm,
            "heart_rate_hz": self.heart_rate_hz,
            "resp_rate_hz": self.resp_rate_hz,
            "chest_wall_ap_mm": self.chest_wall_ap_mm,
            "fiducial_touch_phase_r": (
                None if self.fiducial_touch_phase_r is None else self.fiducial_touch_phase_r.tolist()
            ),
            "fiducial_trace_file": self.fiducial_trace_file,
        }


# -------------------------------------------------------------------- layout
def reachable_patch(heart: AnalyticHeart, *, phase_c: float = 0.7, phase_r: float = 0.3):
    """The subxiphoid reach on the epicardium as a box in (u, v).

    The arc of u is ``REACH_ARC_DEG`` wide, centred on the angle whose outward
    normals, averaged over the latitude band ``REACH_V``, face most
    anterior-inferior (patient -y, -z) at the given phases.

    Returns
    -------
    u_centre : float
        Centre of the arc, in [0, 1).
    half_width_u : float
        Half the arc, in units of u.
    v_range : (float, float)
    """
    n_u, n_v = 360, 12
    u = np.repeat(np.arange(n_u) / n_u, n_v)
    v = np.tile(np.linspace(REACH_V[0], REACH_V[1], n_v), n_u)
    _, R = heart.surface_frames(u, v, np.full(u.shape, phase_c), np.full(u.shape, phase_r))
    score = (R[..., 2] @ _ANTERIOR_INFERIOR).reshape(n_u, n_v).mean(axis=1)
    return float(np.argmax(score) / n_u), REACH_ARC_DEG / 720.0, REACH_V


def _spread_points(rng, heart, n, u_centre, half_width_u, v_range):
    """Farthest-point sample of ``n`` (u, v) in the patch, then ordered along a
    greedy nearest-neighbour path from the point nearest the apex (the order a
    surgeon would visit them)."""
    m = max(2000, 40 * n)
    u = u_centre + rng.uniform(-half_width_u, half_width_u, m)
    v = rng.uniform(v_range[0], v_range[1], m)
    p = heart.reference_points(np.mod(u, 1.0), v)
    chosen = [int(rng.integers(m))]
    dist = np.linalg.norm(p - p[chosen[0]], axis=1)
    for _ in range(n - 1):
        k = int(np.argmax(dist))
        chosen.append(k)
        dist = np.minimum(dist, np.linalg.norm(p - p[k], axis=1))
    chosen = np.asarray(chosen)
    q = p[chosen]
    order = [int(np.argmin(v[chosen]))]
    left = set(range(n)) - set(order)
    while left:
        rest = np.fromiter(sorted(left), dtype=int)
        k = int(rest[np.argmin(np.linalg.norm(q[rest] - q[order[-1]], axis=1))])
        order.append(k)
        left.remove(k)
    idx = chosen[order]
    return np.mod(u[idx], 1.0), v[idx]


# ------------------------------------------------------------ motion helpers
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


def _pose_columns(T):
    """(n, 7): x, y, z (mm) and scalar-first unit quaternion w, x, y, z (w >= 0)."""
    q = Rotation.from_matrix(T[:, :3, :3]).as_quat(canonical=True, scalar_first=True)
    return np.hstack([T[:, :3, 3], q])


def _as_written(cols):
    """Pose columns rounded as the CSV writes them."""
    return np.hstack([np.round(cols[:, :3], 4), np.round(cols[:, 3:], 9)])


def _parse_pose_columns(cols):
    """Inverse of :func:`_pose_columns` after rounding to the written precision."""
    q = cols[:, 3:]
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    return poses(Rotation.from_quat(q, scalar_first=True).as_matrix(), cols[:, :3])


def _rate_in(events, start, end) -> float:
    inside = events[(events >= start) & (events <= end)]
    if len(inside) < 2:
        return float("nan")
    return float((len(inside) - 1) / (inside[-1] - inside[0]))


def _format_rows(values: np.ndarray, fmt: str) -> str:
    return "".join(fmt % tuple(row) + "\n" for row in values.tolist())


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


# -------------------------------------------------------------------- writer
def write_session(
    out_dir: Path,
    config: PhantomConfig,
    *,
    seed: int = 0,
    progress: bool = False,
    n_points: int | None = None,
    duration_s: float | None = None,
) -> SessionTruth:
    """Write the intra-operative session folder ``out_dir / 'session'``.

    The folder is assembled under a temporary name in ``out_dir`` and renamed
    when complete, so it is never seen half-written.  An existing
    ``out_dir / 'session'`` that is a heartreg session is replaced.

    Parameters
    ----------
    out_dir : Path
        Existing or new directory.
    config : PhantomConfig
    seed : int
        Seed of every random choice; the same seed and config give identical bytes.
    progress : bool
        Show a progress bar on stderr.
    n_points : int, optional
        Number of attachment points (default ``config.n_points``).
    duration_s : float, optional
        Length of each record in s (default ``config.session_duration_s``).

    Returns
    -------
    SessionTruth
    """
    if not isinstance(config, PhantomConfig):
        raise TypeError(f"config must be a PhantomConfig, got {type(config).__name__}")
    n_points = config.n_points if n_points is None else int(n_points)
    duration_s = config.session_duration_s if duration_s is None else float(duration_s)
    if n_points < 1:
        raise ValueError(f"n_points must be at least 1, got {n_points}")
    if not duration_s * config.session_rate_hz >= 2:
        raise ValueError(f"duration_s must give at least 2 samples, got {duration_s} s")
    out_dir = Path(out_dir)
    final = out_dir / "session"
    if final.exists() and not _is_session(final):
        raise FileExistsError(
            f"{final} exists and is not a heartreg session; move it away or choose another out_dir"
        )
    out_dir.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".session-", dir=out_dir))
    mask = os.umask(0)
    os.umask(mask)
    os.chmod(tmp, 0o777 & ~mask)  # mkdtemp makes it private; the output is not
    try:
        tmp.chmod(0o755)  # mkdtemp makes it private; a session is an ordinary folder
        truth = _write(tmp, config, seed, progress, n_points, duration_s)
        if final.exists():
            old = Path(tempfile.mkdtemp(prefix=".session-old-", dir=out_dir))
            final.rename(old / "session")
            tmp.rename(final)
            shutil.rmtree(old)
        else:
            tmp.rename(final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return truth


def _is_session(path: Path) -> bool:
    try:
        meta = json.loads((path / "session.json").read_text())
    except (OSError, ValueError):
        return False
    return isinstance(meta, dict) and meta.get("format") == SESSION_FORMAT


def _write(folder: Path, config, seed, progress, n_points, duration_s) -> SessionTruth:
    rng = np.random.default_rng([int(seed), _STREAM])
    rate = config.session_rate_hz
    n_samples = int(round(duration_s * rate))
    heart = make_heart(config)
    T_star = T_patient_from_probe()
    T_probe_from_patient = np.linalg.inv(T_star)
    T_tracker_from_patient = _T_tracker_from_patient()
    noise = config.noise

    # --- where and when
    u_c, half_u, v_range = reachable_patch(
        heart, phase_c=config.gating_target_phase, phase_r=config.image_resp_phase
    )
    u, v = _spread_points(rng, heart, n_points, u_c, half_u, v_range)
    yaw_deg = rng.uniform(-180.0, 180.0, n_points)
    first = round(rng.uniform(*_START_WINDOW_S), 2)
    starts = [first]
    for gap in rng.uniform(*_GAP_S, n_points - 1):
        starts.append(round(starts[-1] + (n_samples - 1) / rate + gap, 2))
    starts = np.asarray(starts)
    end_all = starts[-1] + (n_samples - 1) / rate
    trace = config.fiducial_trace_breaths > 0
    span_start = starts[0]
    if trace:  # the staples are traced before the robot goes in
        t_fid, labels = _fiducial_schedule(config, 0.0, rate)
        span_start = round(starts[0] - t_fid[-1] - rng.uniform(30.0, 90.0), 2)
        t_fid = np.round(t_fid + span_start, 3)
    r_peaks = r_peak_times(
        rng,
        start_s=span_start,
        end_s=end_all,
        heart_rate_hz=config.heart_rate_hz,
        hrv_fraction=config.hrv_fraction,
        ectopic_probability=config.ectopic_probability,
        resp_rate_hz=config.resp_rate_hz,
    )
    onsets = expiration_onsets(rng, start_s=span_start, end_s=end_all, resp_rate_hz=config.resp_rate_hz)
    breathing_mm = float(rng.uniform(*_PROBE_BREATHING_MM))
    drift = _drift_params(rng)

    # --- fiducials
    f_ct = fiducials_patient_mm()
    T_probe_from_staples = T_probe_from_patient @ T_fiducial_shift(config)
    f_clean = apply(T_probe_from_staples, f_ct)
    touch_phase = np.full(9, float(config.image_resp_phase))
    if trace:
        offsets = noise.fiducial_hold_mm * rng.standard_normal(f_ct.shape)
        measured, phase_fid = _write_fiducial_trace(
            folder, rng, config, T_star, T_tracker_from_patient, drift, breathing_mm,
            r_peaks, onsets, t_fid, labels, offsets,
        )
        # the single touch of each staple (format 1's fiducials.csv): mid-hold
        f_probe = np.empty_like(f_ct)
        for k in range(9):
            rows = np.flatnonzero(labels == k + 1)
            mid = rows[rows.size // 2]
            touch = noise.fiducial_touch_mm * rng.standard_normal(3) - offsets[k]
            f_probe[k] = np.round(measured[mid] + touch, 4)
            touch_phase[k] = phase_fid[mid]
    else:
        f_probe = np.round(f_clean + noise.fiducial_touch_mm * rng.standard_normal(f_ct.shape), 4)
    T0 = kabsch(f_probe, f_ct)

    (folder / "points").mkdir()
    points_meta, point_truths = [], []
    sq_pos, sq_rot, n_total = np.zeros(3), 0.0, 0
    iterator = range(n_points)
    if progress:
        from tqdm import tqdm

        iterator = tqdm(iterator, desc="session points", unit="point")
    yaw_R = Rotation.from_euler("z", yaw_deg[:, None], degrees=True).as_matrix()
    for i in iterator:
        time_s = np.round(starts[i] + np.arange(n_samples) / rate, 3)
        phase_c = phase_from_events(time_s, r_peaks)
        phase_r = phase_from_events(time_s, onsets)
        uu, vv = np.full(n_samples, u[i]), np.full(n_samples, v[i])
        p_pat, R_pat = heart.surface_frames(uu, vv, phase_c, phase_r)
        T_patient_from_robot = poses(R_pat @ yaw_R[i], p_pat)
        T_probe_from_robot = T_probe_from_patient @ T_patient_from_robot
        breath = np.zeros((n_samples, 4, 4))
        breath[:] = np.eye(4)
        breath[:, 2, 3] = breathing_mm * respiratory_waveform(phase_r)
        T_tracker_from_probe = _T_drift(time_s, drift) @ (T_tracker_from_patient @ T_star) @ breath
        T_tracker_from_robot = T_tracker_from_probe @ T_probe_from_robot
        meas_robot = _add_noise(rng, T_tracker_from_robot, noise.tracker_position_mm, noise.tracker_rotation_deg)
        meas_probe = _add_noise(rng, T_tracker_from_probe, noise.tracker_position_mm, noise.tracker_rotation_deg)
        ecg = synthesize_ecg(
            rng,
            r_peaks,
            start_s=time_s[0],
            duration_s=n_samples / rate,
            rate_hz=rate,
            noise_mv=noise.ecg_noise_mv,
            wander_mv=noise.ecg_wander_mv,
            resp_rate_hz=config.resp_rate_hz,
        )
        insp, expi = synthesize_airflow(
            rng,
            onsets,
            r_peaks,
            start_s=time_s[0],
            duration_s=n_samples / rate,
            rate_hz=rate,
            noise_lpm=noise.flow_noise_lpm,
        )
        robot_cols = _pose_columns(meas_robot)
        probe_cols = _pose_columns(meas_probe)
        table = np.column_stack([time_s, robot_cols, probe_cols, ecg, insp, expi])
        name = f"points/point_{i:03d}.csv"
        with open(folder / name, "w", newline="") as fh:
            fh.write(",".join(POINT_COLUMNS) + "\n")
            fh.write(_format_rows(table, _ROW_FORMAT))

        # effective noise of the relative pose, as written
        Tr = _parse_pose_columns(_as_written(robot_cols))
        Tp = _parse_pose_columns(_as_written(probe_cols))
        T_meas = invert(Tp) @ Tr
        d_pos = T_meas[:, :3, 3] - T_probe_from_robot[:, :3, 3]
        d_rot = Rotation.from_matrix(
            np.swapaxes(T_probe_from_robot[:, :3, :3], 1, 2) @ T_meas[:, :3, :3]
        ).magnitude()
        sq_pos += (d_pos**2).sum(axis=0)
        sq_rot += float((d_rot**2).sum())
        n_total += n_samples

        p_img, R_img = heart.surface_frames(
            np.array([u[i]]),
            np.array([v[i]]),
            np.array([config.gating_target_phase]),
            np.array([config.image_resp_phase]),
        )
        point_truths.append(
            SessionPointTruth(
                point_id=i,
                u=float(u[i]),
                v=float(v[i]),
                yaw_deg=float(yaw_deg[i]),
                reference_heart_mm=heart.reference_points(np.array([u[i]]), np.array([v[i]]))[0],
                position_patient_mm=p_img[0],
                normal_patient=R_img[0, :, 2],
                start_s=float(time_s[0]),
                end_s=float(time_s[-1]),
                heart_rate_hz=_rate_in(r_peaks, time_s[0], time_s[-1]),
                resp_rate_hz=_rate_in(onsets, time_s[0], time_s[-1]),
                position_noise_rms_mm=np.sqrt((d_pos**2).mean(axis=0)),
                rotation_noise_rms_deg=float(np.rad2deg(np.sqrt((d_rot**2).mean()))),
            )
        )
        points_meta.append({"id": i, "file": name, "surface_point": i})

    with open(folder / "fiducials.csv", "w", newline="") as fh:
        fh.write(",".join(FIDUCIAL_COLUMNS) + "\n")
        for k, row in enumerate(f_probe, start=1):
            fh.write(f"{k:d}," + ",".join(_FMT_POS % x for x in row) + "\n")

    meta = {
        "format": SESSION_FORMAT,
        "version": SESSION_VERSION if trace else 1,
        "units": SESSION_UNITS,
        "quaternion_order": "wxyz",
        "frames": {"poses": "tracker"},
        "sample_rate_hz": rate,
        "points": points_meta,
        "fiducials_file": "fiducials.csv",
        "fiducial_order": FIDUCIAL_ORDER,
        "generator": f"heartreg phantom {__version__}",
    }
    if trace:
        meta["fiducial_trace_file"] = FIDUCIAL_TRACE_FILE
    (folder / "session.json").write_text(json.dumps(meta, indent=2) + "\n")

    hr = np.array([p.heart_rate_hz for p in point_truths])
    rr = np.array([p.resp_rate_hz for p in point_truths])
    return SessionTruth(
        T_patient_from_probe=T_star,
        T_fiducial_shift=T_fiducial_shift(config),
        T0_patient_from_probe=T0,
        T_tracker_from_patient=T_tracker_from_patient,
        fiducials_ct_mm=f_ct,
        fiducials_probe_mm=f_probe,
        r_peaks_s=r_peaks,
        expiration_onsets_s=onsets,
        image_phase_c=float(config.gating_target_phase),
        image_phase_r=float(config.image_resp_phase),
        points=tuple(point_truths),
        probe_breathing_mm=breathing_mm,
        position_noise_rms_mm=np.sqrt(sq_pos / n_total),
        rotation_noise_rms_deg=float(np.rad2deg(np.sqrt(sq_rot / n_total))),
        fiducial_touch_rms_mm=float(np.sqrt(np.mean((f_probe - f_clean) ** 2))),
        heart_rate_hz=float(np.nanmean(hr)),
        resp_rate_hz=float(np.nanmean(rr)),
        chest_wall_ap_mm=float(config.chest_wall_ap_mm),
        fiducial_touch_phase_r=touch_phase,
        fiducial_trace_file=FIDUCIAL_TRACE_FILE if trace else "",
    )
