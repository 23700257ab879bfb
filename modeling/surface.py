"""Binary mask to a closed, smooth, decimated triangle mesh in the patient frame.

Pipeline of :func:`mask_to_mesh` (paper section 2.2.3, "meshed, smoothed, holes
closed, decimated"):

1. crop the mask to its bounding box, pad it with empty voxels so the
   isosurface is closed where the mask touches the volume's edge, fill internal
   cavities (background not connected to the padding);
2. isosurface at level 0.5 of the lightly Gaussian-smoothed float mask
   (``skimage.measure.marching_cubes``), in voxel indices ``(k, j, i)``;
3. reorder to ``(i, j, k)`` *before* mapping through ``T_patient_from_voxel``
   and reverse the triangle winding when the whole index-to-patient map is a
   reflection, so that normals point out of the mask;
4. keep the largest connected component;
5. repair with pymeshlab (duplicate vertices and faces, null faces,
   non-manifold edges and vertices, small holes, unreferenced vertices), unless
   the surface is already closed and manifold with nothing to repair, as
   marching cubes' usually is (checked in numpy);
6. Taubin lambda/mu smoothing, which does not shrink the surface the way plain
   Laplacian smoothing does (uniform weights; in numpy on a surface that
   needed no repair, else in pymeshlab: the same steps);
7. quadric decimation to ``target_faces`` with fast_simplification (and
   repair as in 5. when it left something to repair);
8. verification: watertight, manifold, consistently wound, enclosed volume > 0,
   else :class:`MeshError`.

:func:`write_mesh` writes binary PLY (float64 vertices) or binary STL (float32,
80-byte header carrying ``SPACE=LPS`` the way 3D Slicer does, plus the frame).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np
from scipy import ndimage, sparse
from scipy.sparse import csgraph

from hrcore.errors import HeartregError
from hrcore.geometry import apply_to_points, check_transform
from imaging.files import atomic_path
from modeling.repair import clean_adjacency, taubin_smooth

__all__ = [
    "Mesh",
    "MeshError",
    "mask_to_mesh",
    "decimate",
    "check_mesh",
    "transform_mesh",
    "write_mesh",
    "read_ply",
]

#: Gaussian smoothing of the binary mask before the isosurface, in voxels.
DEFAULT_SIGMA_VOX = 0.7
#: Taubin smoothing defaults (pymeshlab ``apply_coord_taubin_smoothing``).
TAUBIN_LAMBDA = 0.5
TAUBIN_MU = -0.53
#: Holes with up to this many boundary edges are closed.
MAX_HOLE_EDGES = 1000


class MeshError(HeartregError, ValueError):
    """The mask or the mesh cannot make a closed, manifold, outward-oriented surface."""


@dataclass(frozen=True, eq=False)
class Mesh:
    """A triangle mesh; read-only arrays.

    Attributes
    ----------
    vertices : (n, 3) float64, mm
        Vertex positions, in the frame the producer states (patient for
        :func:`mask_to_mesh`).
    faces : (m, 3) int64
        Vertex indices of each triangle, counter-clockwise seen from outside
        (right-hand normal points out of the enclosed volume).
    """

    vertices: np.ndarray
    faces: np.ndarray

    def __post_init__(self):
        v = np.array(self.vertices, dtype=np.float64, copy=True)
        f = np.array(self.faces, copy=True)
        if v.ndim != 2 or v.shape[1] != 3:
            raise ValueError(f"vertices must have shape (n, 3), got {v.shape}")
        if f.ndim != 2 or f.shape[1] != 3:
            raise ValueError(f"faces must have shape (m, 3), got {f.shape}")
        if f.size and not np.issubdtype(f.dtype, np.integer):
            raise ValueError(f"faces must be integer indices, got dtype {f.dtype}")
        f = f.astype(np.int64)
        if f.size and (f.min() < 0 or f.max() >= len(v)):
            raise ValueError(
                f"faces index vertices 0..{len(v) - 1}, found indices {f.min()}..{f.max()}"
            )
        if not np.all(np.isfinite(v)):
            raise ValueError("vertices contain NaN or infinity")
        v.setflags(write=False)
        f.setflags(write=False)
        object.__setattr__(self, "vertices", v)
        object.__setattr__(self, "faces", f)

    def __eq__(self, other):
        if not isinstance(other, Mesh):
            return NotImplemented
        return np.array_equal(self.vertices, other.vertices) and np.array_equal(
            self.faces, other.faces
        )

    __hash__ = None

    @property
    def n_vertices(self) -> int:
        return int(len(self.vertices))

    @property
    def n_faces(self) -> int:
        return int(len(self.faces))

    @cached_property
    def volume_mm3(self) -> float:
        """Signed enclosed volume (divergence theorem); > 0 for outward normals."""
        a, b, c = (self.vertices[self.faces[:, i]] for i in range(3))
        return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)

    @cached_property
    def area_mm2(self) -> float:
        a, b, c = (self.vertices[self.faces[:, i]] for i in range(3))
        return float(0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1).sum())

    @cached_property
    def face_normals(self) -> np.ndarray:
        """(m, 3) float64 unit normals (right-hand rule of the face winding)."""
        a, b, c = (self.vertices[self.faces[:, i]] for i in range(3))
        n = np.cross(b - a, c - a)
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
        n.setflags(write=False)
        return n

    def to_trimesh(self):
        """A ``trimesh.Trimesh`` view (no merging or reordering of vertices)."""
        import trimesh

        return trimesh.Trimesh(
            vertices=np.array(self.vertices), faces=np.array(self.faces), process=False
        )


@dataclass(frozen=True)
class MeshCheck:
    """Topology and orientation of a mesh (see :func:`check_mesh`)."""

    watertight: bool
    winding_consistent: bool
    volume_mm3: float
    euler_number: int
    n_components: int

    @property
    def ok(self) -> bool:
        return (
            self.watertight
            and self.winding_consistent
            and self.volume_mm3 > 0
            and self.n_components == 1
        )


def check_mesh(mesh: Mesh) -> MeshCheck:
    """Check that ``mesh`` is one closed, manifold, outward-oriented surface.

    Watertight means every edge is shared by exactly two faces (which also
    rules out non-manifold edges); winding consistency means those two faces
    traverse the edge in opposite directions; outward orientation means the
    signed volume is positive.
    """
    faces = np.asarray(mesh.faces, dtype=np.int64)
    n = max(int(mesh.n_vertices), 1)
    a = faces.ravel()
    b = faces[:, [1, 2, 0]].ravel()
    directed = np.sort(a * n + b)
    unique_directed = directed.size == 0 or bool(np.all(directed[1:] != directed[:-1]))
    if unique_directed and not np.any(a == b):
        # each undirected edge is there once or twice, twice exactly when its reverse is
        # there too: closed under reversal <=> watertight <=> consistently wound
        winding = bool(np.array_equal(directed, np.sort(b * n + a)))
        watertight = winding and bool(len(faces))
        n_edges = directed.size // 2 if winding else int(np.unique(np.minimum(a, b) * n + np.maximum(a, b)).size)
    else:  # repeated directed edges, or a face that repeats a vertex
        _, counts = np.unique(np.minimum(a, b) * n + np.maximum(a, b), return_counts=True)
        watertight, n_edges = bool(len(faces)) and bool(np.all(counts == 2)), int(counts.size)
        winding = unique_directed and bool(np.array_equal(directed, np.sort(b * n + a)))
    used = np.bincount(a, minlength=mesh.n_vertices) > 0
    labels = _vertex_components(faces, mesh.n_vertices)
    return MeshCheck(
        watertight=watertight,
        winding_consistent=winding,
        volume_mm3=mesh.volume_mm3,
        euler_number=int(used.sum()) - n_edges + int(len(faces)),
        n_components=int(np.count_nonzero(np.bincount(labels[used]))) if len(faces) else 0,
    )


def transform_mesh(T_to_from_from: np.ndarray, mesh: Mesh) -> Mesh:
    """Map a mesh through a rigid transform (winding kept: det must be +1).

    Parameters
    ----------
    T_to_from_from : (4, 4) float64
        Rigid transform from the mesh's frame to the target frame.
    mesh : Mesh

    Returns
    -------
    Mesh
        Same faces, vertices in the target frame.
    """
    T = check_transform(T_to_from_from, name="T_to_from_from")
    if np.linalg.det(T[:3, :3]) <= 0:
        raise ValueError("T_to_from_from must be a proper rigid transform (det > 0)")
    return Mesh(apply_to_points(T, mesh.vertices), mesh.faces)


# ----------------------------------------------------------------------- meshing
def mask_to_mesh(
    mask: np.ndarray,
    T_patient_from_voxel: np.ndarray,
    *,
    target_faces: int = 20000,
    smooth_iterations: int = 10,
    sigma_vox: float = DEFAULT_SIGMA_VOX,
    fill_cavities: bool = True,
    progress: bool = False,
) -> Mesh:
    """Closed, smooth, decimated surface of a binary mask, in patient mm.

    Parameters
    ----------
    mask : (n_k, n_j, n_i) bool
        Segmentation indexed ``[k, j, i]`` like ``Volume.hu``.
    T_patient_from_voxel : (4, 4) float64
        Affine mapping homogeneous ``(i, j, k, 1)`` to patient LPS mm. May be
        oblique, anisotropic, or a reflection.
    target_faces : int
        Face count after decimation (no decimation if the mesh is already smaller).
    smooth_iterations : int
        Taubin lambda/mu steps (0 disables smoothing).
    sigma_vox : float
        Gaussian smoothing of the float mask before the isosurface, in voxels
        (anti-aliasing of the voxel staircase; 0 disables).
    fill_cavities : bool
        Fill enclosed cavities first, so only the outer surface is meshed
        (the epicardium, not the ventricles' blood pools).
    progress : bool
        Show a progress bar on stderr.

    Returns
    -------
    Mesh
        Vertices in patient mm, outward normals, watertight and manifold.

    Raises
    ------
    MeshError
        Empty mask, or a surface that repair cannot make closed and manifold.
    """
    mask = np.asarray(mask)
    if mask.ndim != 3:
        raise ValueError(f"mask must be a 3-D (k, j, i) array, got shape {mask.shape}")
    if mask.dtype != bool:
        raise ValueError(f"mask must be boolean, got dtype {mask.dtype}; use mask > 0")
    T = check_transform(T_patient_from_voxel, name="T_patient_from_voxel")
    if abs(np.linalg.det(T[:3, :3])) < 1e-12:
        raise ValueError("T_patient_from_voxel is singular (zero voxel spacing?)")
    if int(target_faces) < 100:
        raise ValueError(f"target_faces must be >= 100, got {target_faces}")
    if int(smooth_iterations) < 0:
        raise ValueError(f"smooth_iterations must be >= 0, got {smooth_iterations}")
    if sigma_vox < 0:
        raise ValueError(f"sigma_vox must be >= 0, got {sigma_vox}")

    steps = _Steps(progress, 7)
    idx = np.nonzero(mask.any(axis=(1, 2)))[0]
    if idx.size == 0:
        raise MeshError("the mask is empty: nothing to mesh; check the segmentation")

    # 1. crop + pad ------------------------------------------------------------
    steps.next("crop")
    pad = int(np.ceil(3 * sigma_vox)) + 2
    lo, hi = [], []
    for axis in range(3):
        other = tuple(a for a in range(3) if a != axis)
        nz = np.nonzero(mask.any(axis=other))[0]
        lo.append(nz[0])
        hi.append(nz[-1] + 1)
    solid = np.pad(mask[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]], pad, mode="constant")
    if fill_cavities:
        # the background reached from the padding is outside; the rest is solid
        background = np.empty(solid.shape, np.int32)
        ndimage.label(~solid, output=background)
        solid = background != background[0, 0, 0]
        del background
    field = solid.astype(np.float32)
    del solid
    if sigma_vox > 0:
        ndimage.gaussian_filter(field, sigma_vox, mode="constant", output=field)  # in place

    # 2. isosurface -------------------------------------------------------------
    steps.next("marching cubes")
    from skimage.measure import marching_cubes

    verts_kji, faces, _, _ = marching_cubes(field, level=0.5, allow_degenerate=False)
    del field
    verts_kji = verts_kji.astype(np.float64) + (np.asarray(lo, float) - pad)

    # 3. (k, j, i) -> (i, j, k) -> patient; fix the winding of a reflection ---
    verts_ijk = verts_kji[:, ::-1]
    verts = apply_to_points(T, verts_ijk)
    # skimage orients faces so normals point down the gradient (out of the mask)
    # in (k, j, i) index space; the axis swap has det -1, the affine det(A).
    if -np.linalg.det(T[:3, :3]) < 0:
        faces = faces[:, ::-1]
    faces = np.ascontiguousarray(faces, dtype=np.int64)

    # 4. largest component ---------------------------------------------------------
    steps.next("largest component")
    verts, faces = _largest_component(verts, faces)

    # 5-6. repair + Taubin smoothing --------------------------------------------
    steps.next("repair + smoothing")
    verts, faces = _repair(verts, faces, smooth_iterations=int(smooth_iterations))

    # 7. decimation ---------------------------------------------------------------
    steps.next("decimation")
    verts, faces = _decimate(verts, faces, target_faces)

    # 8. verify -----------------------------------------------------------------------
    steps.next("verify")
    mesh = Mesh(verts, faces)
    check = check_mesh(mesh)
    if check.ok:
        steps.close()
        return mesh
    # a consistently wound closed mesh that came out inside-out: flip (never expected)
    if check.watertight and check.winding_consistent and check.volume_mm3 < 0:
        mesh = Mesh(mesh.vertices, mesh.faces[:, ::-1])
        check = check_mesh(mesh)
    steps.close()
    if not check.ok:
        raise MeshError(
            "the surface is not a single closed, manifold, outward-oriented mesh after "
            f"repair (watertight={check.watertight}, winding_consistent="
            f"{check.winding_consistent}, volume={check.volume_mm3:.1f} mm^3, "
            f"components={check.n_components}); check the mask for thin bridges or "
            "one-voxel structures, or raise target_faces"
        )
    return mesh


class _Steps:
    """Optional tqdm progress over named steps."""

    def __init__(self, enabled: bool, total: int):
        self._bar = None
        if enabled:
            from tqdm import tqdm

            self._bar = tqdm(total=total, desc="mesh", unit="step", leave=False)
        self._started = False

    def next(self, name: str) -> None:
        if self._bar is None:
            return
        if self._started:
            self._bar.update(1)
        self._started = True
        self._bar.set_postfix_str(name)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.update(1)
            self._bar.close()


def _decimate(verts, faces, target_faces: int):
    """Quadric decimation to ``target_faces`` (fast_simplification), then repair."""
    if len(faces) <= target_faces:
        return verts, faces
    import fast_simplification

    reduction = 1.0 - float(target_faces) / len(faces)
    verts, faces = fast_simplification.simplify(  # writable copies: its binding refuses read-only arrays
        np.array(verts, dtype=np.float64, order="C"),
        np.array(faces, dtype=np.int64, order="C"),
        target_reduction=reduction,
    )
    verts, faces = _repair(np.asarray(verts, np.float64), np.asarray(faces), smooth_iterations=0)
    return _largest_component(verts, faces)


def decimate(mesh: Mesh, target_faces: int) -> Mesh:
    """Decimate a closed mesh to about ``target_faces`` faces (quadric, then repair).

    Raises
    ------
    MeshError
        If the result is not a single closed, outward-oriented surface.
    """
    if target_faces < 100:
        raise ValueError(f"target_faces must be at least 100, got {target_faces}")
    verts, faces = _decimate(np.asarray(mesh.vertices), np.asarray(mesh.faces), int(target_faces))
    out = Mesh(verts, faces)
    check = check_mesh(out)
    if not check.ok:
        raise MeshError(f"decimation to {target_faces} faces broke the surface ({check}); raise target_faces")
    return out


def _vertex_components(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """Connected-component label of each vertex through the faces' edges."""
    if len(faces) == 0:
        return np.arange(n_vertices)
    rows = np.concatenate([faces[:, 0], faces[:, 1]])
    cols = np.concatenate([faces[:, 1], faces[:, 2]])
    graph = sparse.coo_matrix(
        (np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(n_vertices, n_vertices)
    )
    _, labels = csgraph.connected_components(graph, directed=False)
    return labels


def _largest_component(verts: np.ndarray, faces: np.ndarray):
    """Keep the connected component with the most faces; drop unused vertices."""
    if len(faces) == 0:
        raise MeshError("the isosurface has no faces; is the mask only a few voxels?")
    labels = _vertex_components(faces, len(verts))
    face_label = labels[faces[:, 0]]
    keep = face_label == np.bincount(face_label).argmax()
    faces = faces[keep]
    used = np.flatnonzero(np.bincount(faces.ravel(), minlength=len(verts)))
    remap = np.full(len(verts), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return verts[used], remap[faces]


def _repair(verts: np.ndarray, faces: np.ndarray, *, smooth_iterations: int):
    """Clean-up, hole closing and Taubin smoothing.

    A mesh that needs no clean-up (:func:`modeling.repair.clean_adjacency`) is only smoothed, in
    numpy; any other goes through pymeshlab.
    """
    adjacency = clean_adjacency(verts, faces)
    if adjacency is not None:
        return taubin_smooth(verts, adjacency, smooth_iterations, lambda_=TAUBIN_LAMBDA, mu=TAUBIN_MU), faces
    return _repair_pymeshlab(verts, faces, smooth_iterations=smooth_iterations)


def _repair_pymeshlab(verts: np.ndarray, faces: np.ndarray, *, smooth_iterations: int):
    """pymeshlab clean-up, hole closing and Taubin smoothing."""
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=verts, face_matrix=faces.astype(np.int32)))
    ms.meshing_remove_duplicate_vertices()
    ms.meshing_remove_duplicate_faces()
    ms.meshing_remove_null_faces()
    ms.meshing_repair_non_manifold_edges(method="Remove Faces")
    ms.meshing_repair_non_manifold_vertices()
    ms.meshing_remove_unreferenced_vertices()
    ms.meshing_close_holes(maxholesize=MAX_HOLE_EDGES, selfintersection=False)
    ms.meshing_remove_unreferenced_vertices()
    if smooth_iterations > 0:
        ms.apply_coord_taubin_smoothing(
            lambda_=TAUBIN_LAMBDA, mu=TAUBIN_MU, stepsmoothnum=smooth_iterations
        )
    m = ms.current_mesh()
    return (
        np.asarray(m.vertex_matrix(), dtype=np.float64),
        np.asarray(m.face_matrix(), dtype=np.int64),
    )


# ------------------------------------------------------------------------------ I/O
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
