"""Rigid transforms: 4x4 homogeneous matrices, rotations and their distances.

The 4x4 basics (check, apply, invert, compose, Kabsch) live in
:mod:`hrcore.geometry`, below every package; they are re-exported here under
their old names.

Conventions (DESIGN.md section 3): a transform is a (4, 4) float64 matrix named
``T_<to>_from_<from>``; transforms compose right to left,
``T_a_from_c = T_a_from_b @ T_b_from_c``.  Rotations go through
:class:`scipy.spatial.transform.Rotation`.  Angles are radians inside the library;
the ``*_deg`` functions exist for reports, where Euler angles are intrinsic
X-Y-Z, ``R = Rx(alpha) Ry(beta) Rz(gamma)`` (scipy sequence ``"XYZ"``), as in
Table 1 of Wood et al. 2018.

Stacks of transforms, shape ``(..., 4, 4)``, are accepted wherever noted.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from hrcore.geometry import (
    RIGID_TOL,
    TransformError,
    apply_to_points,
    apply_to_vectors,
    check_points,
    check_rigid,
    check_transform,
    compose,
    invert,
)

__all__ = [
    "RIGID_TOL",
    "TransformError",
    "make_transform",
    "check_rigid",
    "compose",
    "invert",
    "apply_to_points",
    "apply_to_vectors",
    "matrix_from_euler_xyz_deg",
    "euler_xyz_deg_from_matrix",
    "rotation_exp",
    "rotation_log",
    "se3_exp",
    "se3_log",
    "mean_rotation",
    "rotation_distance_deg",
    "translation_distance_mm",
]


def make_transform(rotation=None, translation_mm=None) -> np.ndarray:
    """Build a rigid transform from a rotation and a translation.

    Parameters
    ----------
    rotation : (3, 3) float or scipy Rotation, optional
        Rotation matrix (or ``Rotation``); identity when omitted.
    translation_mm : (3,) float, mm, optional
        Translation; zero when omitted.

    Returns
    -------
    (4, 4) float64
    """
    T = np.eye(4)
    if rotation is not None:
        if isinstance(rotation, Rotation):
            R = rotation.as_matrix()
        else:
            R = np.asarray(rotation, dtype=float)
        if R.shape != (3, 3):
            raise ValueError(f"rotation must have shape (3, 3), got {R.shape}")
        T[:3, :3] = R
    if translation_mm is not None:
        t = np.asarray(translation_mm, dtype=float)
        if t.shape != (3,):
            raise ValueError(f"translation_mm must have shape (3,), got {t.shape}")
        T[:3, 3] = t
    return T


def matrix_from_euler_xyz_deg(angles_deg, translation_mm=None) -> np.ndarray:
    """Rigid transform with rotation ``Rx(alpha) Ry(beta) Rz(gamma)`` (intrinsic X-Y-Z).

    Parameters
    ----------
    angles_deg : (..., 3) float, degrees
        (alpha, beta, gamma).
    translation_mm : (..., 3) float, mm, optional

    Returns
    -------
    (..., 4, 4) float64
    """
    angles = check_points(angles_deg, name="angles_deg")
    flat = angles.reshape(-1, 3)
    R = Rotation.from_euler("XYZ", flat, degrees=True).as_matrix()
    T = np.zeros((flat.shape[0], 4, 4))
    T[:, :3, :3] = R
    T[:, 3, 3] = 1.0
    if translation_mm is not None:
        t = check_points(translation_mm, name="translation_mm")
        T[:, :3, 3] = np.broadcast_to(t, angles.shape).reshape(-1, 3)
    return T.reshape(angles.shape[:-1] + (4, 4))


def euler_xyz_deg_from_matrix(T) -> np.ndarray:
    """Intrinsic X-Y-Z Euler angles (degrees) of the rotation of ``T``.

    Parameters
    ----------
    T : (..., 4, 4) or (..., 3, 3) float

    Returns
    -------
    (..., 3) float64, degrees
        (alpha, beta, gamma) with ``R = Rx(alpha) Ry(beta) Rz(gamma)``; beta in
        [-90, 90].  Near beta = +-90 (gimbal lock) alpha and gamma are not unique;
        scipy then sets gamma = 0 and warns.
    """
    M = np.asarray(T, dtype=float)
    if M.ndim < 2 or M.shape[-2:] not in ((4, 4), (3, 3)):
        raise ValueError(f"T must have shape (..., 4, 4) or (..., 3, 3), got {M.shape}")
    R = M[..., :3, :3]
    flat = R.reshape(-1, 3, 3)
    angles = Rotation.from_matrix(flat).as_euler("XYZ", degrees=True)
    return angles.reshape(R.shape[:-2] + (3,))


def rotation_exp(rotvec) -> np.ndarray:
    """Exponential map: rotation vectors (radians, axis * angle) to matrices.

    Parameters
    ----------
    rotvec : (..., 3) float, rad

    Returns
    -------
    (..., 3, 3) float64
    """
    rv = check_points(rotvec, name="rotvec")
    R = Rotation.from_rotvec(rv.reshape(-1, 3)).as_matrix()
    return R.reshape(rv.shape[:-1] + (3, 3))


def rotation_log(R) -> np.ndarray:
    """Logarithm map: rotation matrices to rotation vectors (angle in [0, pi]).

    Parameters
    ----------
    R : (..., 3, 3) float

    Returns
    -------
    (..., 3) float64, rad
    """
    R = np.asarray(R, dtype=float)
    if R.ndim < 2 or R.shape[-2:] != (3, 3):
        raise ValueError(f"R must have shape (..., 3, 3), got {R.shape}")
    rv = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_rotvec()
    return rv.reshape(R.shape[:-2] + (3,))


def _so3_left_jacobian(rotvec: np.ndarray) -> np.ndarray:
    """Left Jacobian V of SO(3) so that ``t = V rho`` in the SE(3) exponential."""
    theta = np.linalg.norm(rotvec, axis=-1)[..., None, None]
    K = np.zeros(rotvec.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2] = -rotvec[..., 2], rotvec[..., 1]
    K[..., 1, 0], K[..., 1, 2] = rotvec[..., 2], -rotvec[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -rotvec[..., 1], rotvec[..., 0]
    small = theta < 1e-6
    th = np.where(small, 1.0, theta)
    a = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(th)) / th**2)
    b = np.where(small, 1.0 / 6.0 - theta**2 / 120.0, (th - np.sin(th)) / th**3)
    return np.eye(3) + a * K + b * (K @ K)


def se3_exp(twist) -> np.ndarray:
    """Exponential map of SE(3): twists ``(rho, omega)`` to rigid transforms.

    Parameters
    ----------
    twist : (..., 6) float
        ``rho`` (mm) then ``omega`` (rad), the convention of Lie-group robotics
        texts: ``T = [[exp(omega^), V(omega) rho], [0, 1]]``.

    Returns
    -------
    (..., 4, 4) float64
    """
    twist = np.asarray(twist, dtype=float)
    if twist.ndim < 1 or twist.shape[-1] != 6:
        raise ValueError(f"twist must have shape (..., 6), got {twist.shape}")
    rho, omega = twist[..., :3], twist[..., 3:]
    T = np.zeros(twist.shape[:-1] + (4, 4))
    T[..., :3, :3] = rotation_exp(omega)
    T[..., :3, 3] = np.einsum("...ij,...j->...i", _so3_left_jacobian(omega), rho)
    T[..., 3, 3] = 1.0
    return T


def se3_log(T) -> np.ndarray:
    """Logarithm map of SE(3), inverse of :func:`se3_exp` (rotation angle < pi).

    Parameters
    ----------
    T : (..., 4, 4) float

    Returns
    -------
    (..., 6) float64
        ``(rho [mm], omega [rad])``.
    """
    T = check_transform(T, stack=True, finite=False)
    omega = rotation_log(T[..., :3, :3])
    V = _so3_left_jacobian(omega)
    rho = np.linalg.solve(V, T[..., :3, 3][..., None])[..., 0]
    return np.concatenate([rho, omega], axis=-1)


def mean_rotation(R, weights=None) -> np.ndarray:
    """Chordal L2 mean of rotations (Markley's quaternion average, ``Rotation.mean``).

    Parameters
    ----------
    R : (n, 3, 3) float
        Rotation matrices, n >= 1.
    weights : (n,) float, optional
        Non-negative weights.

    Returns
    -------
    (3, 3) float64
        The rotation maximising ``sum w_i (q . q_i)^2``; insensitive to the sign
        of each quaternion.
    """
    R = np.asarray(R, dtype=float)
    if R.ndim != 3 or R.shape[1:] != (3, 3) or R.shape[0] == 0:
        raise ValueError(f"R must have shape (n, 3, 3) with n >= 1, got {R.shape}")
    if weights is not None:
        weights = np.asarray(weights, dtype=float)
        if weights.shape != (R.shape[0],):
            raise ValueError(f"weights must have shape ({R.shape[0]},), got {weights.shape}")
        if np.any(weights < 0):
            raise ValueError("weights must be non-negative")
    return Rotation.from_matrix(R).mean(weights=weights).as_matrix()


def rotation_distance_deg(T_a, T_b) -> np.ndarray:
    """Geodesic distance between the rotations of two transforms, degrees.

    Parameters
    ----------
    T_a, T_b : (..., 4, 4) or (..., 3, 3) float
        Broadcast against each other.

    Returns
    -------
    (...) float64, degrees in [0, 180]
        The angle of ``R_a^T R_b``.

    Examples
    --------
    >>> import numpy as np
    >>> from scipy.spatial.transform import Rotation
    >>> from registration import rotation_distance_deg
    >>> T_a, T_b = np.eye(4), np.eye(4)
    >>> T_b[:3, :3] = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    >>> print(round(float(rotation_distance_deg(T_a, T_b)), 6))
    30.0
    >>> rotation_distance_deg(T_a, np.stack([T_a, T_b])).round(6).tolist()  # a stack of poses
    [0.0, 30.0]
    """
    A = np.asarray(T_a, dtype=float)[..., :3, :3]
    B = np.asarray(T_b, dtype=float)[..., :3, :3]
    rel = np.swapaxes(A, -1, -2) @ B
    # angle from the quaternion of rel: robust near 0 and near pi.
    shape = rel.shape[:-2]
    q = Rotation.from_matrix(rel.reshape(-1, 3, 3)).as_quat()
    angle = 2.0 * np.arctan2(np.linalg.norm(q[:, :3], axis=1), np.abs(q[:, 3]))
    return np.degrees(angle).reshape(shape)


def translation_distance_mm(T_a, T_b, point_mm=None) -> np.ndarray:
    """Distance between where two transforms send a point, mm.

    Parameters
    ----------
    T_a, T_b : (..., 4, 4) float
        Transforms with the same source and target frames.
    point_mm : (3,) float, mm, optional
        The point in the source frame; the source origin by default, so the
        result is ``|t_a - t_b|``, the norm of the translation difference.

    Returns
    -------
    (...) float64, mm

    Examples
    --------
    >>> import numpy as np
    >>> from scipy.spatial.transform import Rotation
    >>> from registration import translation_distance_mm
    >>> T_a, T_b = np.eye(4), np.eye(4)
    >>> T_b[:3, 3] = [3.0, 4.0, 0.0]
    >>> print(round(float(translation_distance_mm(T_a, T_b)), 6))
    5.0

    A rotation moves points away from its axis: 90 degrees about z sends the
    point 10 mm along x a distance 10 * sqrt(2) away.

    >>> T_b = np.eye(4)
    >>> T_b[:3, :3] = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    >>> print(round(float(translation_distance_mm(T_a, T_b)), 6))
    0.0
    >>> print(round(float(translation_distance_mm(T_a, T_b, point_mm=[10.0, 0.0, 0.0])), 3))
    14.142
    """
    A = check_transform(T_a, name="T_a", stack=True, finite=False)
    B = check_transform(T_b, name="T_b", stack=True, finite=False)
    if point_mm is None:
        diff = A[..., :3, 3] - B[..., :3, 3]
    else:
        p = np.asarray(point_mm, dtype=float)
        if p.shape != (3,):
            raise ValueError(f"point_mm must have shape (3,), got {p.shape}")
        diff = (A[..., :3, :3] - B[..., :3, :3]) @ p + A[..., :3, 3] - B[..., :3, 3]
    return np.linalg.norm(diff, axis=-1)
