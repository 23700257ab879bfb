"""Amplitude-modulated dual Fourier motion model of a point on the heart (paper 2.2.5).

Each attachment point's pose ``T_probe_from_robot`` is modelled as a function of
the cardiac and respiration phases (phi_C, phi_R), both fractions of a cycle:

    t(phi) = t_mean + R_mean W_t^T phi(phi_C, phi_R)
    R(phi) = R_mean exp(W_w^T phi(phi_C, phi_R))

with the regressor (Fourier argument ``2 pi phase``)

    phi = [1,
           sin/cos(2 pi i phi_R)                      i = 1..Hr,
           sin/cos(2 pi i phi_C)                      i = 1..Hc,
           sin/cos(2 pi (i phi_C - j phi_R)),
           sin/cos(2 pi (i phi_C + j phi_R))          i = 1..Hmc, j = 1..Hmr]

(defaults Hc = 5, Hr = 4, Hmc = 2, Hmr = 1, as in Wood et al. 2018).  ``t_mean``
is the mean position, ``R_mean`` the mean rotation (quaternion average); the
translation is fitted in the mean robot frame and the rotation in exponential
coordinates about ``R_mean`` (rotation vectors of ``R_mean^T R(t)``).  Both are
linear least squares with one design matrix and 6 right-hand sides per point.
"""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from hrcore.blas import gram, one_blas_thread
from hrcore.errors import HeartregError

__all__ = [
    "Harmonics",
    "MotionModel",
    "MotionModelError",
    "CoverageWarning",
    "design_matrix",
    "fit_motion_model",
    "predict_positions",
]

TWO_PI = 2.0 * np.pi


class MotionModelError(HeartregError, ValueError):
    """Too few (valid) samples to fit the motion model."""


class CoverageWarning(UserWarning):
    """The phases of a trace do not cover the cycle: the model extrapolates there."""


#: Most harmonics per term of a motion model.  The heart's motion holds its energy in the first few (the
#: paper: 5 cardiac, 4 respiratory); 20 cardiac harmonics at 2 Hz reach the Nyquist frequency of a 100 Hz
#: tracker (500 and 400, accepted before session 15, took 98 s and fitted the noise: 4.4 mm off).
MAX_HARMONICS = 20


@dataclass(frozen=True)
class Harmonics:
    """Numbers of harmonics of the AM dual Fourier series.

    Attributes
    ----------
    cardiac, respiratory : int
        Hc and Hr, harmonics of phi_C and of phi_R alone.
    coupled_cardiac, coupled_respiratory : int
        Hmc and Hmr, the coupled terms ``i phi_C -+ j phi_R``.

    Examples
    --------
    >>> from registration import Harmonics
    >>> Harmonics().n_terms, Harmonics(2, 2, 1, 1).n_terms  # paper (5, 4, 2, 1); a small model
    (27, 13)
    """

    cardiac: int = 5
    respiratory: int = 4
    coupled_cardiac: int = 2
    coupled_respiratory: int = 1

    def __post_init__(self):
        for name in ("cardiac", "respiratory", "coupled_cardiac", "coupled_respiratory"):
            value = getattr(self, name)
            if int(value) != value or value < 0:
                raise ValueError(f"{name} must be a non-negative integer, got {value!r}")
            if value > MAX_HARMONICS:
                raise ValueError(f"{name} must be at most {MAX_HARMONICS}, got {value!r}: higher orders fit the "
                                 "noise (the paper uses 5 4 2 1)")

    @property
    def n_terms(self) -> int:
        """Number of regressor columns, ``1 + 2 Hr + 2 Hc + 4 Hmc Hmr``."""
        return (
            1
            + 2 * self.respiratory
            + 2 * self.cardiac
            + 4 * self.coupled_cardiac * self.coupled_respiratory
        )


def _as_phases(phase_c, phase_r):
    phase_c = np.atleast_1d(np.asarray(phase_c, dtype=float))
    phase_r = np.atleast_1d(np.asarray(phase_r, dtype=float))
    if phase_c.ndim != 1 or phase_r.ndim != 1:
        raise ValueError(
            f"phase_c and phase_r must be 1-D, got shapes {phase_c.shape} and {phase_r.shape}"
        )
    if phase_c.shape != phase_r.shape:
        phase_c, phase_r = np.broadcast_arrays(phase_c, phase_r)
    return phase_c, phase_r


def design_matrix(phase_c, phase_r, harmonics: Harmonics = Harmonics()) -> np.ndarray:
    """The regressor phi of each sample, in the column order of the module docstring.

    Parameters
    ----------
    phase_c, phase_r : (n,) float, cycles
        Cardiac and respiration phases (broadcast against each other).
    harmonics : Harmonics

    Returns
    -------
    (n, harmonics.n_terms) float64
    """
    phase_c, phase_r = _as_phases(phase_c, phase_r)
    h = harmonics
    n = phase_c.shape[0]
    X = np.empty((n, h.n_terms))
    X[:, 0] = 1.0
    # powers of unit complex numbers give every harmonic from two exponentials
    n_c = max(h.cardiac, h.coupled_cardiac)
    n_r = max(h.respiratory, h.coupled_respiratory)
    zc = np.cumprod(np.repeat(np.exp(1j * TWO_PI * phase_c)[:, None], max(n_c, 1), axis=1), axis=1)
    zr = np.cumprod(np.repeat(np.exp(1j * TWO_PI * phase_r)[:, None], max(n_r, 1), axis=1), axis=1)
    col = 1
    for z, count in ((zr, h.respiratory), (zc, h.cardiac)):
        if count:
            X[:, col : col + 2 * count : 2] = z[:, :count].imag
            X[:, col + 1 : col + 2 * count : 2] = z[:, :count].real
            col += 2 * count
    for i in range(1, h.coupled_cardiac + 1):
        for j in range(1, h.coupled_respiratory + 1):
            minus = zc[:, i - 1] * np.conj(zr[:, j - 1])
            plus = zc[:, i - 1] * zr[:, j - 1]
            X[:, col] = minus.imag
            X[:, col + 1] = minus.real
            X[:, col + 2] = plus.imag
            X[:, col + 3] = plus.real
            col += 4
    return X


@dataclass(frozen=True)
class MotionModel:
    """A fitted AM dual Fourier model of one point's pose (probe frame).

    Attributes
    ----------
    harmonics : Harmonics
    coef_translation : (k, 3) float64, mm
        ``W_t``: translation coefficients in the mean robot frame.
    coef_rotation : (k, 3) float64, rad
        ``W_w``: rotation-vector coefficients about the mean rotation.
    mean_position_mm : (3,) float64
        Sample mean of the positions (the paper's p_bar), probe frame.
    mean_rotation : (3, 3) float64
        Quaternion-average rotation of the samples.
    residual_rms_mm : (3,) float64
        RMS of the position residuals per axis (probe frame), mm.
    residual_rms_3d_mm : float
        RMS of the 3-D position residual, mm.
    residual_rms_deg : float
        RMS of the residual rotation angle, degrees.
    condition_number : float
        Of the column-scaled design matrix.
    n_samples : int
        Samples used in the fit.
    n_dropped : int
        Samples dropped for a NaN phase or a non-finite pose.
    """

    harmonics: Harmonics
    coef_translation: np.ndarray
    coef_rotation: np.ndarray
    mean_position_mm: np.ndarray
    mean_rotation: np.ndarray
    residual_rms_mm: np.ndarray
    residual_rms_3d_mm: float
    residual_rms_deg: float
    condition_number: float
    n_samples: int
    n_dropped: int = 0

    def predict_position(self, phase_c, phase_r) -> np.ndarray:
        """Robot position at the given phases.

        Parameters
        ----------
        phase_c, phase_r : (m,) float, cycles

        Returns
        -------
        (m, 3) float64, mm, probe frame
        """
        X = design_matrix(phase_c, phase_r, self.harmonics)
        return self.mean_position_mm + (X @ self.coef_translation) @ self.mean_rotation.T

    def predict_rotation(self, phase_c, phase_r) -> np.ndarray:
        """Robot orientation at the given phases, (m, 3, 3) float64."""
        X = design_matrix(phase_c, phase_r, self.harmonics)
        dR = Rotation.from_rotvec(X @ self.coef_rotation).as_matrix()
        return self.mean_rotation @ dR

    def predict(self, phase_c, phase_r) -> np.ndarray:
        """``T_probe_from_robot`` at the given phases, (m, 4, 4) float64."""
        X = design_matrix(phase_c, phase_r, self.harmonics)
        T = np.zeros((X.shape[0], 4, 4))
        T[:, :3, :3] = self.mean_rotation @ Rotation.from_rotvec(X @ self.coef_rotation).as_matrix()
        T[:, :3, 3] = self.mean_position_mm + (X @ self.coef_translation) @ self.mean_rotation.T
        T[:, 3, 3] = 1.0
        return T

    def predict_normal(self, phase_c, phase_r) -> np.ndarray:
        """Surface normal (the robot's z axis) at the given phases, (m, 3) unit vectors."""
        return self.predict_rotation(phase_c, phase_r)[:, :, 2]


def _coverage_gaps(phase, n_bins):
    counts = np.bincount(np.clip((np.mod(phase, 1.0) * n_bins).astype(int), 0, n_bins - 1), minlength=n_bins)
    return np.flatnonzero(counts == 0)


def fit_motion_model(
    phase_c,
    phase_r,
    T_probe_from_robot,
    *,
    harmonics: Harmonics = Harmonics(),
    coverage_bins: int = 10,
    rcond: float | None = None,
) -> MotionModel:
    """Fit the AM dual Fourier model to one point's pose trace.

    Parameters
    ----------
    phase_c, phase_r : (n,) float, cycles in [0, 1]
        Cardiac and respiration phase of each sample; NaN marks an undefined
        phase (outside the covered R-peaks or breaths): such samples are dropped
        and counted in ``n_dropped``.
    T_probe_from_robot : (n, 4, 4) float
        Robot poses in the probe frame, mm.
    harmonics : Harmonics
        Numbers of harmonics (paper defaults).
    coverage_bins : int
        The phases are checked for empty bins of width ``1 / coverage_bins``;
        empty bins raise a :class:`CoverageWarning` (the fit extrapolates there).
    rcond : float, optional
        Passed to :func:`numpy.linalg.lstsq`.

    Returns
    -------
    MotionModel

    Raises
    ------
    MotionModelError
        Fewer valid samples than regressor columns.

    Examples
    --------
    A point that moves 2 mm along x with the heartbeat (72 /min) and 5 mm along
    z with the breath (15 /min), sampled at 50 Hz for 30 s: a small model fits
    it exactly and predicts the pose at any pair of phases.

    >>> import numpy as np
    >>> from registration import Harmonics, fit_motion_model
    >>> t_s = np.arange(0.0, 30.0, 0.02)
    >>> phase_c, phase_r = (1.2 * t_s) % 1.0, (0.25 * t_s) % 1.0
    >>> T_probe_from_robot = np.tile(np.eye(4), (t_s.size, 1, 1))
    >>> T_probe_from_robot[:, :3, 3] = [100.0, 20.0, -50.0]
    >>> T_probe_from_robot[:, 0, 3] += 2.0 * np.sin(2 * np.pi * phase_c)
    >>> T_probe_from_robot[:, 2, 3] += 5.0 * np.cos(2 * np.pi * phase_r)
    >>> model = fit_motion_model(phase_c, phase_r, T_probe_from_robot, harmonics=Harmonics(2, 2, 1, 1))
    >>> print(model.n_samples, f"{model.residual_rms_3d_mm:.3f} mm")
    1500 0.000 mm
    >>> model.predict_position([0.25], [0.0]).round(3).tolist()  # phi_C = 0.25, phi_R = 0
    [[102.0, 20.0, -45.0]]
    """
    phase_c = np.asarray(phase_c, dtype=float)
    phase_r = np.asarray(phase_r, dtype=float)
    T = np.asarray(T_probe_from_robot, dtype=float)
    if phase_c.ndim != 1:
        raise ValueError(f"phase_c must have shape (n,), got {phase_c.shape}")
    if phase_r.shape != phase_c.shape:
        raise ValueError(f"phase_r must have shape {phase_c.shape}, got {phase_r.shape}")
    if T.shape != (phase_c.shape[0], 4, 4):
        raise ValueError(
            f"T_probe_from_robot must have shape ({phase_c.shape[0]}, 4, 4), got {T.shape}"
        )
    ok = np.isfinite(phase_c) & np.isfinite(phase_r) & np.all(np.isfinite(T), axis=(1, 2))
    for name, phase in (("phase_c", phase_c), ("phase_r", phase_r)):
        bad = phase[ok]
        if np.any((bad < 0) | (bad > 1)):
            raise ValueError(f"{name} must be fractions of a cycle in [0, 1]")
    n_dropped = int(np.count_nonzero(~ok))
    phase_c, phase_r, T = phase_c[ok], phase_r[ok], T[ok]
    n = phase_c.shape[0]
    if n < harmonics.n_terms:
        raise MotionModelError(
            f"{n} valid samples (of {n + n_dropped}; {n_dropped} with NaN phase or pose) "
            f"cannot fit {harmonics.n_terms} Fourier terms; record longer or lower the harmonics"
        )
    for name, phase in (("cardiac", phase_c), ("respiration", phase_r)):
        gaps = _coverage_gaps(phase, coverage_bins)
        if gaps.size:
            warnings.warn(
                f"{name} phase leaves {gaps.size} of {coverage_bins} bins empty "
                f"(e.g. [{gaps[0] / coverage_bins:.2f}, {(gaps[0] + 1) / coverage_bins:.2f})): "
                "the motion model extrapolates there; record over more cycles",
                CoverageWarning,
                stacklevel=2,
            )

    R_samples = T[:, :3, :3]
    rotations = Rotation.from_matrix(R_samples)
    R_mean = rotations.mean().as_matrix()
    t_mean = T[:, :3, 3].mean(axis=0)
    local_t = (T[:, :3, 3] - t_mean) @ R_mean  # R_mean^T (t - t_mean), row-wise
    rotvec = _relative_rotvec(Rotation.from_matrix(R_mean).as_quat(), rotations.as_quat())
    Y = np.concatenate([local_t, rotvec], axis=1)

    X = design_matrix(phase_c, phase_r, harmonics)
    coef, condition = _solve_least_squares(X, Y, rcond=rcond)

    model = MotionModel(
        harmonics=harmonics,
        coef_translation=coef[:, :3],
        coef_rotation=coef[:, 3:],
        mean_position_mm=t_mean,
        mean_rotation=R_mean,
        residual_rms_mm=np.zeros(3),
        residual_rms_3d_mm=0.0,
        residual_rms_deg=0.0,
        condition_number=condition,
        n_samples=n,
        n_dropped=n_dropped,
    )
    fitted = X @ coef
    pos_res = T[:, :3, 3] - (t_mean + fitted[:, :3] @ R_mean.T)
    R_fit = R_mean @ Rotation.from_rotvec(fitted[:, 3:]).as_matrix()
    # |R1 - R2|_F = 2 sqrt(2) sin(angle / 2): exact, and accurate at small angles
    chord = np.linalg.norm((R_fit - R_samples).reshape(-1, 9), axis=1) / (2.0 * np.sqrt(2.0))
    ang_res = 2.0 * np.arcsin(np.clip(chord, 0.0, 1.0))
    return dataclasses.replace(
        model,
        residual_rms_mm=np.sqrt(np.mean(pos_res**2, axis=0)),
        residual_rms_3d_mm=float(np.sqrt(np.mean(np.sum(pos_res**2, axis=1)))),
        residual_rms_deg=float(np.degrees(np.sqrt(np.mean(ang_res**2)))),
    )


def _relative_rotvec(q_mean, q):
    """Rotation vectors of ``q_mean^-1 q`` for scalar-last quaternions, (n, 3) rad."""
    x0, y0, z0, w0 = -q_mean[0], -q_mean[1], -q_mean[2], q_mean[3]  # conjugate
    x, y, z, w = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    rel = np.stack(
        [
            w0 * x + x0 * w + y0 * z - z0 * y,
            w0 * y - x0 * z + y0 * w + z0 * x,
            w0 * z + x0 * y - y0 * x + z0 * w,
            w0 * w - x0 * x - y0 * y - z0 * z,
        ],
        axis=1,
    )
    rel *= np.where(rel[:, 3:] < 0, -1.0, 1.0)  # shortest rotation
    vec_norm = np.linalg.norm(rel[:, :3], axis=1)
    angle = 2.0 * np.arctan2(vec_norm, rel[:, 3])
    factor = np.where(vec_norm > 1e-12, angle / np.where(vec_norm > 1e-12, vec_norm, 1.0), 2.0)
    return rel[:, :3] * factor[:, None]


def _solve_least_squares(X, Y, *, rcond=None, max_condition=1e6):
    """Least squares with unit-norm columns: normal equations when well conditioned.

    The regressor columns are sines and cosines of unit amplitude, nearly
    orthogonal over whole cycles (condition ~1-2), where the normal equations
    lose nothing and are much faster than an SVD; otherwise ``lstsq``.
    The long sums (over the samples) are the same bits on any number of BLAS
    threads (:mod:`hrcore.blas`): a batch worker writes the single command's bytes.
    Returns the coefficients and the condition number of the scaled matrix.
    """
    scale = np.linalg.norm(X, axis=0)
    scale[scale == 0] = 1.0
    Xs = X / scale
    G = gram(Xs, Xs)
    evals = np.linalg.eigvalsh(G)
    condition = float(np.sqrt(evals[-1] / evals[0])) if evals[0] > 0 else float("inf")
    if condition < max_condition:
        coef = np.linalg.solve(G, gram(Xs, Y))
    else:
        with one_blas_thread():  # LAPACK's sums over the samples, too
            coef = np.linalg.lstsq(Xs, Y, rcond=rcond)[0]
            sv = np.linalg.svd(Xs, compute_uv=False)
        condition = float(sv[0] / sv[-1]) if sv[-1] > 0 else float("inf")
    return coef / scale[:, None], condition


def predict_positions(models: Sequence[MotionModel], phase_c, phase_r) -> np.ndarray:
    """Positions of many points at many phase pairs, vectorised.

    Parameters
    ----------
    models : sequence of MotionModel, length n
        All with the same harmonics.
    phase_c, phase_r : (m,) float, cycles (broadcast)

    Returns
    -------
    (m, n, 3) float64, mm, probe frame
    """
    return predict_from_design(models, design_matrix(phase_c, phase_r, common_harmonics(models)))


def common_harmonics(models: Sequence[MotionModel]) -> Harmonics:
    """The harmonics every model shares (a prediction needs one design matrix)."""
    if len(models) == 0:
        raise ValueError("models must not be empty")
    h = models[0].harmonics
    if any(m.harmonics != h for m in models):
        raise ValueError("all models must have the same harmonics")
    return h


def predict_from_design(models: Sequence[MotionModel], X) -> np.ndarray:
    """(m, n, 3) positions, probe frame, from the regressors ``X``: (m, k), the same
    phase pairs for every point, or (n, m, k), each point at its own phases."""
    W = np.stack([m.coef_translation for m in models])  # (n, k, 3)
    R = np.stack([m.mean_rotation for m in models])  # (n, 3, 3)
    t = np.stack([m.mean_position_mm for m in models])  # (n, 3)
    local = np.einsum("mk,nkj->mnj" if np.ndim(X) == 2 else "nmk,nkj->mnj", X, W)
    return t[None] + np.einsum("nij,mnj->mni", R, local)
