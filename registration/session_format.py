"""The session folder's format: its constants, errors and the values read from it.

:func:`registration.session.read_session` returns a :class:`Session` of
:class:`PointRecord` (and, in version 2, a :class:`FiducialTrace`); the
format itself is documented in ``docs/formats.md`` (section *Session folder*).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hrcore.errors import HeartregError

__all__ = [
    "SESSION_FORMAT",
    "SUPPORTED_VERSIONS",
    "SESSION_UNITS",
    "POINT_COLUMNS",
    "FIDUCIAL_COLUMNS",
    "FIDUCIAL_TRACE_COLUMNS",
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
#: a tracker on its own rate or clock: its poses are interpolated between frames at most this many
#: median frame steps apart (one lost frame is bridged), and it must run at this rate or faster (Hz): the
#: heartbeat's fifth harmonic, the motion model's highest, is 7.5 Hz at 90 beats/min.
MAX_FRAME_GAP = 2.5
MIN_TRACKER_RATE_HZ = 20.0
#: largest accepted ``poses_time_offset_s`` (three centuries: room for a PLUS clock counting Unix time).
MAX_TIME_OFFSET_S = 1e10
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
#: two tracked tools (robot sensor and chest probe; two staples) are never closer than this, mm: a record or
#: fiducials closer are in metres, not the format's millimetres (a tracker export's unit, an audit).
MIN_SEPARATION_MM = 1.0


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
    n_invalid : int
        Samples dropped because the tracker marked their pose invalid (a PLUS
        sequence's ``INVALID`` or ``MISSING``); 0 for a CSV record.
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
    n_invalid: int = 0

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
        Where the poses came from: ``"csv"``, ``"PLUS sequence"`` or ``"PLUS sequences (N files)"`` (by
        kind, never by file name: it can name the patient).
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
