"""Meshes on disk: binary PLY (float64 vertices) and binary STL.

:func:`write_mesh` writes binary PLY (float64 vertices) or binary STL (float32,
80-byte header carrying ``SPACE=LPS`` the way 3D Slicer does, plus the frame);
:func:`read_ply` reads the PLY back. Files are written atomically.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from imaging.files import atomic_path
from modeling.mesh import Mesh, MeshError

__all__ = ["read_ply", "write_mesh"]


def write_mesh(path, mesh: Mesh, *, frame_note: str, space: str = "LPS") -> Path:
    """Write a mesh as binary PLY (``.ply``) or binary STL (``.stl``), atomically.

    Parameters
    ----------
    path : str or Path
        Output file; the suffix picks the format.
    mesh : Mesh
    frame_note : str
        Short description of the vertices' frame, e.g. ``"patient"`` or
        ``"heart (T_heart_from_patient in model.json)"``; stored in the PLY
        comments and the STL header.
    space : {"LPS", "RAS"}
        Axis convention of the coordinates, written as ``SPACE=...`` like 3D
        Slicer, which reads this token to decide whether to flip x and y.

    Notes
    -----
    PLY stores float64 vertices (exact round trip); STL stores float32 vertices
    and per-face normals (about 1e-5 mm rounding at 100 mm). The STL header is
    80 bytes of ASCII that never starts with ``solid``.
    """
    path = Path(path)
    if not isinstance(mesh, Mesh):
        raise TypeError(f"mesh must be a Mesh, got {type(mesh).__name__}")
    if space not in ("LPS", "RAS"):
        raise ValueError(f"space must be 'LPS' or 'RAS', got {space!r}")
    if "\n" in frame_note or "\r" in frame_note:
        raise ValueError("frame_note must be a single line")
    suffix = path.suffix.lower()
    if suffix == ".ply":
        data = _ply_bytes(mesh, frame_note=frame_note, space=space)
    elif suffix == ".stl":
        data = _stl_bytes(mesh, frame_note=frame_note, space=space)
    else:
        raise ValueError(f"unsupported mesh format {path.suffix!r}; use .ply or .stl")
    _atomic_write(path, data)
    return path


def _atomic_write(path: Path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def _ply_bytes(mesh: Mesh, *, frame_note: str, space: str) -> bytes:
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        "comment written by heartreg modeling.surface\n"
        f"comment SPACE={space}\n"
        f"comment frame {frame_note}\n"
        "comment units mm\n"
        f"element vertex {mesh.n_vertices}\n"
        "property double x\nproperty double y\nproperty double z\n"
        f"element face {mesh.n_faces}\n"
        "property list uchar int vertex_indices\n"
        "end_header\n"
    ).encode("ascii")
    vdata = np.ascontiguousarray(mesh.vertices, dtype="<f8").tobytes()
    fdt = np.dtype([("n", "u1"), ("idx", "<i4", (3,))])
    farr = np.empty(mesh.n_faces, dtype=fdt)
    farr["n"] = 3
    farr["idx"] = mesh.faces
    return header + vdata + farr.tobytes()


def _stl_bytes(mesh: Mesh, *, frame_note: str, space: str) -> bytes:
    text = f"SPACE={space} FRAME={frame_note} UNITS=mm heartreg"
    header = text.encode("ascii", errors="replace")[:80].ljust(80, b" ")
    rec = np.dtype([("n", "<f4", (3,)), ("v", "<f4", (3, 3)), ("attr", "<u2")])
    arr = np.zeros(mesh.n_faces, dtype=rec)
    arr["n"] = mesh.face_normals
    arr["v"] = mesh.vertices[mesh.faces]
    return header + np.uint32(mesh.n_faces).tobytes() + arr.tobytes()


def read_ply(path) -> Mesh:
    """Read a binary little-endian triangle PLY as written by :func:`write_mesh`.

    Raises
    ------
    MeshError
        The file is missing, truncated, or not in that layout.
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise MeshError(f"cannot read mesh file {path}: {exc}") from exc
    end = raw.find(b"end_header\n")
    if not raw.startswith(b"ply\n") or end < 0:
        raise MeshError(f"{path} is not a PLY file (no 'ply' magic or 'end_header')")
    lines = raw[:end].decode("ascii", errors="replace").splitlines()
    body = raw[end + len(b"end_header\n") :]
    if "format binary_little_endian 1.0" not in lines:
        raise MeshError(f"{path}: only binary_little_endian PLY is supported; re-export it")
    try:
        n_v = int(next(ln.split()[2] for ln in lines if ln.startswith("element vertex")))
        n_f = int(next(ln.split()[2] for ln in lines if ln.startswith("element face")))
    except (StopIteration, IndexError, ValueError) as exc:
        raise MeshError(f"{path}: PLY header lacks vertex/face counts") from exc
    props = [ln for ln in lines if ln.startswith("property")]
    expected = [
        "property double x",
        "property double y",
        "property double z",
        "property list uchar int vertex_indices",
    ]
    if props != expected:
        raise MeshError(f"{path}: PLY properties {props} are not the heartreg layout {expected}")
    fdt = np.dtype([("n", "u1"), ("idx", "<i4", (3,))])
    need = n_v * 24 + n_f * fdt.itemsize
    if len(body) != need:
        raise MeshError(f"{path}: PLY body has {len(body)} bytes, expected {need} (truncated?)")
    verts = np.frombuffer(body, dtype="<f8", count=n_v * 3).reshape(n_v, 3)
    farr = np.frombuffer(body, dtype=fdt, count=n_f, offset=n_v * 24)
    if n_f and not np.all(farr["n"] == 3):
        raise MeshError(f"{path}: PLY has non-triangle faces")
    try:
        return Mesh(verts, farr["idx"].astype(np.int64))
    except ValueError as exc:
        raise MeshError(f"{path}: {exc}") from exc
