"""The session folder's format as the phantom writes it (``docs/formats.md``).

The phantom is the independent truth and does not import the reader
(:mod:`registration.session`); these constants are its own copy of the format,
and ``tests/registration/test_session.py`` checks that both copies agree.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from heartreg.phantom.geometry import poses

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
_TRACE_ROW_FORMAT = ",".join(
    [_FMT_TIME, "%d"] + [_FMT_POS] * 3 + [_FMT_POS] * 3 + [_FMT_QUAT] * 4 + [_FMT_FLOW, _FMT_FLOW]
)


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


def _format_rows(values: np.ndarray, fmt: str) -> str:
    return "".join(fmt % tuple(row) + "\n" for row in values.tolist())
