"""The phantom's session as PLUS toolkit sequence files (tracking only).

:func:`write_plus_session` turns the phantom's CSV session folder into the same
session with its poses in one PLUS sequence file, as a PLUS (or 3D Slicer
Sequences) recording of the tracker would hold them: ``RobotToTracker`` and
``ProbeToTracker`` transforms (``T_tracker_from_robot``, ``T_tracker_from_probe``,
4 x 4 row by row, mm) with a status and a timestamp per frame.  ECG and airflow
stay in per-point CSV files beside it; ``session.json`` names the sequence file
in each point's ``poses`` key (``docs/formats.md``).

The matrices are the rotations the CSV quaternions stand for (normalised, then
converted as the session reader converts them), written with 17 significant
digits: read back, the poses are the CSV session's to the last bit, so both
give the same registration.  Like every part of the phantom this module imports
nothing from ``imaging``, ``modeling`` or ``registration``.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = ["PLUS_TRANSFORMS", "SIGNAL_COLUMNS", "write_plus_sequence", "write_plus_session"]

PLUS_TRANSFORMS = ("RobotToTracker", "ProbeToTracker")
SIGNAL_COLUMNS = ("time_s", "ecg_mv", "flow_insp_lpm", "flow_exp_lpm")
_POSE_COLUMNS = {
    "RobotToTracker": ("robot_x_mm", "robot_y_mm", "robot_z_mm", "robot_qw", "robot_qx", "robot_qy", "robot_qz"),
    "ProbeToTracker": ("probe_x_mm", "probe_y_mm", "probe_z_mm", "probe_qw", "probe_qx", "probe_qy", "probe_qz"),
}


def _num(x: float) -> str:
    return repr(float(x))  # shortest text that reads back to the same float64


def _frame_fields(time_s, transforms, valid, sep: str) -> list[str]:
    lines = []
    n = len(time_s)
    texts = {}
    for name, T in transforms.items():
        flat = np.asarray(T, dtype=np.float64).reshape(n, 16)
        texts[name] = [" ".join(_num(x) for x in row) for row in flat.tolist()]
    for i in range(n):
        tag = f"Seq_Frame{i:04d}_"
        lines.append(f"{tag}FrameNumber{sep}{i}")
        for name in transforms:
            ok = True if valid is None or name not in valid else bool(valid[name][i])
            lines.append(f"{tag}{name}Transform{sep}{texts[name][i] if ok else ' '.join(['0'] * 16)}")
            lines.append(f"{tag}{name}TransformStatus{sep}{'OK' if ok else 'INVALID'}")
        lines.append(f"{tag}Timestamp{sep}{_num(time_s[i])}")
        lines.append(f"{tag}UnfilteredTimestamp{sep}{_num(time_s[i])}")
    return lines


def write_plus_sequence(path, time_s, transforms, *, valid=None) -> Path:
    """Write a tracking-only PLUS sequence file, MetaImage (``.mha``) or NRRD (``.nrrd``).

    Parameters
    ----------
    path : str or Path
        Output file; ``.seq.mha``/``.igs.mha`` or ``.igs.nrrd``/``.seq.nrrd``.
    time_s : (n,) float, s
        Frame timestamps.
    transforms : dict of str to (n, 4, 4) float, mm
        Poses by PLUS name without the ``Transform`` suffix (``"RobotToTracker"``).
    valid : dict of str to (n,) bool, optional
        Per transform, whether the tracker saw the tool (status ``OK``) or not
        (``INVALID``, written as a zero matrix).

    Returns
    -------
    Path
    """
    path = Path(path)
    time_s = np.asarray(time_s, dtype=np.float64)
    n = len(time_s)
    for name, T in transforms.items():
        if np.shape(T) != (n, 4, 4):
            raise ValueError(f"transform {name} must have shape ({n}, 4, 4), got {np.shape(T)}")
    suffix = path.name.lower()
    if suffix.endswith(".mha"):
        header = [
            "ObjectType = Image", "NDims = 3", "AnatomicalOrientation = RAI", "BinaryData = True",
            "BinaryDataByteOrderMSB = False", "CompressedData = False", f"DimSize = 1 1 {n}",
            "ElementSpacing = 1 1 1", "Offset = 0 0 0", "TransformMatrix = 1 0 0 0 1 0 0 0 1",
            "ElementType = MET_UCHAR", "Kinds = domain domain list",
        ]
        header += _frame_fields(time_s, transforms, valid, " = ")
        header.append("ElementDataFile = LOCAL")
    elif suffix.endswith(".nrrd"):
        header = [
            "NRRD0004", "# Complete NRRD file format specification at:",
            "# http://teem.sourceforge.net/nrrd/format.html", "# tracking-only PLUS sequence, heartreg phantom",
            "dimension: 3", "encoding: raw", "endian: little", "kinds: domain domain list",
            f"sizes: 1 1 {n}", "space dimension: 2", "space directions: (1,0) (0,1) none",
            "space origin: (0,0)", "type: uint8",
        ]
        header += _frame_fields(time_s, transforms, valid, ":=")
        header.append("")  # a blank line ends a NRRD header
    else:
        raise ValueError(f"a PLUS sequence file ends in .mha or .nrrd, got {path.name}")
    data = ("\n".join(header) + "\n").encode("utf-8") + bytes(n)  # one blank 1 x 1 pixel per frame
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def _poses(table: np.ndarray) -> np.ndarray:
    """(n, 4, 4) from (n, 7) columns x, y, z, qw, qx, qy, qz, as the session reader converts them."""
    q = table[:, 3:7]
    q = q / np.linalg.norm(q, axis=1)[:, None]
    T = np.zeros((len(table), 4, 4))
    if len(table):
        T[:, :3, :3] = Rotation.from_quat(q, scalar_first=True).as_matrix()
    T[:, :3, 3] = table[:, :3]
    T[:, 3, 3] = 1.0
    return T


def _tracker_rows(time_s: np.ndarray, rate_hz: float, rng: np.random.Generator) -> np.ndarray:
    """Indices of the rows nearest to a tracker's frame times (``1 / rate_hz`` apart, jittered)."""
    step = 1.0 / rate_hz
    nominal = np.arange(time_s[0], time_s[-1], step)
    nominal = nominal + rng.uniform(-0.2, 0.2, nominal.size) * step
    after = np.clip(np.searchsorted(time_s, nominal), 1, time_s.size - 1)
    nearest = np.where(nominal - time_s[after - 1] <= time_s[after] - nominal, after - 1, after)
    return np.unique(nearest)


def write_plus_session(session_dir, out_dir, *, sequence_name: str = "tracking.seq.mha",
                       tracker_rate_hz: float | None = None, seed: int = 0, overwrite: bool = False) -> Path:
    """Write the phantom's CSV session ``session_dir`` again with its poses in a PLUS file.

    ``out_dir`` receives ``session.json`` (each point with ``poses``),
    ``points/point_NNN.csv`` (``time_s, ecg_mv, flow_insp_lpm, flow_exp_lpm``,
    the CSV session's text), the sequence file ``sequence_name`` (all records'
    frames, in time order) and ``fiducials.csv``.  Written in a temporary
    folder beside ``out_dir`` and renamed into place.

    With ``tracker_rate_hz`` the tracker runs at its own rate, as real ones do
    (an optical tracker at 40-60 Hz beside signals at 100 Hz or more): each
    record's frames are its rows nearest to times ``1 / tracker_rate_hz``
    apart, each jittered by up to a fifth of that step (``seed``), so a frame's
    timestamp and pose are the row's exactly and the rows between have none.

    Returns
    -------
    Path
        ``out_dir``.
    """
    src, out = Path(session_dir), Path(out_dir)
    meta = json.loads((src / "session.json").read_text(encoding="utf-8"))
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise FileExistsError(f"{out} is not empty; choose another folder or pass overwrite=True")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}-", dir=out.parent))
    try:
        os.chmod(tmp, 0o755)
        (tmp / "points").mkdir()
        times, poses = [], {name: [] for name in PLUS_TRANSFORMS}
        rng = np.random.default_rng([int(seed), 0x9105])
        for entry in meta["points"]:
            text = (src / entry["file"]).read_text(encoding="utf-8").splitlines()
            names = text[0].split(",")
            keep = [names.index(c) for c in SIGNAL_COLUMNS]
            rows = [line.split(",") for line in text[1:] if line]
            (tmp / entry["file"]).write_text(
                "\n".join([",".join(SIGNAL_COLUMNS)] + [",".join(r[k] for k in keep) for r in rows]) + "\n",
                encoding="utf-8",
            )
            table = np.array([[float(r[names.index(c)]) for c in ("time_s",) + _POSE_COLUMNS["RobotToTracker"]
                               + _POSE_COLUMNS["ProbeToTracker"]] for r in rows]).reshape(-1, 15)
            if tracker_rate_hz is not None:
                table = table[_tracker_rows(table[:, 0], float(tracker_rate_hz), rng)]
            times.append(table[:, 0])
            poses["RobotToTracker"].append(_poses(table[:, 1:8]))
            poses["ProbeToTracker"].append(_poses(table[:, 8:15]))
            entry["poses"] = sequence_name
        time_s = np.concatenate(times)
        order = np.argsort(time_s, kind="stable")
        write_plus_sequence(tmp / sequence_name, time_s[order],
                            {name: np.concatenate(p)[order] for name, p in poses.items()})
        shutil.copyfile(src / meta["fiducials_file"], tmp / meta["fiducials_file"])
        if meta.get("fiducial_trace_file"):  # session format 2: the staples traced over a breath
            shutil.copyfile(src / meta["fiducial_trace_file"], tmp / meta["fiducial_trace_file"])
        meta["generator"] = f"{meta.get('generator', 'heartreg phantom')}; poses in PLUS sequence {sequence_name}"
        (tmp / "session.json").write_text(json.dumps(meta, indent=2) + "\n", encoding="utf-8")
        if out.exists():
            shutil.rmtree(out)
        os.rename(tmp, out)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)
    return out
