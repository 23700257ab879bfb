"""Homogeneous 4x4 transforms: check, apply, invert, compose, fit (Kabsch).

The one geometry every package uses (``imaging``, ``modeling``,
``registration``, ``heartreg``); :mod:`registration.transforms` adds the
rotation algebra (Euler angles, SO(3)/SE(3) maps, means, distances) on top.
The phantom (``heartreg.phantom``) keeps its own copy, checked against this one
by the tests.

Conventions (DESIGN.md section 3): a transform is a (4, 4) float64 matrix named
``T_<to>_from_<from>``; transforms compose right to left,
``T_a_from_c = T_a_from_b @ T_b_from_c``; points are rows, ``(..., 3)`` in mm.
Stacks of transforms, shape ``(..., 4, 4)``, are accepted wherever noted.

Examples
--------
>>> import numpy as np
>>> from hrcore.geometry import apply_to_points, compose, invert, kabsch
>>> T_b_from_a = np.array([[0.0, -1, 0, 10], [1, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
>>> apply_to_points(T_b_from_a, [1.0, 0.0, 0.0])
array([10.,  1.,  0.])
>>> np.allclose(compose(invert(T_b_from_a), T_b_from_a), np.eye(4))
True
>>> a = np.array([[0.0, 0, 0], [1, 0, 0], [0, 2, 0], [0, 0, 3]])
>>> np.allclose(kabsch(a, apply_to_points(T_b_from_a, a)), T_b_from_a)
True
"""

from __future__ import annotations

import numpy as np

from hrcore.errors import HeartregError

__all__ = [
    "RIGID_TOL",
    "TransformError",
    "check_transform",
    "check_rigid",
    "is_rigid",
    "check_points",
    "apply_to_points",
    "apply_to_vectors",
    "invert",
    "compose",
    "interpolate_poses",
    "kabsch",
    "frozen",
]

#: Default tolerance on ``R^T R - I``, ``det R - 1`` and the last row ``(0, 0, 0, 1)``.
RIGID_TOL = 1e-6

_LAST_ROW = np.array([0.0, 0.0, 0.0, 1.0])


class TransformError(HeartregError, ValueError):
    """A matrix that should be a 4x4 transform is not (shape, values, rotation, last row)."""


def check_transform(T, *, name: str = "T", rigid: bool = False, tol: float = RIGID_TOL,
                    stack: bool = False, finite: bool = True) -> np.ndarray:
    """Return ``T`` as float64 after checking it is a homogeneous 4x4 transform.

    Parameters
    ----------
    T : (4, 4) float, or (..., 4, 4) with ``stack=True``
    name : str
        The argument's name, for the message.
    rigid : bool
        Also require a proper rotation block (orthonormal, determinant +1).
    tol : float
        Tolerance on the last row, and with ``rigid`` on ``R^T R - I`` and
        ``det R - 1``.
    stack : bool
        Accept a stack ``(..., 4, 4)`` instead of one matrix.
    finite : bool
        Refuse NaN or infinite entries. With ``finite=False`` non-finite
        matrices of a stack (invalid frames) pass; the others are checked.

    Returns
    -------
    (4, 4) or (..., 4, 4) float64
        A new array only when ``T`` was not float64 already.

    Raises
    ------
    TransformError
        One line naming ``name``: wrong shape, non-finite entries, last row not
        ``(0, 0, 0, 1)``, rotation block not orthonormal or a reflection.
    """
    T = _check_shape(T, name, stack)
    if finite and not np.all(np.isfinite(T)):
        raise TransformError(f"{name} has non-finite entries (NaN or infinity)")
    # NaN compares False: the non-finite frames allowed by finite=False pass below
    if np.any(np.abs(T[..., 3, :] - _LAST_ROW) > tol):
        raise TransformError(f"{name} last row must be (0, 0, 0, 1)")
    if rigid and T.size:
        ortho, det = _rotation_errors(T)
        if np.any(ortho > tol):
            raise TransformError(f"{name} is not a rigid transform: its rotation block is not orthonormal (max |R^T R - I| = {np.nanmax(ortho):.2e})")
        if np.any(np.abs(det - 1.0) > tol):
            raise TransformError(
                f"{name} is not a rigid transform: its rotation block has determinant {np.nanmin(det):.6f}: a reflection, not a rotation"
            )
    return T


def is_rigid(T, *, tol: float = RIGID_TOL, name: str = "T") -> np.ndarray:
    """Which matrices of a stack are finite proper rigid transforms, without raising.

    Parameters
    ----------
    T : (..., 4, 4) float
    tol : float
        Tolerance on ``R^T R - I``, ``det R - 1`` and the last row.
    name : str
        The argument's name, for the message on a wrong shape.

    Returns
    -------
    (...) bool
        For a reader that must say which frame of a file is bad.
    """
    T = _check_shape(T, name, stack=True)
    ortho, det = _rotation_errors(T)
    last = np.abs(T[..., 3, :] - _LAST_ROW).max(axis=-1)
    finite = np.all(np.isfinite(T), axis=(-2, -1))
    return finite & (ortho <= tol) & (np.abs(det - 1.0) <= tol) & (last <= tol)


def _check_shape(T, name: str, stack: bool) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if stack and (T.ndim < 2 or T.shape[-2:] != (4, 4)):
        raise TransformError(f"{name} must have shape (..., 4, 4), got {T.shape}")
    if not stack and T.shape != (4, 4):
        raise TransformError(f"{name} must have shape (4, 4), got {T.shape}")
    return T


def _rotation_errors(T: np.ndarray):
    """Per matrix: max ``|R^T R - I|`` and ``det R``, each ``(...)``."""
    R = T[..., :3, :3]
    ortho = np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max(axis=(-2, -1))
    with np.errstate(invalid="ignore"):  # NaN frames of a stack give NaN, not a warning
        return ortho, np.linalg.det(R)


def check_rigid(T, *, tol: float = RIGID_TOL, name: str = "T") -> np.ndarray:
    """Return ``T`` (``(..., 4, 4)``) as float64 after checking it is a proper rigid transform.

    Shorthand for ``check_transform(T, name=name, rigid=True, tol=tol, stack=True)``.

    Raises
    ------
    TransformError
        When the shape is wrong, an entry is not finite, the rotation block is
        not orthonormal with determinant +1 (a reflection), or the last row is
        not ``(0, 0, 0, 1)``.
    """
    return check_transform(T, name=name, rigid=True, tol=tol, stack=True)


def check_points(points, *, name: str = "points") -> np.ndarray:
    """Return ``points`` as float64 after checking their shape is ``(..., 3)``.

    Raises
    ------
    ValueError
        One line naming ``name`` and the shape found.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim < 1 or points.shape[-1] != 3:
        raise ValueError(f"{name} must have shape (..., 3), got {points.shape}")
    return points


def apply_to_points(T_to_from_from, points) -> np.ndarray:
    """Map points through a 4x4 transform (rigid, or affine such as voxel to patient).

    Parameters
    ----------
    T_to_from_from : (4, 4) float
    points : (..., 3) float, mm
        Points in the source frame (voxel indices ``(i, j, k)`` for
        ``T_patient_from_voxel``).

    Returns
    -------
    (..., 3) float64, mm
        Points in the target frame.
    """
    T = check_transform(T_to_from_from, name="T_to_from_from", finite=False)
    return check_points(points) @ T[:3, :3].T + T[:3, 3]


def apply_to_vectors(T_to_from_from, vectors) -> np.ndarray:
    """Rotate direction vectors (normals, displacements) by a 4x4 transform.

    Parameters
    ----------
    T_to_from_from : (4, 4) float
    vectors : (..., 3) float

    Returns
    -------
    (..., 3) float64
        The vectors in the target frame (translation ignored).
    """
    T = check_transform(T_to_from_from, name="T_to_from_from", finite=False)
    return check_points(vectors, name="vectors") @ T[:3, :3].T


def invert(T) -> np.ndarray:
    """Inverse of rigid transforms, using ``R^T`` (exact for rigid matrices).

    Parameters
    ----------
    T : (..., 4, 4) float
        ``T_a_from_b``.

    Returns
    -------
    (..., 4, 4) float64
        ``T_b_from_a``.
    """
    T = check_transform(T, stack=True, finite=False)
    out = np.zeros_like(T)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def compose(*transforms) -> np.ndarray:
    """Compose transforms right to left: ``compose(A, B, C) = A @ B @ C``.

    Parameters
    ----------
    *transforms : (..., 4, 4) float
        At least one; stacks broadcast.

    Returns
    -------
    (..., 4, 4) float64
    """
    if not transforms:
        raise ValueError("compose needs at least one transform")
    out = check_transform(transforms[0], name="transforms[0]", stack=True, finite=False)
    for k, T in enumerate(transforms[1:], start=1):
        out = out @ check_transform(T, name=f"transforms[{k}]", stack=True, finite=False)
    return out


def interpolate_poses(T_a, T_b, w) -> np.ndarray:
    """Rigid poses a fraction ``w`` of the way from ``T_a`` to ``T_b``: translation linearly, rotation along
    the shortest arc (slerp).

    Parameters
    ----------
    T_a, T_b : (n, 4, 4) float
        Rigid poses (their rotations orthonormalised by scipy).
    w : (n,) float
        0 at ``T_a``, 1 at ``T_b``.

    Returns
    -------
    (n, 4, 4) float64

    Examples
    --------
    >>> import numpy as np
    >>> from scipy.spatial.transform import Rotation
    >>> T_b = np.eye(4)[None].copy()
    >>> T_b[0, :3, :3] = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    >>> T_b[0, :3, 3] = [10.0, 0.0, 0.0]
    >>> T = interpolate_poses(np.eye(4)[None], T_b, np.array([0.5]))
    >>> Rotation.from_matrix(T[0, :3, :3]).as_euler("xyz", degrees=True).round(6).tolist(), T[0, :3, 3].tolist()
    ([0.0, 0.0, 45.0], [5.0, 0.0, 0.0])
    """
    from scipy.spatial.transform import Rotation

    T_a, T_b = np.asarray(T_a, dtype=np.float64), np.asarray(T_b, dtype=np.float64)
    w = np.asarray(w, dtype=np.float64)[:, None]
    R_a = Rotation.from_matrix(T_a[:, :3, :3])
    arc = (R_a.inv() * Rotation.from_matrix(T_b[:, :3, :3])).as_rotvec()
    T = np.zeros((len(w), 4, 4))
    T[:, :3, :3] = (R_a * Rotation.from_rotvec(w * arc)).as_matrix()
    T[:, :3, 3] = (1.0 - w) * T_a[:, :3, 3] + w * T_b[:, :3, 3]
    T[:, 3, 3] = 1.0
    return T


def kabsch(source, target, *, weights=None) -> np.ndarray:
    """Least-squares rigid transform mapping ``source[i]`` onto ``target[i]`` (Kabsch/SVD).

    Parameters
    ----------
    source, target : (n, 3) or (b, n, 3) float, mm
        Corresponding points; a leading batch axis fits ``b`` problems at once.
    weights : (n,) or (b, n) float, optional
        Non-negative weights, not all zero; equal by default.

    Returns
    -------
    (4, 4) or (b, 4, 4) float64
        ``T_target_from_source`` minimising ``sum w_i |T s_i - t_i|^2``. The
        rotation is proper (det +1) even for coplanar or noisy points: the
        reflection an SVD may give is turned into the nearest rotation. The
        caller checks the points are not collinear (then the rotation about
        their line is arbitrary).
    """
    source = np.asarray(source, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    if source.ndim not in (2, 3) or source.shape[-1] != 3 or target.shape != source.shape:
        raise ValueError(
            f"source and target must have the same shape (n, 3) or (b, n, 3), got {source.shape} and {target.shape}"
        )
    w = np.ones(source.shape[:-1]) if weights is None else np.broadcast_to(np.asarray(weights, dtype=np.float64),
                                                                              source.shape[:-1])
    w = w / w.sum(axis=-1, keepdims=True)
    cs = np.einsum("...k,...ki->...i", w, source)
    ct = np.einsum("...k,...ki->...i", w, target)
    H = np.einsum("...k,...ki,...kj->...ij", w, source - cs[..., None, :], target - ct[..., None, :])
    U, _, Vt = np.linalg.svd(H)
    V, Ut = np.swapaxes(Vt, -1, -2), np.swapaxes(U, -1, -2)
    d = np.sign(np.linalg.det(V @ Ut))
    D = np.zeros(H.shape)
    D[..., 0, 0] = D[..., 1, 1] = 1.0
    D[..., 2, 2] = np.where(d == 0, 1.0, d)
    R = V @ D @ Ut
    T = np.zeros(H.shape[:-2] + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = ct - np.einsum("...ij,...j->...i", R, cs)
    T[..., 3, 3] = 1.0
    return T


def frozen(a, dtype=None) -> np.ndarray:
    """A read-only C-contiguous copy of ``a``, for the fields of frozen results.

    Parameters
    ----------
    a : array_like
    dtype : numpy dtype, optional
        The dtype of the copy; ``a``'s own by default. Floats become integers by
        rounding (``1.9999999`` read from text is 2), not by truncation.

    Returns
    -------
    numpy.ndarray
        Never a view of ``a``: the caller's array stays writable and unchanged.
    """
    a = np.asarray(a)
    if dtype is not None and np.issubdtype(np.dtype(dtype), np.integer) and not np.issubdtype(a.dtype, np.integer):
        a = np.round(a)
    out = np.array(a, dtype=dtype, order="C", copy=True)
    out.setflags(write=False)
    return out
