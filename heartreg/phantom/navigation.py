"""A phantom navigation session: the robot crawls across the beating heart.

After the registration session (the robot held at ~100 points for 30 s each),
an organ-mounted crawler such as HeartLander moves over the epicardium to
places that were *not* among the registered points.  This module writes such
a session and its truth, for :mod:`heartreg.track` to be tested against:

``OUT/navigation/``
    A ``heartreg-session`` v1 folder (``docs/formats.md``) with one record,
    ``points/point_000.csv``, whose ``surface_point`` is ``-1`` (the robot is
    not attached to one point), and freshly touched ``fiducials.csv``.  Same
    heart, reference probe, tracker placement, noise and signal models as the
    registration session (:mod:`heartreg.phantom.session`), on the same clock,
    starting a minute after it.
``OUT/navigation_truth.csv``
    Per sample: ``time_s``, the robot's surface coordinates ``u, v``, its
    true phases ``phase_c, phase_r``, its position *on the map*
    ``map_x_mm, map_y_mm, map_z_mm`` (the surface point at the image phases
    ``(phi_C*, phi_R*)`` of ``truth.json``, CT patient frame, LPS), and
    ``nearest_registered_mm``: the end-diastolic distance to the nearest
    registration point (how far the robot is from any point the registration
    modelled).

The path: the robot rests for ``rest_s`` seconds (so the live phases can
lock on), then crawls at ``speed_mm_s`` along straight lines in (u, v)
between random waypoints of the subxiphoid reach, chosen as far as possible
from the registration points, pausing ``pause_s`` at each.

Like the rest of the phantom, this imports nothing from imaging, modeling or
registration.
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
from heartreg.phantom.config import config_from_dict
from heartreg.phantom.generate import PhantomError
from heartreg.phantom.geometry import apply, poses
from heartreg.phantom.heart import respiratory_waveform
from heartreg.phantom.layout import (
    T_fiducial_shift,
    T_patient_from_probe,
    fiducials_patient_mm,
    make_heart,
)
from heartreg.phantom.session import reachable_patch
from heartreg.phantom.session_format import (
    _FMT_POS,
    _ROW_FORMAT,
    FIDUCIAL_COLUMNS,
    FIDUCIAL_ORDER,
    POINT_COLUMNS,
    SESSION_FORMAT,
    SESSION_UNITS,
    SESSION_VERSION,
    _format_rows,
    _pose_columns,
)
from heartreg.phantom.session_motion import _add_noise, _drift_params, _T_drift, _T_tracker_from_patient
from heartreg.phantom.signals import (
    expiration_onsets,
    phase_from_events,
    r_peak_times,
    synthesize_airflow,
    synthesize_ecg,
)

__all__ = ["NAVIGATION_TRUTH_COLUMNS", "NavigationTruth", "write_navigation"]

NAVIGATION_TRUTH_COLUMNS = (
    "time_s", "u", "v", "phase_c", "phase_r",
    "map_x_mm", "map_y_mm", "map_z_mm", "nearest_registered_mm",
)  # fmt: skip
#: separate random stream from the session's and the CT's, same user seed.
_STREAM = 0x4A7
_START_AFTER_S = 60.0


@dataclass(frozen=True, eq=False)
class NavigationTruth:
    """The truth of a navigation session (what ``navigation_truth.csv`` holds).

    Attributes
    ----------
    time_s, u, v, phase_c, phase_r : (n,) float64
        Sample time (s), surface coordinates, true cardiac and respiration phase.
    map_patient_mm : (n, 3) float64, mm
        The robot's position on the map (image phases), CT patient frame.
    nearest_registered_mm : (n,) float64, mm
        End-diastolic distance to the nearest registration point.
    image_phase_c, image_phase_r : float
        The phases of the map (phi_C*, phi_R* of ``truth.json``).
    """

    time_s: np.ndarray
    u: np.ndarray
    v: np.ndarray
    phase_c: np.ndarray
    phase_r: np.ndarray
    map_patient_mm: np.ndarray
    nearest_registered_mm: np.ndarray
    image_phase_c: float
    image_phase_r: float

    @classmethod
    def read(cls, out_dir, case_dir=None) -> NavigationTruth:
        """Read ``out_dir/navigation_truth.csv`` (and the image phases of the case's
        ``truth.json``; ``case_dir`` defaults to ``out_dir``)."""
        data = np.loadtxt(Path(out_dir) / "navigation_truth.csv", delimiter=",", skiprows=1, ndmin=2)
        truth = json.loads((Path(case_dir or out_dir) / "truth.json").read_text())
        return cls(data[:, 0], data[:, 1], data[:, 2], data[:, 3], data[:, 4], data[:, 5:8], data[:, 8],
                   float(truth["cardiac_phase"]), float(truth["respiration_phase"]))


def _surface_path(rng, heart, n_samples, rate, *, rest_s, speed_mm_s, pause_s, box, avoid_ref):
    """(u, v) of every sample: rest, then straight crawls between waypoints."""
    u_c, half_u, (v_lo, v_hi) = box
    # candidate waypoints inside the reach, kept away from the patch edge
    m = 4000
    cu = u_c + rng.uniform(-0.8 * half_u, 0.8 * half_u, m)
    cv = rng.uniform(v_lo + 0.1 * (v_hi - v_lo), v_hi - 0.1 * (v_hi - v_lo), m)
    ref = heart.reference_points(np.mod(cu, 1.0), cv)
    if avoid_ref is not None and len(avoid_ref):
        d = np.min(np.linalg.norm(ref[:, None] - avoid_ref[None], axis=2), axis=1)
        good = np.flatnonzero(d >= np.percentile(d, 75))  # the places the registration missed
    else:
        good = np.arange(m)
    order = rng.permutation(good)
    u = np.empty(n_samples)
    v = np.empty(n_samples)
    k = int(round(rest_s * rate))
    cur = np.array([cu[order[0]], cv[order[0]]])
    u[:k], v[:k] = cur
    w = 1
    while k < n_samples:
        nxt = np.array([cu[order[w % len(order)]], cv[order[w % len(order)]]])
        w += 1
        # arc length of the straight (u, v) segment on the reference surface
        s = np.linspace(0.0, 1.0, 200)
        seg = heart.reference_points(np.mod(cur[0] + s * (nxt[0] - cur[0]), 1.0), cur[1] + s * (nxt[1] - cur[1]))
        length = float(np.linalg.norm(np.diff(seg, axis=0), axis=1).sum())
        n_move = max(2, int(round(length / speed_mm_s * rate)))
        frac = np.arange(1, n_move + 1) / n_move
        ku = cur[0] + frac * (nxt[0] - cur[0])
        kv = cur[1] + frac * (nxt[1] - cur[1])
        n_pause = int(round(pause_s * rate))
        seg_u = np.concatenate([ku, np.full(n_pause, nxt[0])])
        seg_v = np.concatenate([kv, np.full(n_pause, nxt[1])])
        take = min(seg_u.size, n_samples - k)
        u[k:k + take], v[k:k + take] = seg_u[:take], seg_v[:take]
        k += take
        cur = nxt
    return np.mod(u, 1.0), v


def write_navigation(
    case_dir,
    *,
    out_dir=None,
    duration_s: float = 60.0,
    rest_s: float = 12.0,
    speed_mm_s: float = 3.0,
    pause_s: float = 3.0,
    seed: int | None = None,
) -> NavigationTruth:
    """Write ``navigation/`` and ``navigation_truth.csv`` into a phantom case.

    Parameters
    ----------
    case_dir : path
        A case written by :func:`heartreg.phantom.generate.make_phantom` with
        its session (its ``truth.json`` gives the configuration, the seed, the
        image phases and the registration points).
    out_dir : path, optional
        Where to write (default ``case_dir``); existing navigation outputs
        there are replaced.
    duration_s : float, s
        Length of the record.
    rest_s, pause_s : float, s
        Rest before the first move; pause at each waypoint.
    speed_mm_s : float, mm/s
        Crawling speed over the surface.
    seed : int, optional
        Seed of the path and noise (default: the case's seed).

    Returns
    -------
    NavigationTruth
    """
    case = Path(case_dir)
    try:
        truth = json.loads((case / "truth.json").read_text())
    except (OSError, ValueError) as exc:
        raise PhantomError(f"{case}: no readable truth.json of a phantom case ({exc}); run heartreg phantom first") from None
    if "session" not in truth:
        raise PhantomError(f"{case}: the phantom case has no session (made with --no-session); navigation needs it")
    for name, value in (("duration_s", duration_s), ("speed_mm_s", speed_mm_s)):
        if not (np.isfinite(value) and value > 0):
            raise PhantomError(f"{name} must be positive, got {value!r}")
    if not (0 <= rest_s < duration_s) or pause_s < 0:
        raise PhantomError(f"rest_s must be in [0, duration_s) and pause_s >= 0, got {rest_s!r}, {pause_s!r}")
    config = config_from_dict(truth["config"])  # the anatomy too (a tight field of view, a stent, chambers)
    seed = int(truth["seed"] if seed is None else seed)
    out = case if out_dir is None else Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=".navigation-", dir=out))
    try:
        os.chmod(staging, 0o777 & ~_umask())
        nav = _write(staging, config, truth, seed, duration_s, rest_s, speed_mm_s, pause_s)
        for name in ("navigation", "navigation_truth.csv"):
            dst = out / name
            if dst.is_dir():
                shutil.rmtree(dst)
            elif dst.exists():
                dst.unlink()
            (staging / name).rename(dst)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return nav


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _write(staging, config, truth, seed, duration_s, rest_s, speed_mm_s, pause_s) -> NavigationTruth:
    rng = np.random.default_rng([seed, _STREAM])
    rate = config.session_rate_hz
    n = int(round(duration_s * rate))
    heart = make_heart(config)
    T_star = T_patient_from_probe()
    T_probe_from_patient = np.linalg.inv(T_star)
    noise = config.noise
    points = truth["session"]["points"]
    start = round(max(p["end_s"] for p in points) + _START_AFTER_S, 2)
    time_s = np.round(start + np.arange(n) / rate, 3)
    r_peaks = r_peak_times(
        rng, start_s=time_s[0], end_s=time_s[-1], heart_rate_hz=config.heart_rate_hz,
        hrv_fraction=config.hrv_fraction, ectopic_probability=config.ectopic_probability,
        resp_rate_hz=config.resp_rate_hz,
    )
    onsets = expiration_onsets(rng, start_s=time_s[0], end_s=time_s[-1], resp_rate_hz=config.resp_rate_hz)
    phase_c = phase_from_events(time_s, r_peaks)
    phase_r = phase_from_events(time_s, onsets)

    avoid = np.array([p["reference_heart_mm"] for p in points])
    box = reachable_patch(heart, phase_c=config.gating_target_phase, phase_r=config.image_resp_phase)
    u, v = _surface_path(rng, heart, n, rate, rest_s=rest_s, speed_mm_s=speed_mm_s, pause_s=pause_s,
                         box=box, avoid_ref=avoid)
    yaw = Rotation.from_euler("z", rng.uniform(-180.0, 180.0), degrees=True).as_matrix()
    p_pat, R_pat = heart.surface_frames(u, v, phase_c, phase_r)
    T_probe_from_robot = T_probe_from_patient @ poses(R_pat @ yaw, p_pat)
    breath = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
    breath[:, 2, 3] = truth["session"]["probe_breathing_mm"] * respiratory_waveform(phase_r)
    T_tracker_from_probe = _T_drift(time_s, _drift_params(rng)) @ (_T_tracker_from_patient() @ T_star) @ breath
    meas_robot = _add_noise(rng, T_tracker_from_probe @ T_probe_from_robot,
                            noise.tracker_position_mm, noise.tracker_rotation_deg)
    meas_probe = _add_noise(rng, T_tracker_from_probe, noise.tracker_position_mm, noise.tracker_rotation_deg)
    ecg = synthesize_ecg(
        rng, r_peaks, start_s=time_s[0], duration_s=n / rate, rate_hz=rate,
        noise_mv=noise.ecg_noise_mv, wander_mv=noise.ecg_wander_mv, resp_rate_hz=config.resp_rate_hz,
    )
    insp, expi = synthesize_airflow(
        rng, onsets, r_peaks, start_s=time_s[0], duration_s=n / rate, rate_hz=rate, noise_lpm=noise.flow_noise_lpm,
    )

    folder = staging / "navigation"
    (folder / "points").mkdir(parents=True)
    table = np.column_stack([time_s, _pose_columns(meas_robot), _pose_columns(meas_probe), ecg, insp, expi])
    with open(folder / "points" / "point_000.csv", "w", newline="") as fh:
        fh.write(",".join(POINT_COLUMNS) + "\n")
        fh.write(_format_rows(table, _ROW_FORMAT))
    f_ct = fiducials_patient_mm()
    T_probe_from_staples = T_probe_from_patient @ T_fiducial_shift(config)
    f_probe = apply(T_probe_from_staples, f_ct)
    f_probe = np.round(f_probe + noise.fiducial_touch_mm * rng.standard_normal(f_ct.shape), 4)
    with open(folder / "fiducials.csv", "w", newline="") as fh:
        fh.write(",".join(FIDUCIAL_COLUMNS) + "\n")
        fh.writelines(f"{k:d}," + ",".join(_FMT_POS % x for x in row) + "\n" for k, row in enumerate(f_probe, start=1))
    meta = {
        "format": SESSION_FORMAT,
        "version": SESSION_VERSION,
        "units": SESSION_UNITS,
        "quaternion_order": "wxyz",
        "frames": {"poses": "tracker"},
        "sample_rate_hz": rate,
        "points": [{"id": 0, "file": "points/point_000.csv", "surface_point": -1}],
        "fiducials_file": "fiducials.csv",
        "fiducial_order": FIDUCIAL_ORDER,
        "generator": f"heartreg phantom {__version__} (navigation)",
    }
    (folder / "session.json").write_text(json.dumps(meta, indent=2) + "\n")

    image_c, image_r = float(truth["cardiac_phase"]), float(truth["respiration_phase"])
    on_map = heart.surface_points(u, v, np.full(n, image_c), np.full(n, image_r))
    ref = heart.reference_points(u, v)
    nearest = np.min(np.linalg.norm(ref[:, None] - avoid[None], axis=2), axis=1)
    rows = np.column_stack([time_s, u, v, phase_c, phase_r, on_map, nearest])
    with open(staging / "navigation_truth.csv", "w", newline="") as fh:
        fh.write(",".join(NAVIGATION_TRUTH_COLUMNS) + "\n")
        fh.write(_format_rows(rows, "%.3f,%.9f,%.9f,%.9f,%.9f,%.6f,%.6f,%.6f,%.6f"))
    return NavigationTruth(time_s, u, v, phase_c, phase_r, on_map, nearest, image_c, image_r)
