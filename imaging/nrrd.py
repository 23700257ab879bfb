"""NRRD files, 3D Slicer's own format: the voxels and their affine in LPS.

One reader for CT volumes (:func:`imaging.volume_file.read_nrrd_volume`) and
label maps (:mod:`modeling.labelmap`).  An attached header (``.nrrd``) or a
detached one (``.nhdr`` naming one data file, as ITK and 3D Slicer write it;
a list of files is refused), raw, gzip or bzip2 encoding; 3-D, or 4-D with
a leading ``list`` axis (a 3D Slicer segmentation whose segments overlap keeps
one label layer per entry); the ``space`` may be LPS, RAS or LAS (Slicer writes
LPS), and ``space directions`` and ``space origin`` give the affine of voxel
index ``(i, j, k)`` (the file's fastest spatial axis first), converted to LPS.
"""

from __future__ import annotations

import bz2
import gzip
import re
from pathlib import Path

import numpy as np

from hrcore.errors import HeartregError

__all__ = ["NrrdError", "is_nrrd_path", "read_nrrd", "read_nrrd_header"]

_TYPES = {
    "uchar": "u1", "unsigned char": "u1", "uint8": "u1", "uint8_t": "u1",
    "signed char": "i1", "int8": "i1", "int8_t": "i1", "char": "i1",
    "short": "i2", "int16": "i2", "int16_t": "i2", "signed short": "i2", "short int": "i2",
    "ushort": "u2", "unsigned short": "u2", "uint16": "u2", "uint16_t": "u2",
    "int": "i4", "int32": "i4", "int32_t": "i4", "signed int": "i4",
    "uint": "u4", "unsigned int": "u4", "uint32": "u4", "uint32_t": "u4",
    "longlong": "i8", "long long": "i8", "long long int": "i8", "signed long long": "i8",
    "signed long long int": "i8", "int64": "i8", "int64_t": "i8",
    "ulonglong": "u8", "unsigned long long": "u8", "unsigned long long int": "u8", "uint64": "u8", "uint64_t": "u8",
    "float": "f4", "double": "f8",
}
#: LPS from each anatomical space NRRD names (its long name and its short one).
_SPACES = {
    name: flip
    for names, flip in ((("left-posterior-superior", "lps"), np.eye(4)),
                        (("right-anterior-superior", "ras"), np.diag([-1.0, -1.0, 1.0, 1.0])),
                        (("left-anterior-superior", "las"), np.diag([1.0, -1.0, 1.0, 1.0])))
    for name in names
}


class NrrdError(HeartregError, ValueError):
    """A file that is not a readable 3-D NRRD volume (the message names it)."""


def is_nrrd_path(path) -> bool:
    """True when ``path`` names an NRRD file (``.nrrd``; a detached ``.nhdr`` header too, to be refused by name)."""
    return str(path).lower().endswith((".nrrd", ".nhdr"))


def _vector(text: str) -> list[float]:
    return [float(x) for x in text.strip().strip("()").split(",")]


def _header(raw: bytes, path) -> tuple[dict, re.Match | None]:
    """The header fields (keys lower-cased) of an NRRD file's bytes (its first MB will do), and the empty line
    that ends an attached header (None where none does: a detached header, or no NRRD)."""
    if not raw.startswith(b"NRRD"):
        raise NrrdError(f"{path} is not an NRRD file")
    blank = re.search(rb"\r?\n\r?\n", raw[:1 << 20])  # the header ends at its first empty line
    fields = {}
    for line in raw[: len(raw) if blank is None else blank.start()].decode("utf-8", "replace").splitlines()[1:]:
        if line.startswith("#") or ":" not in line:
            continue
        key, _, value = line.partition(":")
        fields[key.strip().lower()] = value.lstrip("=").strip()
    return fields, blank


def read_nrrd_header(path) -> dict:
    """An NRRD file's header fields alone (keys lower-cased), read from its first MB: the voxels are not read.

    Raises
    ------
    NrrdError
        Not an NRRD file.  OSError: the file cannot be read.
    """
    with open(path, "rb") as f:
        return _header(f.read(1 << 20), path)[0]


def _data_file(header: Path, name: str) -> bytes:
    """The bytes of a detached header's one data file: a name relative to the header's folder, or absolute (the
    NRRD format allows both; teem and pynrrd write either)."""
    parts = name.split()
    if len(parts) != 1 or parts[0].upper() == "LIST":  # "LIST", or a format string with its index range
        raise NrrdError(f"NRRD header {header} spreads its data over several files ({name[:60]!r}); save the "
                        "volume as a single .nrrd")
    data = Path(parts[0]) if Path(parts[0]).is_absolute() else header.parent / parts[0]
    if not data.is_file():
        raise NrrdError(f"NRRD header {header} names its data file {parts[0][:200]}, which "
                        + ("does not exist" if Path(parts[0]).is_absolute() else "is not beside it")
                        + "; copy the two files together")
    return data.read_bytes()


def read_nrrd(path) -> tuple[np.ndarray, np.ndarray, dict]:
    """The voxels, ``T_patient_from_voxel`` (LPS) and header fields of an NRRD file.

    Returns
    -------
    data : array, the file's type
        ``[k, j, i]``; ``[layer, k, j, i]`` for a 4-D file with a leading list axis.
    T : (4, 4) float64
    fields : dict
        Every header field (key lower-cased), e.g. a Slicer segmentation's
        ``segment0_name``.

    Raises
    ------
    NrrdError
        Not an NRRD file (an attached header, or a detached one beside its one
        data file), a missing or bad field, not 3-D (or 4-D with a list axis),
        an unsupported encoding or a truncated body.
    """
    path = Path(path)
    raw = path.read_bytes()
    fields, blank = _header(raw, path)
    detached = fields.get("data file", fields.get("datafile"))
    if detached is None and blank is None:
        raise NrrdError(f"{path} is not an NRRD file with an attached header (no empty line ends its header)")
    if fields.get("type", "").lower() not in _TYPES:
        raise NrrdError(f"NRRD file {path}: voxel type {fields.get('type', '(none)')!r} is not read; save it as an "
                        "integer or float type")
    space_name = fields.get("space", "left-posterior-superior").strip().lower()
    if space_name not in _SPACES:  # scanner-xyz, 3d-right-handed, ...: no patient directions
        raise NrrdError(f"NRRD file {path}: space '{space_name[:40]}' names no patient directions (only "
                        "left-posterior-superior, right-anterior-superior or left-anterior-superior place a CT); "
                        "save the volume in patient space (3D Slicer writes left-posterior-superior)")
    try:
        sizes = [int(v) for v in fields["sizes"].split()]
        dtype = np.dtype(_TYPES[fields["type"].lower()])
        space = _SPACES[space_name]
        directions = [_vector(d) for d in re.findall(r"\([^)]*\)", fields["space directions"])]
        origin = _vector(fields.get("space origin", "(0,0,0)"))
    except (KeyError, ValueError) as exc:
        raise NrrdError(f"NRRD file {path}: missing or bad header field ({exc}); save the volume with its "
                        "geometry ('space directions' and 'space origin', as 3D Slicer writes them)") from None
    if any(size < 1 for size in sizes):
        raise NrrdError(f"NRRD file {path}: sizes {sizes} must all be positive")
    for skip in ("byte skip", "byteskip", "line skip", "lineskip"):
        if fields.get(skip, "0").strip() not in ("0", ""):
            raise NrrdError(f"NRRD file {path}: '{skip}: {fields[skip]}' is not supported; save it again from Slicer")
    layered = len(sizes) == 4 and fields.get("kinds", "").lower().split()[:1] == ["list"]
    if len(sizes) - layered != 3 or len(directions) != 3 or any(len(d) != 3 for d in directions) or len(origin) != 3:
        raise NrrdError(f"NRRD file {path} must hold a 3-D volume in 3-D space, got sizes {sizes}")
    encoding = fields.get("encoding", "raw").lower()
    body = memoryview(raw)[blank.end():] if detached is None else _data_file(path, detached)  # no copy of the data
    try:
        if encoding in ("gzip", "gz"):
            body = gzip.decompress(body)
        elif encoding in ("bzip2", "bz2"):
            body = bz2.decompress(body)
        elif encoding != "raw":
            raise NrrdError(f"NRRD file {path}: encoding {encoding!r} not supported (use raw, gzip or bzip2)")
    except (OSError, EOFError, ValueError) as exc:
        if isinstance(exc, NrrdError):
            raise
        raise NrrdError(f"NRRD file {path}: its {encoding} data cannot be decompressed ({exc})") from None
    if dtype.itemsize > 1:
        dtype = dtype.newbyteorder("<" if fields.get("endian", "little") == "little" else ">")
    n = int(np.prod(sizes))
    if len(body) < n * dtype.itemsize:
        of = "" if detached is None else f" (its data file {detached.strip()[:200]})"
        raise NrrdError(f"NRRD file {path}{of} is truncated ({len(body)} of {n * dtype.itemsize} bytes)")
    if len(body) > n * dtype.itemsize:
        raise NrrdError(f"NRRD file {path} holds {len(body) - n * dtype.itemsize} bytes more than its sizes and "
                        f"type say: the header and the data disagree")
    data = np.frombuffer(body[: n * dtype.itemsize], dtype=dtype).reshape(sizes[::-1])  # [k, j, i(, layer)]
    if layered:
        data = np.moveaxis(data, -1, 0)
    T = np.eye(4)
    T[:3, :3] = np.asarray(directions, dtype=float).T
    T[:3, 3] = origin
    return data, space @ T, fields
