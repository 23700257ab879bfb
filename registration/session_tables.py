"""Reading the files of a session folder: tables, point records, poses, fiducials.

The checks behind :func:`registration.session.read_session`: every CSV's
header, numbers, units and clock, the quaternions, the PLUS sequence poses,
the touched and the traced fiducials, each refused with a
:class:`~registration.session_format.SessionError` naming the file, the
column and the row.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path, PurePosixPath

import numpy as np
from scipy.spatial.transform import Rotation

from hrcore.geometry import frozen, interpolate_poses
from registration.fiducial import collinear
from registration.plus import PlusFileError, read_plus_sequence
from registration.session_format import (
    FIDUCIAL_COLUMNS, FIDUCIAL_ORDER, FIDUCIAL_TRACE_COLUMNS, MAX_ABS, MAX_CSV_BYTES, MIN_SEPARATION_MM,
    MAX_FRAME_GAP, MAX_TIME_OFFSET_S, MIN_TRACKER_RATE_HZ, N_FIDUCIALS, PLUS_TIME_TOL,
    PLUS_TRANSFORMS, POINT_COLUMNS, QUATERNION_TOL, RATE_TOL, SIGNAL_COLUMNS, FiducialTrace, PointRecord,
    SessionError, SessionNotFoundError,
)

def _check_time_offset(meta: dict) -> None:
    """``poses_time_offset_s``, where given (PLUS poses or not): a finite number of at most three centuries."""
    if "poses_time_offset_s" not in meta:
        return
    offset = meta["poses_time_offset_s"]
    if isinstance(offset, bool) or not isinstance(offset, (int, float)) or (isinstance(offset, float)
                                                                         and not math.isfinite(offset)):
        raise SessionError(f"session.json: 'poses_time_offset_s' must be a number of seconds, got {offset!r}")
    if abs(offset) > MAX_TIME_OFFSET_S:  # compared exactly: an integer of hundreds of digits is no float
        shown = (f"{offset:.6g}" if isinstance(offset, float) or abs(offset) < 1e300 else
                 f"{'-' if offset < 0 else ''}1e+{len(str(abs(offset))) - 1}")
        raise SessionError(f"session.json: 'poses_time_offset_s' is {shown} s, more than the "
                           f"{MAX_TIME_OFFSET_S:g} s (three centuries) two clocks can differ by: give the PLUS "
                           "clock's offset from the signals' clock in seconds")


def _check_relative(file: Path, key: str, name: str) -> None:
    p = PurePosixPath(name)
    if p.is_absolute() or ".." in p.parts or "\\" in name:
        raise SessionError(
            f"{file}: {key} = {name!r} must be a relative path inside the session folder, "
            "with '/' separators"
        )


def _read_header(file: Path, rel: str, required) -> list[int]:
    if file.exists() and not file.is_file():
        raise SessionError(f"{rel} is not a regular file (a folder, named pipe or device); give the CSV file")
    try:
        with open(file, encoding="utf-8-sig", newline="") as fh:  # -sig: Excel's "CSV UTF-8" BOM
            header = fh.readline(1 << 16)
    except FileNotFoundError:
        raise SessionNotFoundError(f"{rel} is listed in session.json but missing from the folder") from None
    except UnicodeDecodeError:
        raise SessionError(f"{rel}: not a UTF-8 text CSV file") from None
    if not header.strip():
        raise SessionError(f"{rel} is empty; record the point again or remove it from session.json")
    names = [c.strip() for c in header.strip().split(",")]
    if len(names) == 1 and any(sep in header for sep in ";\t"):
        raise SessionError(f"{rel}: columns separated by ';' or tabs; save it as comma-separated CSV")
    dupes = sorted({c for c in names if names.count(c) > 1})
    if dupes:
        raise SessionError(f"{rel}: header repeats column(s) {', '.join(dupes)}")
    missing = [c for c in required if c not in names]
    if missing:
        raise SessionError(
            f"{rel}: missing column(s) {', '.join(missing)}; the header must hold "
            f"{', '.join(required)}"
        )
    return [names.index(c) for c in required]


def _load_table(file: Path, rel: str, usecols: list[int], names) -> np.ndarray:
    # every row must have the header's number of fields: np.loadtxt with usecols
    # would read a row with an extra field shifted, without a word
    size = file.stat().st_size
    if size > MAX_CSV_BYTES:
        raise SessionError(
            f"{rel} holds {size / 1e6:.0f} MB, more than the {MAX_CSV_BYTES / 1e6:.0f} MB of hours of "
            "samples; split the record or check that it is the right file"
        )
    lines = [line for line in file.read_bytes().splitlines() if line.strip()]
    if lines:
        width = lines[0].count(b",")
        if any(line.count(b",") != width for line in lines[1:]):
            raise SessionError(_locate_bad_cell(file, rel, usecols, names) or f"{rel}: rows differ in field count")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "Empty input file"
            data = np.loadtxt(file, delimiter=",", skiprows=1, usecols=usecols, ndmin=2, dtype=np.float64)
    except ValueError as exc:
        raise SessionError(_locate_bad_cell(file, rel, usecols, names) or f"{rel}: {exc}") from None
    return data


def _locate_bad_cell(file: Path, rel: str, usecols: list[int], names) -> str | None:
    """Slow path after a parse failure: the first line that does not parse."""
    with open(file, encoding="utf-8-sig", errors="replace", newline="") as fh:  # bad bytes: a bad cell
        width = len(fh.readline().split(","))
        for line_no, line in enumerate(fh, start=2):
            if not line.strip():
                continue
            cells = line.rstrip("\r\n").split(",")
            if len(cells) != width:
                return f"{rel}: line {line_no} has {len(cells)} fields, the header has {width}"
            for col, name in zip(usecols, names):
                try:
                    float(cells[col])
                except ValueError:
                    return (
                        f"{rel}: column {name!r}, row {line_no - 1} (line {line_no}): "
                        f"{cells[col].strip()!r} is not a number"
                    )
    return None


def _check_finite(data: np.ndarray, rel: str, columns) -> None:
    bad = ~np.isfinite(data)
    if bad.any():
        row, col = np.argwhere(bad)[0]
        raise SessionError(
            f"{rel}: column {columns[col]!r}, row {row + 1} (line {row + 2}): value "
            f"{float(data[row, col])!r} is not finite ({int(bad.sum())} such values in the file); "
            "remove the row or record it again"
        )


def _unit_of(column: str) -> str:
    for suffix, unit in (("_mm", "mm"), ("_s", "s"), ("_mv", "mV"), ("_lpm", "L/min")):
        if column.endswith(suffix):
            return unit
    return ""


def _check_magnitude(data: np.ndarray, rel: str, columns) -> None:
    """Refuse values no tracker, clock or amplifier gives (e.g. a pose of 1e30 mm)."""
    limits = np.array([MAX_ABS[_unit_of(c)] for c in columns])
    bad = np.abs(data) > limits
    if bad.any():
        row, col = np.argwhere(bad)[0]
        unit = _unit_of(columns[col])
        raise SessionError(
            f"{rel}: column {columns[col]!r}, row {row + 1} (line {row + 2}): value "
            f"{float(data[row, col]):.6g}{' ' + unit if unit else ''} is beyond the plausible "
            f"{limits[col]:g}{' ' + unit if unit else ''} ({int(bad.sum())} such values in the file); "
            "check the logger's units or remove the point"
        )


def _read_samples(folder: Path, rel: str, columns, rate_hz: float) -> np.ndarray:
    """The checked rows of a sample table: every column there, finite, plausible, on the declared clock."""
    file = folder / rel
    data = _load_table(file, rel, _read_header(file, rel, columns), columns)
    if data.shape[0] and data.shape[1] != len(columns):
        raise SessionError(f"{rel}: expected {len(columns)} columns, read {data.shape[1]}")
    data = data.reshape(-1, len(columns))
    _check_finite(data, rel, columns)
    _check_magnitude(data, rel, columns)
    _check_non_negative(data, rel, columns)
    _check_clock(data[:, 0], rel, rate_hz)
    return data


#: Airflow (L/min) down to this below zero is a flow sensor's zero offset and noise, not a reversed sign (a
#: ventilator's breath peaks at 30-60 L/min).
FLOW_ZERO_TOL_LPM = 1.0


def _check_non_negative(data: np.ndarray, rel: str, columns) -> None:
    """Refuse a negative time (seconds after midnight) or airflow (each line's flow, >= 0 by the format, less a
    sensor's zero offset: :data:`FLOW_ZERO_TOL_LPM`)."""
    which = [k for k, c in enumerate(columns) if c == "time_s" or c.endswith("_lpm")]
    floor = np.array([0.0 if columns[k] == "time_s" else -FLOW_ZERO_TOL_LPM for k in which])
    bad = data[:, which] < floor
    if bad.any():
        row, k = np.argwhere(bad)[0]
        name = columns[which[k]]
        what = ("seconds after midnight of the day of surgery (>= 0): check the logger's clock" if name == "time_s"
                else "the airflow in that line (>= 0; the other line carries the other direction): check the flow "
                     "sensor's sign and zero")
        raise SessionError(
            f"{rel}: column {name!r}, row {row + 1} (line {row + 2}): value {float(data[row, which[k]]):.6g} "
            f"{_unit_of(name)} is negative ({int(bad[:, k].sum())} such values in the column); the format needs "
            f"{what}"
        )


def _point_record(entry: dict, rate_hz: float, time_s, T_probe_from_robot, signals, n_invalid=0) -> PointRecord:
    """The record of ``entry``; ``signals`` (n, 3): ECG mV, inspiratory and expiratory flow L/min."""
    return PointRecord(
        point_id=int(entry["id"]),
        surface_point=int(entry["surface_point"]),
        file=entry["file"],
        time_s=frozen(time_s),
        T_probe_from_robot=frozen(T_probe_from_robot),
        ecg_mv=frozen(signals[:, 0]),
        flow_insp_lpm=frozen(signals[:, 1]),
        flow_exp_lpm=frozen(signals[:, 2]),
        rate_hz=rate_hz,
        n_invalid=int(n_invalid),
    )


def _read_point(folder: Path, entry: dict, rate_hz: float, quaternion_tol: float) -> PointRecord:
    rel = entry["file"]
    data = _read_samples(folder, rel, POINT_COLUMNS, rate_hz)
    q_robot = _unit_quaternions(data[:, 4:8], rel, "robot", quaternion_tol)
    q_probe = _unit_quaternions(data[:, 11:15], rel, "probe", quaternion_tol)
    T = _probe_from_robot(_matrices(q_robot), data[:, 1:4], _matrices(q_probe), data[:, 8:11])
    _check_millimetres(T, rel)
    return _point_record(entry, rate_hz, data[:, 0], T, data[:, 15:18])


def _check_millimetres(T_probe_from_robot: np.ndarray, rel: str) -> None:
    """Refuse a record in metres: its robot sensor would sit within a millimetre of the chest probe."""
    if not len(T_probe_from_robot):
        return
    distance = float(np.median(np.linalg.norm(T_probe_from_robot[:, :3, 3], axis=1)))
    if distance < MIN_SEPARATION_MM:
        raise SessionError(
            f"{rel}: the robot sensor is a median {distance:.3g} mm from the reference probe, closer than two "
            f"tools can be ({MIN_SEPARATION_MM:g} mm): are the positions in metres? the format needs mm "
            "(multiply them by 1000)"
        )


def _check_clock(time_s: np.ndarray, rel: str, rate_hz: float) -> None:
    steps = np.diff(time_s)
    if (steps <= 0).any():
        row = int(np.argmax(steps <= 0)) + 1
        raise SessionError(
            f"{rel}: column 'time_s' is not strictly increasing at row {row + 1} "
            f"(line {row + 2}): {float(time_s[row - 1])!r} then {float(time_s[row])!r}"
        )
    if steps.size:
        median = float(np.median(steps))
        if abs(median * rate_hz - 1.0) > RATE_TOL:
            raise SessionError(
                f"{rel}: column 'time_s' has a median step of {median:.6g} s but session.json "
                f"declares sample_rate_hz = {rate_hz:g}"
            )


def _probe_from_robot(R_robot, t_robot, R_probe, t_probe) -> np.ndarray:
    """(n, 4, 4) ``inv(T_tracker_from_probe) @ T_tracker_from_robot`` from rotations and translations.

    One computation for every pose source, so that the same poses give the same
    bits whether they were read from CSV quaternions or PLUS matrices.
    """
    R_robot = np.ascontiguousarray(R_robot, dtype=np.float64)
    R_probe_T = np.ascontiguousarray(np.swapaxes(R_probe, 1, 2), dtype=np.float64)
    d = np.ascontiguousarray(np.asarray(t_robot, dtype=np.float64) - np.asarray(t_probe, dtype=np.float64))
    T = np.zeros((R_robot.shape[0], 4, 4))
    T[:, :3, :3] = R_probe_T @ R_robot
    T[:, :3, 3] = np.einsum("nij,nj->ni", R_probe_T, d)
    T[:, 3, 3] = 1.0
    return T


def _read_plus_point(folder: Path, entry: dict, rate_hz: float, meta: dict, cache: dict, notes: list,
                     dropped: dict) -> PointRecord:
    """A record whose ECG and flow are in a CSV file and poses in a PLUS sequence file; ``dropped`` gathers, by
    point, the samples left without a pose between a tracker's own frames (samples, of how many) for one note."""
    rel, poses_rel = entry["file"], entry["poses"]
    data = _read_samples(folder, rel, SIGNAL_COLUMNS, rate_hz)
    if poses_rel not in cache:
        if not (folder / poses_rel).is_file():
            raise SessionNotFoundError(f"{poses_rel} is listed in session.json but missing from the folder")
        try:
            cache[poses_rel] = read_plus_sequence(folder / poses_rel)
        except PlusFileError as exc:
            raise SessionError(str(exc)) from None
    seq = cache[poses_rel]
    offset = meta.get("poses_time_offset_s", 0.0)  # a finite number of plausible size (checked with session.json)
    try:
        T_robot, T_probe = (seq.transform(name) for name in PLUS_TRANSFORMS)
    except PlusFileError as exc:
        raise SessionError(str(exc)) from None
    t_frames, t = seq.time_s + float(offset), data[:, 0]
    n = len(t_frames)
    same = np.diff(t_frames) <= 0
    if same.any():  # the shifted times lost the precision that told the frames apart
        k = int(np.argmax(same))
        raise SessionError(f"{poses_rel}: with session.json 'poses_time_offset_s' = {float(offset):.6g} s its frames "
                           f"{k} and {k + 1} fall on one time ({int(same.sum())} such pairs): the offset is too "
                           "large for the timestamps' precision; give the PLUS clock's offset in seconds")
    after = np.searchsorted(t_frames, t)
    lo, hi = np.clip(after - 1, 0, n - 1), np.clip(after, 0, n - 1)
    k = np.where(np.abs(t_frames[lo] - t) <= np.abs(t_frames[hi] - t), lo, hi)
    if np.any(np.abs(t_frames[k] - t) > PLUS_TIME_TOL / rate_hz):
        # the tracker on its own rate or clock: each sample's pose between the frames around it
        if n < 2:
            raise SessionError(f"{poses_rel} holds a single frame, at no sample's time: record the poses over the "
                               "whole point")
        step = float(np.median(np.diff(t_frames)))
        T, have = _poses_between_frames(t_frames, T_robot, T_probe, seq.valid, t, step, rel, poses_rel)
        note = (f"poses interpolated from the PLUS sequence's {1.0 / step:.3g} Hz frames to the samples' "
                f"{rate_hz:g} Hz (translation linear, rotation along the shortest arc)")
        if note not in notes:  # once per sequence rate, not per point
            notes.append(note)
        if not have.all():
            dropped[entry["id"]] = (int((~have).sum()), len(have))
        _check_millimetres(T, poses_rel)
        return _point_record(entry, rate_hz, t[have], T, data[have, 1:4], n_invalid=int((~have).sum()))
    # a frame at every sample's time (within a quarter step): each sample takes it as written
    ok = seq.valid[PLUS_TRANSFORMS[0]][k] & seq.valid[PLUS_TRANSFORMS[1]][k]
    if not ok.all():
        notes.append(f"point {entry['id']}: {int((~ok).sum())} of {len(ok)} samples dropped, "
                     "the tracker marked the pose invalid in its PLUS sequence")  # by kind: a name may name the patient
        data, k = data[ok], k[ok]
    Tr, Tp = T_robot[k], T_probe[k]
    T = _probe_from_robot(Tr[:, :3, :3], Tr[:, :3, 3], Tp[:, :3, :3], Tp[:, :3, 3])
    _check_millimetres(T, poses_rel)
    return _point_record(entry, rate_hz, data[:, 0], T, data[:, 1:4], n_invalid=int((~ok).sum()))


def _poses_between_frames(t_frames, T_robot, T_probe, valid, t, step, rel, poses_rel):
    """``T_probe_from_robot`` at the sample times ``t`` from a tracker's frames on its own rate or clock.

    Each frame's relative pose (both tools seen) is interpolated to the samples
    between it and the next such frame, when they are at most
    :data:`MAX_FRAME_GAP` median frame steps apart (one lost frame is bridged, a
    longer dropout is not): translation linearly, rotation along the shortest
    arc (slerp).  A sample at a frame's time takes that frame's pose as read.

    Returns
    -------
    T : (m, 4, 4) float64
        Poses of the samples that have one.
    have : (n,) bool
        Which samples have a pose.
    """
    rate = 1.0 / step
    if rate < MIN_TRACKER_RATE_HZ:
        raise SessionError(
            f"{poses_rel}: its frames come every {step:.4g} s ({rate:.3g} Hz), too seldom for the heartbeat's "
            f"motion (its fifth harmonic is at 7.5 Hz at 90 beats/min); record the robot and the probe at "
            f"{MIN_TRACKER_RATE_HZ:g} Hz or more (a tracking-only PLUS capture, not the video's frames)"
        )
    reach = MAX_FRAME_GAP * step
    outside = (t < t_frames[0] - reach) | (t > t_frames[-1] + reach)
    if outside.any():  # a tracker recording covers its records: a sample well outside it is on another clock
        row = int(np.argmax(outside))
        raise SessionError(
            f"{rel}: row {row + 1} (time_s {float(t[row]):.3f}) lies outside the frames of {poses_rel} "
            f"({float(t_frames[0]):.3f}-{float(t_frames[-1]):.3f} s; {int(outside.sum())} such rows): a tracker "
            "recording covers its points; if PLUS ran on its own clock, give session.json 'poses_time_offset_s', "
            "if it started late or stopped early, trim the point's rows to its frames"
        )
    seen = valid[PLUS_TRANSFORMS[0]] & valid[PLUS_TRANSFORMS[1]]
    tf = t_frames[seen]
    Tr, Tp = T_robot[seen], T_probe[seen]
    T_f = _probe_from_robot(Tr[:, :3, :3], Tr[:, :3, 3], Tp[:, :3, :3], Tp[:, :3, 3])
    lo = np.searchsorted(tf, t, side="right") - 1  # the last frame at or before each sample
    at_frame = (lo >= 0) & (tf[np.clip(lo, 0, None)] == t) if tf.size else np.zeros(t.shape, bool)
    between = (lo >= 0) & (lo < tf.size - 1)
    lo_c, hi_c = np.clip(lo, 0, max(tf.size - 2, 0)), np.clip(lo + 1, 0, max(tf.size - 1, 0))
    gap = tf[hi_c] - tf[lo_c] if tf.size > 1 else np.zeros(t.shape)
    between &= gap <= reach
    have = at_frame | between
    if not have.any():
        raise SessionError(f"{rel}: no sample lies between frames of {poses_rel} where the tracker saw both the "
                           "robot and the probe")
    # a sample at a frame's time takes that frame's pose as read; the others the arc from the frame before
    start = np.where(at_frame, np.clip(lo, 0, None), lo_c)[have]
    T = T_f[start].copy()
    moved = ~at_frame[have]
    if moved.any():
        a, b = start[moved], hi_c[have][moved]
        T[moved] = interpolate_poses(T_f[a], T_f[b], (t[have][moved] - tf[a]) / (tf[b] - tf[a]))
    return T, have


def _matrices(q_wxyz: np.ndarray) -> np.ndarray:
    if q_wxyz.shape[0] == 0:
        return np.zeros((0, 3, 3))
    return Rotation.from_quat(q_wxyz, scalar_first=True).as_matrix()


def _unit_quaternions(q: np.ndarray, rel: str, sensor: str, tol: float) -> np.ndarray:
    norm = np.linalg.norm(q, axis=1)
    off = np.abs(norm - 1.0) > tol
    if off.any():
        row = int(np.argmax(off))
        raise SessionError(
            f"{rel}: columns {sensor}_qw..{sensor}_qz, row {row + 1} (line {row + 2}): "
            f"quaternion norm {norm[row]:.6g} is not 1 (tolerance {tol:g}; {int(off.sum())} "
            "such rows); check the quaternion order (w, x, y, z) and the logger"
        )
    return q / norm[:, None]


def _read_fiducials(folder: Path, rel: str) -> np.ndarray:
    file = folder / rel
    cols = _read_header(file, rel, FIDUCIAL_COLUMNS)
    data = _load_table(file, rel, cols, FIDUCIAL_COLUMNS)
    if data.shape != (N_FIDUCIALS, len(FIDUCIAL_COLUMNS)):
        raise SessionError(
            f"{rel}: expected {N_FIDUCIALS} fiducial rows of {', '.join(FIDUCIAL_COLUMNS)}, "
            f"got {data.shape[0]} row(s); touch all 9 staples in the documented order"
        )
    _check_finite(data, rel, FIDUCIAL_COLUMNS)
    _check_magnitude(data, rel, FIDUCIAL_COLUMNS)
    spread = float(np.ptp(data[:, 1:4], axis=0).max())
    if spread < MIN_SEPARATION_MM:
        raise SessionError(
            f"{rel}: the 9 staples lie within {spread:.3g} mm of each other, closer than two staples can be "
            f"({MIN_SEPARATION_MM:g} mm): are the positions in metres? the format needs mm (multiply them by 1000)"
        )
    if (s := collinear(data[:, 1:4])) is not None:  # a 3 x 3 grid of staples spans a plane: the touches went wrong
        raise SessionError(
            f"{rel}: the {N_FIDUCIALS} touched staples lie on one line (singular values {s[0]:.3g}, {s[1]:.3g} mm): "
            "the rotation about it is undetermined; touch the staples again, each its own staple, or check the "
            "file's rows"
        )
    labels = data[:, 0]
    if not np.array_equal(labels, np.arange(1, N_FIDUCIALS + 1)):
        raise SessionError(
            f"{rel}: column 'fiducial' must number the staples 1..9 in order ({FIDUCIAL_ORDER}), "
            f"got {labels.tolist()}"
        )
    return frozen(data[:, 1:4])


def _read_fiducial_trace(folder: Path, rel: str, rate_hz: float) -> FiducialTrace:
    file = folder / rel
    cols = _read_header(file, rel, FIDUCIAL_TRACE_COLUMNS)
    data = _load_table(file, rel, cols, FIDUCIAL_TRACE_COLUMNS).reshape(-1, len(FIDUCIAL_TRACE_COLUMNS))
    if not len(data):  # it said all nine staples were 'never held' (an audit)
        raise SessionError(f"{rel} holds a header and no rows; record the trace again, or remove "
                           "'fiducial_trace_file' from session.json to register with the touched fiducials alone")
    _check_finite(data, rel, FIDUCIAL_TRACE_COLUMNS)
    _check_non_negative(data, rel, FIDUCIAL_TRACE_COLUMNS)
    time_s = data[:, 0]
    steps = np.diff(time_s)
    if (steps <= 0).any():
        row = int(np.argmax(steps <= 0)) + 1
        raise SessionError(f"{rel}: column 'time_s' is not strictly increasing at row {row + 1} (line {row + 2})")
    labels = data[:, 1]
    bad = (labels != np.round(labels)) | (labels < 0) | (labels > N_FIDUCIALS)
    if bad.any():
        row = int(np.argmax(bad))
        raise SessionError(
            f"{rel}: column 'fiducial', row {row + 1} (line {row + 2}): {float(labels[row]):g} is not a staple "
            f"number 1..{N_FIDUCIALS} (or 0 in transit)"
        )
    missing = sorted(set(range(1, N_FIDUCIALS + 1)) - set(labels.astype(int).tolist()))
    if missing:
        raise SessionError(f"{rel}: staple(s) {missing} never held; trace all {N_FIDUCIALS} staples")
    q = _unit_quaternions(data[:, 8:12], rel, "probe", QUATERNION_TOL)
    R_probe_T = np.swapaxes(_matrices(q), 1, 2)
    tip = np.einsum("nij,nj->ni", R_probe_T, data[:, 2:5] - data[:, 5:8])
    return FiducialTrace(
        file=rel,
        time_s=frozen(time_s),
        fiducial=frozen(labels, np.int64),
        stylus_probe_mm=frozen(tip),
        flow_insp_lpm=frozen(data[:, 12]),
        flow_exp_lpm=frozen(data[:, 13]),
        rate_hz=rate_hz,
    )
