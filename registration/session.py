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
from pathlib import Path

import numpy as np

from registration.session_format import (  # the format's public names are this module's too
    FIDUCIAL_COLUMNS, FIDUCIAL_ORDER, FIDUCIAL_TRACE_COLUMNS, MAX_FRAME_GAP, MAX_JSON_BYTES, MIN_DURATION_S, PLUS_TRANSFORMS,
    POINT_COLUMNS, QUATERNION_TOL, SESSION_FORMAT, SESSION_UNITS, SIGNAL_COLUMNS, SUPPORTED_VERSIONS,
    FiducialTrace, PointRecord, Session, SessionError, SessionNotFoundError,
)
from registration.session_tables import (
    _check_relative, _check_time_offset, _read_fiducial_trace, _read_fiducials, _read_plus_point, _read_point,
)

__all__ = ["read_session"]  # the format's names are importable from here too (imported above)


# --------------------------------------------------------------------- reader
#: Longest pause (s) in a point's samples: a tracker that lost the robot for longer leaves a gap across which
#: phases and motion are interpolated, not measured (1 s in one record of the phantom's session: the final
#: transform 2.7 mm off with the trust "ok"; in every record 10.9 mm, session 15's registration sweep).
MAX_GAP_S = 0.25


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

    Examples
    --------
    A session recorded in surgery, or written by ``heartreg phantom case``
    (which the repository does not ship, hence skipped):

    >>> from registration import read_session
    >>> session = read_session("case/session")  # doctest: +SKIP
    >>> len(session.points), session.fiducials_probe_mm.shape  # doctest: +SKIP
    (8, (9, 3))

    A folder that is not there is refused in one line:

    >>> read_session("no_such_folder")
    Traceback (most recent call last):
        ...
    registration.session_format.SessionNotFoundError: session folder no_such_folder does not exist
    """
    if not min_duration_s >= 0:
        raise ValueError(f"min_duration_s must be >= 0 s, got {min_duration_s!r}")
    if not 0 < quaternion_tol < 1:
        raise ValueError(f"quaternion_tol must be in (0, 1), got {quaternion_tol!r}")
    folder = _find_folder(Path(path))
    try:
        return _read_folder(folder, min_duration_s, quaternion_tol)
    except SessionError as exc:  # a file's error names it within the folder: which session it is in, too
        if str(folder) in str(exc):
            raise
        raise type(exc)(f"session {folder}: {exc}") from None


def _read_folder(folder: Path, min_duration_s: float, quaternion_tol: float) -> Session:
    meta = _read_meta(folder)
    rate_hz = float(meta["sample_rate_hz"])

    points, exclusions, notes, plus_files, dropped = [], [], [], {}, {}
    for entry in meta["points"]:
        if "poses" in entry:
            record = _read_plus_point(folder, entry, rate_hz, meta, plus_files, notes, dropped)
        else:
            record = _read_point(folder, entry, rate_hz, quaternion_tol)
        if record.n_samples < 2 or record.duration_s < min_duration_s:
            duration = record.duration_s if record.n_samples >= 2 else 0.0
            exclusions.append(
                (
                    record.point_id,
                    f"its record lasts {duration:.2f} s, shorter than "
                    f"min_duration_s = {min_duration_s:g} s (two breaths)",
                )
            )
            continue
        steps = np.diff(record.time_s)
        gap = float(steps.max())
        if gap > MAX_GAP_S:
            at = float(record.time_s[int(np.argmax(steps))])
            exclusions.append(
                (
                    record.point_id,
                    f"its samples stop for {gap:.2f} s after t = {at:.2f} s (the tracker lost the "
                    f"robot?), longer than {MAX_GAP_S:g} s: its motion cannot be followed across the gap",
                )
            )
            continue
        points.append(record)
    if dropped:  # one note: a tracker's frames rarely reach a record's very first and last samples
        lost, total = (sum(v[i] for v in dropped.values()) for i in (0, 1))
        most = sorted(dropped, key=lambda k: -dropped[k][0])
        listed = ", ".join(f"point {k}: {dropped[k][0]}" for k in most[:6]) + (
            f", {len(most) - 6} more" if len(most) > 6 else "")
        notes.append(f"{lost} of {total} samples of {len(dropped)} point(s) dropped ({listed}): no tracked pose within "
                     f"{MAX_FRAME_GAP:g} frame steps of them in the PLUS sequence (a record's first or last samples, "
                     "or the tracker's dropouts)")
    if meta.get("poses_time_offset_s", 0) and not plus_files:
        notes.append("session.json's 'poses_time_offset_s' is unused: no point takes its poses from a PLUS sequence "
                     "(the CSV poses are on the signals' clock)")
    if not points:
        reasons = "; ".join(f"point {i}: {why}" for i, why in exclusions) or "session.json lists no points"
        raise SessionError(
            f"{folder}: no usable point record ({reasons}); record longer points (at least two breaths "
            "each)"
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
        pose_source=_plus_source(len(plus_files)) if plus_files else "csv",  # by kind: a file name can name the patient
        notes=tuple(notes),
        fiducial_trace=trace,
    )


def _plus_source(n_files: int) -> str:
    """Where the poses came from, by kind and count (PLUS files are often named after the patient)."""
    return "PLUS sequence" if n_files == 1 else f"PLUS sequences ({n_files} files)"


def _find_folder(path: Path) -> Path:
    if not path.exists():
        raise SessionNotFoundError(f"session folder {path} does not exist")
    if path.is_file() and path.name == "session.json":
        path = path.parent
    if not path.is_dir():
        raise SessionNotFoundError(f"session {path} is not a folder; pass the folder written by the tracker logger "
                                   "or the phantom (it holds session.json, points/ and fiducials.csv)")
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
    except ValueError:  # Python's limit on integer digits: no id or count has thousands
        raise SessionError(f"{file} holds an integer of thousands of digits: check its point ids") from None
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
    _check_time_offset(meta)  # refused where it is wrong, PLUS poses or not
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
            if not -(2**63) <= value < 2**63:  # stored as int64 (the registration's point_ids)
                raise SessionError(f"{where}: {key!r} is {value}, outside the 64-bit integers "
                                   f"(-2**63 to 2**63 - 1) a point is stored with; number the points again")
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
