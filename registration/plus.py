"""Read PLUS toolkit sequence files holding tracking data only (``.seq.mha``, ``.igs.nrrd``).

The PLUS toolkit (and 3D Slicer's Sequences / SlicerIGT) record tracker poses
as a MetaImage (``.mha``) or NRRD (``.nrrd``) header with one group of custom
fields per frame::

    Seq_Frame0000_Timestamp = 33321.250
    Seq_Frame0000_RobotToTrackerTransform = r11 r12 r13 tx r21 ... 0 0 0 1
    Seq_Frame0000_RobotToTrackerTransformStatus = OK

(``key = value`` in MetaImage, ``key:=value`` in NRRD).  A transform named
``<From>To<To>`` maps points of ``From`` into ``To``: ``RobotToTracker`` is
``T_tracker_from_robot``, 16 numbers row by row, mm.  A status other than
``OK`` (PLUS writes ``INVALID`` or ``MISSING``) marks a pose the tracker did
not see.  The image part, if any, is not read.

:func:`read_plus_sequence` returns a :class:`PlusSequence`; the session reader
(:mod:`registration.session`) uses it for the pose part of a session whose
ECG and airflow are in CSV files beside it (``docs/formats.md``).
"""

from __future__ import annotations

import io
import re
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType

import numpy as np

from hrcore.errors import HeartregError
from hrcore.geometry import is_rigid
from registration.session_format import MAX_ABS

__all__ = ["PLUS_SUFFIXES", "PlusFileError", "PlusSequence", "read_plus_sequence"]

PLUS_SUFFIXES = (".mha", ".mhd", ".nrrd", ".nhdr")
#: a transform's rotation must be orthonormal to this (larger errors: not a rigid pose).
RIGID_TOL = 1e-3
#: largest plausible translation (mm), the session CSVs' bound: a tracker works within a metre or two.
MAX_TRANSLATION_MM = MAX_ABS["mm"]


class PlusFileError(HeartregError, ValueError):
    """A PLUS sequence file that cannot be read as tracking data."""


@dataclass(frozen=True, eq=False)
class PlusSequence:
    """The tracking part of a PLUS sequence file, frames in recording order.

    Attributes
    ----------
    path : Path
    time_s : (n,) float64, s
        ``Timestamp`` of every frame, strictly increasing.
    transforms : Mapping of str to (n, 4, 4) float64
        By name without the ``Transform`` suffix (e.g. ``"RobotToTracker"``);
        invalid poses hold NaN.
    valid : Mapping of str to (n,) bool
        Whether the status of each pose is ``OK``.
    """

    path: Path
    time_s: np.ndarray
    transforms: Mapping = field(default_factory=dict)
    valid: Mapping = field(default_factory=dict)

    @property
    def n_frames(self) -> int:
        return int(self.time_s.shape[0])

    def transform(self, name: str) -> np.ndarray:
        """(n, 4, 4) poses of transform ``name`` (e.g. ``"ProbeToTracker"``)."""
        if name not in self.transforms:
            raise PlusFileError(
                f"{self.path.name} has no transform {name!r} (it has "
                f"{', '.join(sorted(self.transforms)) or 'none'}); name the tracker's "
                f"tools {name.split('To')[0]} and {name.split('To')[-1]} in the PLUS configuration"
            )
        return self.transforms[name]


def _header_text(path: Path) -> tuple[str, bool]:
    """The text header of a MetaImage or NRRD file (up to the data), and whether it is NRRD."""
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise PlusFileError(f"PLUS sequence file {path} does not exist") from None
    except OSError as exc:
        raise PlusFileError(f"cannot read {path}: {exc}") from None
    if raw.startswith(b"\xef\xbb\xbf"):  # a UTF-8 byte-order mark
        raw = raw[3:]
    nrrd = raw.startswith(b"NRRD")
    if nrrd:
        blank = re.search(rb"\r?\n\r?\n", raw)  # a blank line ends a NRRD header (LF or CRLF)
        end = len(raw) if blank is None else blank.start()
    else:
        at = raw.find(b"ElementDataFile")  # the last MetaImage header line
        if at < 0:
            raise PlusFileError(f"{path}: no ElementDataFile line, the MetaImage header's last: the file is cut "
                                "short (copy it again) or is not a PLUS sequence file")
        end = raw.find(b"\n", at)
        end = len(raw) if end < 0 else end
    try:
        return raw[:end].decode("utf-8"), nrrd
    except UnicodeDecodeError:
        raise PlusFileError(f"{path}: the header is not text; is this a PLUS sequence file?") from None


_FIELD = {
    False: re.compile(r"^Seq_Frame(\d+)_(\w+)[ \t]*=(.*)$", re.MULTILINE),
    True: re.compile(r"^Seq_Frame(\d+)_(\w+)[ \t]*:=(.*)$", re.MULTILINE),
}


def read_plus_sequence(path) -> PlusSequence:
    r"""Read the poses of a PLUS sequence file (``.seq.mha``, ``.igs.mha``, ``.igs.nrrd``, ...).

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    PlusSequence
        Frames in recording (frame number) order, timestamps strictly increasing.

    Raises
    ------
    PlusFileError
        Missing file, no frames, a frame without ``Timestamp``, repeated
        timestamps or one earlier than its predecessor's (a clock reset), a transform that is not 16 finite numbers of a rigid pose
        or moves more than :data:`MAX_TRANSLATION_MM`, or a transform missing from some frames.

    Examples
    --------
    A two-frame MetaImage header as PLUS writes it (tracking only, no image);
    the tracker lost the robot in the second frame.

    >>> import tempfile
    >>> from pathlib import Path
    >>> from registration import read_plus_sequence
    >>> header = "\n".join([
    ...     "ObjectType = Image", "NDims = 3", "DimSize = 1 1 2", "ElementType = MET_UCHAR",
    ...     "Seq_Frame0000_Timestamp = 33321.25",
    ...     "Seq_Frame0000_RobotToTrackerTransform = 1 0 0 10 0 1 0 20 0 0 1 30 0 0 0 1",
    ...     "Seq_Frame0000_RobotToTrackerTransformStatus = OK",
    ...     "Seq_Frame0001_Timestamp = 33321.26",
    ...     "Seq_Frame0001_RobotToTrackerTransform = 1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1",
    ...     "Seq_Frame0001_RobotToTrackerTransformStatus = INVALID",
    ...     "ElementDataFile = LOCAL", ""])
    >>> folder = tempfile.TemporaryDirectory()
    >>> path = Path(folder.name) / "rec.seq.mha"
    >>> _ = path.write_text(header + "\0\0")
    >>> seq = read_plus_sequence(path)
    >>> seq.n_frames, seq.time_s.tolist(), seq.valid["RobotToTracker"].tolist()
    (2, [33321.25, 33321.26], [True, False])
    >>> seq.transform("RobotToTracker")[:, :3, 3].tolist()  # T_tracker_from_robot, mm; NaN where invalid
    [[10.0, 20.0, 30.0], [nan, nan, nan]]
    >>> folder.cleanup()
    """
    path = Path(path)
    if not path.name.lower().endswith(PLUS_SUFFIXES):
        raise PlusFileError(f"{path.name}: a PLUS sequence file ends in {', '.join(PLUS_SUFFIXES)}")
    text, nrrd = _header_text(path)
    times: dict[int, str] = {}
    poses: dict[str, dict[int, str]] = {}
    status: dict[str, dict[int, str]] = {}
    for number, name, value in _FIELD[nrrd].findall(text):
        frame = int(number)
        if name == "Timestamp":
            times[frame] = value
        elif name.endswith("TransformStatus"):
            status.setdefault(name[: -len("TransformStatus")], {})[frame] = value
        elif name.endswith("Transform"):
            poses.setdefault(name[: -len("Transform")], {})[frame] = value
    if not times:
        raise PlusFileError(f"{path}: no Seq_Frame####_Timestamp fields: not a PLUS sequence file with frames")
    frames = sorted(times)
    try:
        t = np.array([float(times[f]) for f in frames])
    except ValueError:
        bad = next(f for f in frames if not _is_float(times[f]))
        raise PlusFileError(f"{path}: Seq_Frame{bad:04d}_Timestamp = {times[bad]!r} is not a number") from None
    if not np.all(np.isfinite(t)):
        raise PlusFileError(f"{path}: a Timestamp is NaN or infinite")
    back = np.diff(t) < 0  # frames in recording order: a timestamp going back is a clock reset, not an order
    if back.any():
        k = int(np.argmax(back)) + 1
        raise PlusFileError(
            f"{path}: Seq_Frame{frames[k]:04d}_Timestamp = {float(t[k])!r} is earlier than frame {frames[k - 1]}'s "
            f"{float(t[k - 1])!r}: the PLUS clock went back (a restart?) and the frames after it are on another "
            "clock; record again or split the file there"
        )
    if np.any(np.diff(t) == 0):
        k = int(np.argmax(np.diff(t) == 0))
        raise PlusFileError(f"{path}: two frames share the Timestamp {float(t[k])!r}; the recording is corrupt")
    transforms, valid = {}, {}
    for name, values in poses.items():
        missing = [f for f in frames if f not in values]
        if missing:
            raise PlusFileError(f"{path}: frame {missing[0]} has no {name}Transform ({len(missing)} frames lack it)")
        states = status.get(name, {})
        ok = np.array([states.get(f, "OK").strip().upper() == "OK" for f in frames], dtype=bool)
        T = np.full((len(frames), 4, 4), np.nan)
        good = [f for f, o in zip(frames, ok) if o]
        if good:
            T[ok] = _matrices(path, name, good, values)
        _check_poses(path, name, T[ok], good)
        T.setflags(write=False)
        ok.setflags(write=False)
        transforms[name], valid[name] = T, ok
    t.setflags(write=False)
    return PlusSequence(path=path, time_s=t, transforms=MappingProxyType(transforms),
                        valid=MappingProxyType(valid))


def _matrices(path: Path, name: str, frames, values) -> np.ndarray:
    """(n, 4, 4) from the frames' 16-number strings (one fast parse; the slow path names the frame)."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            flat = np.loadtxt(io.StringIO("\n".join(values[f] for f in frames)), ndmin=2, dtype=np.float64)
        if flat.shape == (len(frames), 16):
            return flat.reshape(-1, 4, 4)
    except ValueError:
        pass
    for f in frames:
        cells = values[f].split()
        if len(cells) != 16 or not all(_is_float(c) for c in cells):
            raise PlusFileError(
                f"{path}: Seq_Frame{f:04d}_{name}Transform must be 16 numbers (a 4 x 4 matrix row by row)"
            )
    raise PlusFileError(f"{path}: the {name}Transform fields do not parse")  # pragma: no cover


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _check_poses(path: Path, name: str, T: np.ndarray, frames) -> None:
    if not T.size:
        return
    bad = ~is_rigid(T, tol=RIGID_TOL)
    if bad.any():
        k = int(np.argmax(bad))
        raise PlusFileError(
            f"{path}: Seq_Frame{frames[k]:04d}_{name}Transform is not a rigid pose (rotation "
            f"orthonormal within {RIGID_TOL:g}, last row 0 0 0 1); {int(bad.sum())} such frame(s)"
        )
    far = np.abs(T[:, :3, 3]) > MAX_TRANSLATION_MM
    if far.any():
        k, i = (int(x) for x in np.argwhere(far)[0])
        raise PlusFileError(
            f"{path}: Seq_Frame{frames[k]:04d}_{name}Transform: translation {float(T[k, i, 3]):.6g} mm (its "
            f"{4 * i + 4}th number) is beyond the plausible {MAX_TRANSLATION_MM:g} mm ({int(far.any(axis=1).sum())} "
            "such frame(s)); check the tracker's units or record again"
        )
