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
  (:func:`~heartreg.phantom.session_motion.chest_wall_displacement`, zero at the CT's phi_R*) and a touch offset
  ``o ~ N(0, fiducial_touch_mm)`` per staple; format 2 records the stylus held on
  each staple over ``fiducial_trace_breaths`` breaths (``fiducial_trace.csv``,
  tracker noise per sample), ``fiducials.csv`` its mid-hold sample.

The written format is :mod:`~heartreg.phantom.session_format`, the motions and
noise :mod:`~heartreg.phantom.session_motion`, the returned truth
:mod:`~heartreg.phantom.session_truth`.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
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
from heartreg.phantom.session_format import (
    FIDUCIAL_COLUMNS,
    FIDUCIAL_ORDER,
    FIDUCIAL_TRACE_COLUMNS,
    FIDUCIAL_TRACE_FILE,
    POINT_COLUMNS,
    SESSION_FORMAT,
    SESSION_UNITS,
    SESSION_VERSION,
    _FMT_POS,
    _ROW_FORMAT,
    _as_written,
    _format_rows,
    _parse_pose_columns,
    _pose_columns,
)
from heartreg.phantom.session_motion import (
    _T_drift,
    _T_tracker_from_patient,
    _add_noise,
    _drift_params,
    _fiducial_schedule,
    _write_fiducial_trace,
    chest_wall_displacement,
)
from heartreg.phantom.session_truth import SessionPointTruth, SessionTruth
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


#: the subxiphoid reach: heart-frame latitude band and arc of u around the
#: direction that faces anterior-inferior (patient LPS: -y and -z).
REACH_V = (0.08, 0.62)
REACH_ARC_DEG = 220.0
_ANTERIOR_INFERIOR = np.array([0.0, -1.0, -0.6]) / np.linalg.norm([0.0, -1.0, -0.6])
#: surgery starts between 08:00 and 10:00; the robot moves 5-20 s between points.
_START_WINDOW_S = (8 * 3600.0, 10 * 3600.0)
_GAP_S = (5.0, 20.0)
#: chest-wall breathing of the probe along its z (mm).
_PROBE_BREATHING_MM = (2.0, 4.0)
#: separate random stream from the CT writer's, same user seed.
_STREAM = 0x5E55


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


def _rate_in(events, start, end) -> float:
    inside = events[(events >= start) & (events <= end)]
    if len(inside) < 2:
        return float("nan")
    return float((len(inside) - 1) / (inside[-1] - inside[0]))


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
        window = {"start_s": time_s[0], "duration_s": n_samples / rate, "rate_hz": rate}
        ecg = synthesize_ecg(
            rng,
            r_peaks,
            **window,
            noise_mv=noise.ecg_noise_mv,
            wander_mv=noise.ecg_wander_mv,
            resp_rate_hz=config.resp_rate_hz,
        )
        insp, expi = synthesize_airflow(rng, onsets, r_peaks, **window, noise_lpm=noise.flow_noise_lpm)
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
