"""Read an intra-operative session folder (format ``heartreg-session`` v1 or v2).

The format is documented in ``docs/formats.md`` (section *Session folder*).  In
short: ``session.json`` (metadata and the list of point records),
``points/point_NNN.csv`` (one record per attachment point: time, robot and
reference-probe poses in the tracker frame with scalar-first quaternions, ECG,
inspiratory and expiratory flow) and ``fiducials.csv`` (the 9 chest staples as
touched with the tracked stylus, reference-probe frame).  Version 2 adds
``fiducial_trace.csv`` (named by ``fiducial_trace_file``): the stylus held on
each staple over at least a breath, with the probe pose and the airflow, so
that the staples' positions are known as a function of the respiration phase.

:func:`read_session` validates everything and returns the robot poses in the
reference-probe frame, ``T_probe_from_robot = inv(T_tracker_from_probe) @
T_tracker_from_robot``.  A record too short to cover two breaths is not
dropped silently: it is listed in :attr:`Session.exclusions` with the reason.
Anything else that is wrong stops the reading with a :class:`SessionError`
naming the file, the column and the row.

The poses may instead come from a PLUS sequence file (``.seq.mha``,
``.igs.nrrd``; :mod:`registration.plus`): a point entry with a ``poses`` key
names it, and the record's CSV then needs only :data:`SIGNAL_COLUMNS`; each
sample takes the frame with the same timestamp (``RobotToTracker`` and
``ProbeToTracker`` transforms), and samples whose pose the tracker marked
invalid are dropped (said in :attr:`Session.notes`).
"""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import numpy as np
from scipy.spatial.transform import Rotation

from hrcore.errors import HeartregError
from hrcore.geometry import frozen
from registration.plus import PlusFileError, read_plus_sequence

__all__ = [
    "SESSION_FORMAT",
    "SUPPORTED_VERSIONS",
    "SESSION_UNITS",
    "POINT_COLUMNS",
    "FIDUCIAL_COLUMNS",
    "SIGNAL_COLUMNS",
    "PLUS_TRANSFORMS",
    "FIDUCIAL_ORDER",
    "MIN_DURATION_S",
    "QUATERNION_TOL",
    "SessionError",
    "SessionNotFoundError",
    "PointRecord",
    "FiducialTrace",
    "Session",
    "read_session",
]

SESSION_FORMAT = "heartreg-session"
SUPPORTED_VERSIONS = (1, 2)
#: the only units versions 1 and 2 know.
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
#: the columns of a record whose poses are in a PLUS sequence file (entry key ``poses``).
SIGNAL_COLUMNS = ("time_s", "ecg_mv", "flow_insp_lpm", "flow_exp_lpm")
#: the PLUS transforms of the robot sensor and the reference probe (``<From>To<To>``).
PLUS_TRANSFORMS = ("RobotToTracker", "ProbeToTracker")
#: a PLUS frame matches a sample when their times differ by at most this share of a step.
PLUS_TIME_TOL = 0.25
FIDUCIAL_TRACE_COLUMNS = (
    "time_s", "fiducial",
    "stylus_x_mm", "stylus_y_mm", "stylus_z_mm",
    "probe_x_mm", "probe_y_mm", "probe_z_mm",
    "probe_qw", "probe_qx", "probe_qy", "probe_qz",
    "flow_insp_lpm", "flow_exp_lpm",
)  # fmt: skip
FIDUCIAL_ORDER = "rows superior to inferior, within a row patient right to left"
N_FIDUCIALS = 9
#: a record shorter than this (two breaths at 12/min) cannot fit a respiratory model.
MIN_DURATION_S = 10.0
#: quaternions whose norm is off by at most this are renormalised; more is refused.
QUATERNION_TOL = 1e-3
#: largest accepted session.json (it holds metadata only).
MAX_JSON_BYTES = 16_000_000
#: largest accepted record or fiducials CSV (hours of 100 Hz samples).
MAX_CSV_BYTES = 500_000_000
#: largest plausible magnitude per unit of a record's columns: a tracker works
#: within a metre or two, times are seconds after midnight, an ECG is millivolts.
MAX_ABS = {"mm": 1e4, "s": 1e6, "mV": 1e3, "L/min": 1e3, "": 1e6}
#: the median sample interval must match ``sample_rate_hz`` within this fraction.
RATE_TOL = 0.05


class SessionError(HeartregError, ValueError):
    """A session folder that does not follow the ``heartreg-session`` format."""


class SessionNotFoundError(SessionError, FileNotFoundError):
    """The session folder, its ``session.json`` or a file it lists is missing."""


@dataclass(frozen=True, eq=False)
class PointRecord:
    """One attachment point's record, robot poses in the reference-probe frame.

    Attributes
    ----------
    point_id : int
        The record's id in ``session.json``.
    surface_point : int
        Id of the surface point the robot was attached to.
    file : str
        The record's file, relative to the session folder.
    time_s : (n,) float64, s
        Sample times, seconds after midnight of the surgery, strictly increasing.
    T_probe_from_robot : (n, 4, 4) float64
        Robot pose in the reference-probe frame (mm).
    ecg_mv : (n,) float64, mV
    flow_insp_lpm, flow_exp_lpm : (n,) float64, L/min
        Inspiratory and expiratory airflow.
    rate_hz : float
        Declared sample rate.
    """

    point_id: int
    surface_point: int
    file: str
    time_s: np.ndarray
    T_probe_from_robot: np.ndarray
    ecg_mv: np.ndarray
    flow_insp_lpm: np.ndarray
    flow_exp_lpm: np.ndarray
    rate_hz: float

    @property
    def n_samples(self) -> int:
        return int(self.time_s.shape[0])

    @property
    def duration_s(self) -> float:
        return float(self.time_s[-1] - self.time_s[0])


@dataclass(frozen=True, eq=False)
class FiducialTrace:
    """The stylus held on each staple in turn (format 2), reference-probe frame.

    Attributes
    ----------
    file : str
        Relative to the session folder.
    time_s : (n,) float64, s
        Strictly increasing, the clock of the point records.
    fiducial : (n,) int64
        Staple 1..9 held at each sample (documented order), 0 in transit.
    stylus_probe_mm : (n, 3) float64, mm
        Stylus tip in the reference-probe frame.
    flow_insp_lpm, flow_exp_lpm : (n,) float64, L/min
    rate_hz : float
    """

    file: str
    time_s: np.ndarray
    fiducial: np.ndarray
    stylus_probe_mm: np.ndarray
    flow_insp_lpm: np.ndarray
    flow_exp_lpm: np.ndarray
    rate_hz: float


@dataclass(frozen=True, eq=False)
class Session:
    """A validated intra-operative session.

    Attributes
    ----------
    path : Path
        The session folder.
    format_version : int
    sample_rate_hz : float
    points : tuple of PointRecord
        The usable records, in the order of ``session.json``.
    fiducials_probe_mm : (9, 3) float64, mm
        Touched staples in the reference-probe frame, rows superior to
        inferior, within a row patient right to left.
    exclusions : tuple of (int, str)
        ``(point id, reason)`` of every record that was read but not used.
    generator : str
        The writing software, as recorded (may be empty).
    pose_source : str
        Where the poses came from: ``"csv"``, or ``"PLUS sequence (NAME)"``.
    notes : tuple of str
        What the reader did that a user should know (e.g. samples dropped for
        an invalid PLUS pose).
    fiducial_trace : FiducialTrace or None
        The staples traced over a breath (format 2); None in format 1.
    """

    path: Path
    format_version: int
    sample_rate_hz: float
    points: tuple[PointRecord, ...]
    fiducials_probe_mm: np.ndarray
    exclusions: tuple[tuple[int, str], ...]
    generator: str = ""
    pose_source: str = "csv"
    notes: tuple[str, ...] = ()
    fiducial_trace: FiducialTrace | None = None

    def point(self, point_id: int) -> PointRecord:
        """The usable record with id ``point_id``."""
        for record in self.points:
            if record.point_id == point_id:
                return record
        excluded = dict(self.exclusions)
        if point_id in excluded:
            raise KeyError(f"point {point_id} was excluded: {excluded[point_id]}")
        raise KeyError(f"no point {point_id} in session {self.path}")


# --------------------------------------------------------------------- reader
def read_session(
    path,
    *,
    min_duration_s: float = MIN_DURATION_S,
    quaternion_tol: float = QUATERNION_TOL,
) -> Session:
    """Read and validate a ``heartreg-session`` folder.

    Parameters
    ----------
    path : str or Path
        The session folder (holding ``session.json``), or a folder holding a
        ``session/`` subfolder (the phantom's output folder).
    min_duration_s : float, s
        Records shorter than this are excluded (reported in
        :attr:`Session.exclusions`), not used.
    quaternion_tol : float
        Largest accepted deviation of a quaternion's norm from 1; smaller
        deviations are renormalised.

    Returns
    -------
    Session

    Raises
    ------
    SessionNotFoundError
        The folder, ``session.json`` or a listed file is missing.
    SessionError
        Anything that breaks the format, naming the file, column and row; or no
        usable record at all.
    """
    if not min_duration_s >= 0:
        raise ValueError(f"min_duration_s must be >= 0 s, got {min_duration_s!r}")
    if not 0 < quaternion_tol < 1:
        raise ValueError(f"quaternion_tol must be in (0, 1), got {quaternion_tol!r}")
    folder = _find_folder(Path(path))
    meta = _read_meta(folder)
    rate_hz = float(meta["sample_rate_hz"])

    points, exclusions, notes, plus_files = [], [], [], {}
    for entry in meta["points"]:
        if "poses" in entry:
            record = _read_plus_point(folder, entry, rate_hz, meta, plus_files, notes)
        else:
            record = _read_point(folder, entry, rate_hz, quaternion_tol)
        if record.n_samples < 2 or record.duration_s < min_duration_s:
            duration = record.duration_s if record.n_samples >= 2 else 0.0
            exclusions.append(
                (
                    record.point_id,
                    f"{record.file}: record lasts {duration:.2f} s, shorter than "
                    f"min_duration_s = {min_duration_s:g} s (two breaths)",
                )
            )
            continue
        points.append(record)
    if not points:
        reasons = "; ".join(f"point {i}: {why}" for i, why in exclusions) or "session.json lists no points"
        raise SessionError(
            f"{folder}: no usable point record ({reasons}); record longer points or "
            "lower min_duration_s"
        )
    fiducials = _read_fiducials(folder, meta["fiducials_file"])
    trace = None
    if meta.get("fiducial_trace_file") is not None:
        trace = _read_fiducial_trace(folder, meta["fiducial_trace_file"], rate_hz)
    return Session(
        path=folder,
        format_version=int(meta["version"]),
        sample_rate_hz=rate_hz,
        points=tuple(points),
        fiducials_probe_mm=fiducials,
        exclusions=tuple(exclusions),
        generator=str(meta.get("generator", "")),
        pose_source=f"PLUS sequence ({', '.join(sorted(plus_files))})" if plus_files else "csv",
        notes=tuple(notes),
        fiducial_trace=trace,
    )


def _find_folder(path: Path) -> Path:
    if not path.exists():
        raise SessionNotFoundError(f"session folder {path} does not exist")
    if path.is_file() and path.name == "session.json":
        path = path.parent
    if not (path / "session.json").is_file() and (path / "session" / "session.json").is_file():
        path = path / "session"
    if not (path / "session.json").is_file():
        raise SessionNotFoundError(
            f"{path} has no session.json: pass the folder written by the tracker "
            "logger or the phantom (it holds session.json, points/ and fiducials.csv)"
        )
    return path


def _read_meta(folder: Path) -> dict:
    file = folder / "session.json"
    if file.stat().st_size > MAX_JSON_BYTES:
        raise SessionError(
            f"{file} holds {file.stat().st_size / 1e6:.0f} MB; a session.json is a few kB: "
            "check that it is the session's metadata file"
        )
    try:
        meta = json.loads(file.read_text(encoding="utf-8-sig"))  # -sig: a byte-order mark is accepted
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise SessionError(f"{file} is not valid JSON: {' '.join(str(exc).split())}") from None
    if not isinstance(meta, dict):
        raise SessionError(f"{file} must hold a JSON object, got {type(meta).__name__}")
    if meta.get("format") != SESSION_FORMAT:
        raise SessionError(
            f"{file}: 'format' is {meta.get('format')!r}, expected {SESSION_FORMAT!r}; "
            "this is not a heartreg session"
        )
    version = meta.get("version")
    if not isinstance(version, int) or isinstance(version, bool):
        raise SessionError(f"{file}: 'version' must be an integer, got {version!r}")
    if version not in SUPPORTED_VERSIONS:
        hint = "upgrade heartreg" if version > max(SUPPORTED_VERSIONS) else "rewrite the session"
        raise SessionError(
            f"{file}: {SESSION_FORMAT} version {version} is not supported "
            f"(this reader knows {', '.join(map(str, SUPPORTED_VERSIONS))}); {hint}"
        )
    units = meta.get("units")
    if not isinstance(units, dict):
        raise SessionError(f"{file}: 'units' must be an object like {json.dumps(SESSION_UNITS)}")
    for key, expected in SESSION_UNITS.items():
        if key not in units:
            raise SessionError(f"{file}: 'units' has no {key!r} (expected {expected!r})")
        if units[key] != expected:
            raise SessionError(
                f"{file}: unknown unit units.{key} = {units[key]!r}; the format accepts only "
                f"{expected!r}: convert the data"
            )
    for key in sorted(set(units) - set(SESSION_UNITS)):
        raise SessionError(f"{file}: unknown quantity units.{key} = {units[key]!r}")
    if meta.get("quaternion_order") != "wxyz":
        raise SessionError(
            f"{file}: 'quaternion_order' is {meta.get('quaternion_order')!r}; the format "
            "stores scalar-first quaternions and needs 'wxyz'"
        )
    frames = meta.get("frames")
    if not isinstance(frames, dict) or frames.get("poses") != "tracker":
        raise SessionError(f"{file}: 'frames' must be {{\"poses\": \"tracker\"}}, got {frames!r}")
    rate = meta.get("sample_rate_hz")
    if isinstance(rate, bool) or not isinstance(rate, (int, float)) or not np.isfinite(rate) or rate <= 0:
        raise SessionError(f"{file}: 'sample_rate_hz' must be a positive number, got {rate!r}")
    order = meta.get("fiducial_order")
    if order != FIDUCIAL_ORDER:
        raise SessionError(
            f"{file}: 'fiducial_order' is {order!r}; the format requires {FIDUCIAL_ORDER!r}"
        )
    trace = meta.get("fiducial_trace_file")
    if trace is not None:
        if version < 2:
            raise SessionError(f"{file}: 'fiducial_trace_file' needs format version 2, the file says {version}")
        if not isinstance(trace, str) or not trace:
            raise SessionError(f"{file}: 'fiducial_trace_file' must name a file, got {trace!r}")
        _check_relative(file, "fiducial_trace_file", trace)
    fid = meta.get("fiducials_file")
    if not isinstance(fid, str) or not fid:
        raise SessionError(f"{file}: 'fiducials_file' must name a file, got {fid!r}")
    _check_relative(file, "fiducials_file", fid)
    points = meta.get("points")
    if not isinstance(points, list):
        raise SessionError(f"{file}: 'points' must be a list of point records, got {type(points).__name__}")
    seen: set[int] = set()
    files: dict[str, int] = {}
    for k, entry in enumerate(points):
        where = f"{file}: points[{k}]"
        if not isinstance(entry, dict):
            raise SessionError(f"{where} must be an object with 'id', 'file', 'surface_point'")
        for key in ("id", "surface_point"):
            value = entry.get(key)
            if not isinstance(value, int) or isinstance(value, bool):
                raise SessionError(f"{where}: {key!r} must be an integer, got {value!r}")
        if not isinstance(entry.get("file"), str) or not entry["file"]:
            raise SessionError(f"{where}: 'file' must name the record's CSV file")
        _check_relative(file, f"points[{k}].file", entry["file"])
        if "poses" in entry:
            if not isinstance(entry["poses"], str) or not entry["poses"]:
                raise SessionError(f"{where}: 'poses' must name a PLUS sequence file (.seq.mha, .igs.nrrd)")
            _check_relative(file, f"points[{k}].poses", entry["poses"])
        if entry["id"] in seen:
            raise SessionError(f"{where}: point id {entry['id']} is used twice")
        seen.add(entry["id"])
        if entry["file"] in files:
            raise SessionError(
                f"{where}: file {entry['file']!r} is also the record of point {files[entry['file']]}; "
                "each point needs its own CSV file"
            )
        files[entry["file"]] = entry["id"]
    return meta


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
    names = [c.strip() for c in header.strip().split(",")]
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
            "remove or re-record the point"
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
    _check_clock(data[:, 0], rel, rate_hz)
    return data


def _point_record(entry: dict, rate_hz: float, time_s, T_probe_from_robot, signals) -> PointRecord:
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
    )


def _read_point(folder: Path, entry: dict, rate_hz: float, quaternion_tol: float) -> PointRecord:
    rel = entry["file"]
    data = _read_samples(folder, rel, POINT_COLUMNS, rate_hz)
    q_robot = _unit_quaternions(data[:, 4:8], rel, "robot", quaternion_tol)
    q_probe = _unit_quaternions(data[:, 11:15], rel, "probe", quaternion_tol)
    T = _probe_from_robot(_matrices(q_robot), data[:, 1:4], _matrices(q_probe), data[:, 8:11])
    return _point_record(entry, rate_hz, data[:, 0], T, data[:, 15:18])


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


def _read_plus_point(folder: Path, entry: dict, rate_hz: float, meta: dict, cache: dict, notes: list) -> PointRecord:
    """A record whose ECG and flow are in a CSV file and poses in a PLUS sequence file."""
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
    offset = meta.get("poses_time_offset_s", 0.0)
    if isinstance(offset, bool) or not isinstance(offset, (int, float)) or not np.isfinite(offset):
        raise SessionError(f"session.json: 'poses_time_offset_s' must be a number of seconds, got {offset!r}")
    try:
        T_robot, T_probe = (seq.transform(name) for name in PLUS_TRANSFORMS)
    except PlusFileError as exc:
        raise SessionError(str(exc)) from None
    # each sample takes the frame nearest in time, which must be within a quarter step
    t_frames = seq.time_s + float(offset)
    t, n = data[:, 0], len(t_frames)
    after = np.searchsorted(t_frames, t)
    lo, hi = np.clip(after - 1, 0, n - 1), np.clip(after, 0, n - 1)
    k = np.where(np.abs(t_frames[lo] - t) <= np.abs(t_frames[hi] - t), lo, hi)
    far = np.abs(t_frames[k] - data[:, 0]) > PLUS_TIME_TOL / rate_hz
    if far.any():
        row = int(np.argmax(far))
        raise SessionError(
            f"{rel}: row {row + 1} (time_s {float(data[row, 0]):.3f}) has no frame in {poses_rel} within "
            f"{PLUS_TIME_TOL / rate_hz:g} s ({int(far.sum())} such rows); check the PLUS clock "
            "(session.json 'poses_time_offset_s')"
        )
    ok = seq.valid[PLUS_TRANSFORMS[0]][k] & seq.valid[PLUS_TRANSFORMS[1]][k]
    if not ok.all():
        notes.append(f"point {entry['id']}: {int((~ok).sum())} of {len(ok)} samples dropped, "
                     f"the tracker marked the pose invalid in {poses_rel}")
        data, k = data[ok], k[ok]
    Tr, Tp = T_robot[k], T_probe[k]
    T = _probe_from_robot(Tr[:, :3, :3], Tr[:, :3, 3], Tp[:, :3, :3], Tp[:, :3, 3])
    return _point_record(entry, rate_hz, data[:, 0], T, data[:, 1:4])


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
    _check_finite(data, rel, FIDUCIAL_TRACE_COLUMNS)
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
            f"{rel}: column 'fiducial', row {row + 1} (line {row + 2}): {labels[row]!r} is not a staple "
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


