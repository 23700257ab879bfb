"""The triangle mesh of a model: :class:`Mesh`, its checks and rigid transforms.

A :class:`Mesh` holds float64 vertices in mm and int32 triangles wound so that
normals point out of the enclosed volume; :func:`check_mesh` says whether it is
closed, manifold and consistently wound. Made from a mask by
:mod:`modeling.surface`, written and read by :mod:`modeling.mesh_io`.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph

from hrcore.errors import HeartregError
from hrcore.geometry import apply_to_points, check_transform

__all__ = ["Mesh", "MeshCheck", "MeshError", "check_mesh", "transform_mesh", "vertex_normals"]


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


def vertex_normals(vertices, faces) -> np.ndarray:
    """(n, 3) unit vertex normals: the sum of the faces' area-weighted normals (0 where none).

    Outward for a mesh wound counter-clockwise seen from outside.
    """
    v = np.asarray(vertices, dtype=float)
    f = np.asarray(faces)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    normals = np.zeros_like(v)
    for c in range(3):
        np.add.at(normals, f[:, c], fn)
    return normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
