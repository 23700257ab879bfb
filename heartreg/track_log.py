"""The outputs of ``heartreg track``: the CSV log's rows and the ``RobotStatus`` string as text, and what a run
did (:class:`TrackSummary`).

Formats: ``docs/formats.md`` (*Track log and OpenIGTLink messages*).  The rows
come from :class:`heartreg.track.TrackRows`; :func:`heartreg.track.run_track`
writes them.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = ["TRACK_COLUMNS", "TrackSummary", "csv_lines", "status_text", "trust_cell"]

TRACK_COLUMNS = (
    "time_s", "cardiac_phase", "respiration_phase", "quality", "flags",
    "map_x_mm", "map_y_mm", "map_z_mm", "map_qw", "map_qx", "map_qy", "map_qz",
    "surface_x_mm", "surface_y_mm", "surface_z_mm", "distance_mm", "nearest_point_mm",
    "static_x_mm", "static_y_mm", "static_z_mm", "sent", "registration_trust",
)  # fmt: skip

_ROW_FMT = ",".join(
    ["%.3f", "%.4f", "%.4f", "%s", "%d"] + ["%.4f"] * 3 + ["%.6f"] * 4 + ["%.4f"] * 4 + ["%.3f"]
    + ["%.4f"] * 3 + ["%d", "%s"]
) + "\n"


@dataclass(frozen=True)
class TrackSummary:
    """What a run did: samples, sent, dropped, placed, wall time, R-peak latency, invalid poses, qualities."""

    n_samples: int
    n_placed: int
    n_sent: int
    n_dropped: int
    models_sent: int
    wall_s: float
    r_peak_latency_ms: tuple
    interrupted: bool
    #: what interrupted the stream: KeyboardInterrupt (Ctrl-C) or a subclass of it (the CLI's SIGTERM)
    interrupted_by: type | None = None
    #: samples whose pose was no finite rigid transform (logged with quality ``tracker``, not placed)
    n_invalid_pose: int = 0
    #: samples by their ``quality`` (the log's column)
    qualities: dict = field(default_factory=dict)


def status_text(rows, i: int, trust: str = "unknown") -> str:
    """The ``RobotStatus`` JSON of sample ``i`` of a :class:`heartreg.track.TrackRows` (``trust``: the
    registration's, :func:`trust_cell`: Slicer's operator sees it with every place, as the log does)."""
    p = rows.T_heart_from_robot[i, :3, 3]
    return json.dumps({
        "time_s": round(float(rows.time_s[i]), 4),
        "cardiac_phase": None if np.isnan(rows.cardiac_phase[i]) else round(float(rows.cardiac_phase[i]), 4),
        "respiration_phase": (None if np.isnan(rows.respiration_phase[i])
                              else round(float(rows.respiration_phase[i]), 4)),
        "quality": rows.quality[i],
        "distance_mm": None if np.isnan(rows.distance_mm[i]) else round(float(rows.distance_mm[i]), 3),
        "map_heart_mm": None if np.isnan(p[0]) else [round(float(x), 3) for x in p],
        "registration_trust": trust,
    }, separators=(",", ":"))


def trust_cell(trust) -> str:
    """The log's ``registration_trust``: the level of a :class:`registration.plausibility.Trust`, then its
    reasons' codes after ``:``, joined by ``+`` (``caution:phase_undecided``); ``unknown`` without one."""
    if trust is None:
        return "unknown"
    return ":".join([trust.level.value, "+".join(r.code for r in trust.reasons)] if trust.reasons else [trust.level.value])


def csv_lines(rows, sent: np.ndarray, trust: str = "unknown") -> str:
    """The log rows of a chunk (``nan`` where a value is undefined; ``trust``: :func:`trust_cell`)."""
    T = rows.T_heart_from_robot
    m = T.shape[0]
    ok = np.isfinite(T[:, 0, 0])
    q = np.full((m, 4), np.nan)
    if ok.any():
        q[ok] = Rotation.from_matrix(T[ok, :3, :3]).as_quat(canonical=True, scalar_first=True)
    cols = [rows.time_s, rows.cardiac_phase, rows.respiration_phase, rows.quality, rows.flags,
            *T[:, :3, 3].T, *q.T, *rows.surface_mm.T, rows.distance_mm, rows.nearest_point_mm,
            *rows.static_mm.T, sent.astype(int), (trust,) * m]
    cols = [c if isinstance(c, tuple) else np.asarray(c).tolist() for c in cols]
    fmt = _ROW_FMT
    return "".join([fmt % r for r in zip(*cols)])
