"""The result of a spatiotemporal registration: frozen values and their JSON form.

:class:`RegistrationResult` holds everything :func:`registration.pipeline.register_session`
found and everything :mod:`registration.report` writes; :class:`PointFit` and
:class:`IcpReport` are its per-point fits and the final ICP's degeneracy report.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Mapping

import numpy as np

from registration.plausibility import Trust
from registration.spatiotemporal import PhaseSweep, StaticComparison
from registration.temporal import TemporalEstimate
from registration.transforms import euler_xyz_deg_from_matrix

__all__ = ["PointFit", "IcpReport", "RegistrationResult"]


def _version() -> str:
    try:
        from importlib.metadata import version

        return version("heartreg")
    except Exception:  # noqa: BLE001 - not installed: still register
        return "0+unknown"


@dataclass(frozen=True, eq=False)
class PointFit:
    """The motion-model fit of one attachment point.

    Attributes
    ----------
    point_id, surface_point : int
        As in ``session.json``.
    n_samples : int
        Samples in the record.
    n_used : int
        Samples with both phases defined, used in the fit.
    n_nan_phase : int
        Samples dropped because a phase is undefined (before the first or after
        the last R-peak or start of expiration).
    n_beats, n_breaths : int
        Complete heartbeats and breaths in the record.
    heart_rate_hz, resp_rate_hz : float
        Mean rates from the detected events.
    residual_rms_mm : (3,) float64, mm
        RMS position residual of the fit per probe axis.
    residual_rms_3d_mm : float, mm
        RMS of the 3-D position residual.
    residual_rms_deg : float, degrees
        RMS residual rotation angle.
    condition_number : float
        Of the column-scaled design matrix.
    notes : tuple of str
        Coverage warnings and the like.
    n_outlier_samples : int
        Samples far from their running median (tracker glitches), left out of
        the fit (:func:`registration.plausibility.outlier_samples`).
    """

    point_id: int
    surface_point: int
    n_samples: int
    n_used: int
    n_nan_phase: int
    n_beats: int
    n_breaths: int
    heart_rate_hz: float
    resp_rate_hz: float
    residual_rms_mm: np.ndarray
    residual_rms_3d_mm: float
    residual_rms_deg: float
    condition_number: float
    notes: tuple[str, ...] = ()
    n_outlier_samples: int = 0

    def to_dict(self) -> dict:
        return {
            "point_id": self.point_id,
            "surface_point": self.surface_point,
            "n_samples": self.n_samples,
            "n_used": self.n_used,
            "n_nan_phase": self.n_nan_phase,
            "n_beats": self.n_beats,
            "n_breaths": self.n_breaths,
            "heart_rate_hz": self.heart_rate_hz,
            "resp_rate_hz": self.resp_rate_hz,
            "residual_rms_mm": [float(x) for x in self.residual_rms_mm],
            "residual_rms_3d_mm": self.residual_rms_3d_mm,
            "residual_rms_deg": self.residual_rms_deg,
            "condition_number": _finite_or_none(self.condition_number),
            "n_outlier_samples": self.n_outlier_samples,
            "notes": list(self.notes),
        }


@dataclass(frozen=True, eq=False)
class IcpReport:
    """How well the final ICP pins the transform down (see :class:`registration.icp.IcpResult`).

    Attributes
    ----------
    hessian_eigenvalues : (6,) float64, mm^2 per point
        Ascending eigenvalues of the point-to-plane normal matrix at the solution.
    weakest_direction : (6,) float64
        Unit eigenvector of the smallest eigenvalue (scaled rotation, translation),
        heart frame.
    condition_number : float
    degenerate : bool
        The points can slide along the surface in ``weakest_direction``.
    iterations : int
    converged : bool
    rms_inlier_mm : float, mm
    """

    hessian_eigenvalues: np.ndarray
    weakest_direction: np.ndarray
    condition_number: float
    degenerate: bool
    iterations: int
    converged: bool
    rms_inlier_mm: float

    def to_dict(self) -> dict:
        return {
            "hessian_eigenvalues": [float(x) for x in self.hessian_eigenvalues],
            "weakest_direction": [float(x) for x in self.weakest_direction],
            "condition_number": _finite_or_none(self.condition_number),
            "degenerate": self.degenerate,
            "iterations": self.iterations,
            "converged": self.converged,
            "rms_inlier_mm": self.rms_inlier_mm,
        }


@dataclass(frozen=True, eq=False)
class RegistrationResult:
    """A complete spatiotemporal registration of a session to a heart model.

    All transforms map the reference-probe frame (the session's frame) to the
    heart frame of the model, mm.

    Attributes
    ----------
    cardiac_phase : float
        The map's cardiac phase phi_C* (from the model).
    cardiac_phase_source : str
        Where phi_C* came from.
    respiration_phase : float
        The estimated respiration phase phi_R* (``phase_estimates[0]``).
    T_heart_from_probe : (4, 4) float64
        Final spatiotemporal registration (ICP at (phi_C*, phi_R*)).
    T0_heart_from_probe : (4, 4) float64
        Fiducial registration, the seed.
    fre_mm : float
        RMS fiducial registration error.
    fiducial_residuals_mm : (9,) float64
        Per touched fiducial, in session order.
    fiducials_reordered, fiducials_ambiguous : bool
        See :class:`registration.fiducial.FiducialRegistration`.
    rms_mm : float
        RMS point-to-surface distance at phi_R*.
    translation_distance_mm, rotation_distance_deg : float
        Distance of the final registration from T0 at the pivot (eq. 10).
    euler_xyz_deg : (3,) float64
        Intrinsic X-Y-Z Euler angles of ``T_heart_from_probe``.
    respiration_sweep : PhaseSweep
        phi_R swept at phi_C* (paper Figs. 2B, 6, 7).
    cardiac_sweep : PhaseSweep or None
        phi_C swept at phi_R* (paper Fig. 2A), when asked.
    static : StaticComparison
        Mean-position registration and delta_i (paper 2.3.2, Fig. 9).
    point_ids : (n,) int64
        Ids of the registered points, in the row order of the arrays below.
    points_probe_mm : (n, 3) float64
        Predicted positions at (phi_C*, phi_R*), probe frame.
    normals_probe : (n, 3) float64
        Predicted surface normals (robot z) at (phi_C*, phi_R*), probe frame.
    mean_points_probe_mm : (n, 3) float64
        Mean positions (static registration input), probe frame.
    point_fits : tuple of PointFit
        One per registered point, same order.
    exclusions : tuple of (int, str)
        ``(point id, reason)`` of every record not registered, including those
        the session reader left out.
    icp : IcpReport
        Degeneracy report of the final ICP.
    trust : Trust
        How far to trust the result: ``ok``, ``caution`` or ``poor`` and why
        (:func:`registration.plausibility.assess_trust`).
    phase_estimates : tuple of TemporalEstimate
        phi_R* with its 90 % interval by each estimator, the one used first
        (:mod:`registration.temporal`).
    parameters : dict
        Everything that shaped the result (JSON values; treat as read-only).
    timings_s : dict
        Seconds per stage; printed by the CLI, kept out of ``to_dict`` (and so out
        of ``registration.json``) so that the same inputs give the same bytes.
    notes : tuple of str
        Warnings worth a user's attention.
    n_faces : int
        Faces of the model surface.
    version : str
        heartreg version.
    """

    cardiac_phase: float
    cardiac_phase_source: str
    respiration_phase: float
    T_heart_from_probe: np.ndarray
    T0_heart_from_probe: np.ndarray
    fre_mm: float
    fiducial_residuals_mm: np.ndarray
    fiducials_reordered: bool
    fiducials_ambiguous: bool
    rms_mm: float
    translation_distance_mm: float
    rotation_distance_deg: float
    euler_xyz_deg: np.ndarray
    respiration_sweep: PhaseSweep
    cardiac_sweep: PhaseSweep | None
    static: StaticComparison
    point_ids: np.ndarray
    points_probe_mm: np.ndarray
    normals_probe: np.ndarray
    mean_points_probe_mm: np.ndarray
    point_fits: tuple[PointFit, ...]
    exclusions: tuple[tuple[int, str], ...]
    icp: IcpReport
    trust: Trust
    phase_estimates: tuple[TemporalEstimate, ...] = ()
    parameters: Mapping = field(default_factory=dict)
    timings_s: Mapping = field(default_factory=dict)
    notes: tuple[str, ...] = ()
    n_faces: int = 0
    version: str = field(default_factory=_version)

    @property
    def n_points(self) -> int:
        return int(self.point_ids.shape[0])

    @property
    def delta_static_mean_mm(self) -> float:
        """Mean distance between the spatiotemporal and static surface points (mm)."""
        return float(self.static.mean_delta_mm)

    def to_dict(self) -> dict:
        """JSON-ready summary (sweeps are in their own CSV files).

        Transforms are nested lists, row-major; angles in degrees; lengths in mm.
        """
        st = self.static
        T_static_heart_from_probe = st.T_static_heart_from_probe
        return {
            "version": self.version,
            "frames": "T_heart_from_probe maps reference-probe mm to the model's heart frame mm",
            "trust": self.trust.to_dict(),
            "cardiac_phase": self.cardiac_phase,
            "cardiac_phase_source": self.cardiac_phase_source,
            "respiration_phase": self.respiration_phase,
            "respiration_phase_estimate": self.phase_estimates[0].to_dict() if self.phase_estimates else None,
            "respiration_phase_alternatives": [e.to_dict() for e in self.phase_estimates[1:]],
            "T_heart_from_probe": self.T_heart_from_probe.tolist(),
            "T0_heart_from_probe": self.T0_heart_from_probe.tolist(),
            "euler_xyz_deg": [float(x) for x in self.euler_xyz_deg],
            "translation_mm": [float(x) for x in self.T_heart_from_probe[:3, 3]],
            "T0_euler_xyz_deg": [float(x) for x in euler_xyz_deg_from_matrix(self.T0_heart_from_probe)],
            "rms_mm": self.rms_mm,
            "translation_distance_mm": self.translation_distance_mm,
            "rotation_distance_deg": self.rotation_distance_deg,
            "pivot_heart_mm": [float(x) for x in self.respiration_sweep.pivot_mm],
            "fre_mm": self.fre_mm,
            "fiducial_residuals_mm": [float(x) for x in self.fiducial_residuals_mm],
            "fiducials_reordered": self.fiducials_reordered,
            "fiducials_ambiguous": self.fiducials_ambiguous,
            "static": {
                "T_heart_from_probe": T_static_heart_from_probe.tolist(),
                "euler_xyz_deg": [float(x) for x in euler_xyz_deg_from_matrix(T_static_heart_from_probe)],
                "rms_mm": float(st.rms_static_mm),
            },
            "delta_static_mean_mm": self.delta_static_mean_mm,
            "delta_static_mm": {str(int(i)): float(d) for i, d in zip(self.point_ids, st.delta_mm)},
            "icp": self.icp.to_dict(),
            "n_points": self.n_points,
            "point_ids": [int(i) for i in self.point_ids],
            "point_fits": [p.to_dict() for p in self.point_fits],
            "exclusions": [{"point_id": int(i), "reason": r} for i, r in self.exclusions],
            "n_faces": self.n_faces,
            "sweep": {
                "respiration_phases": len(self.respiration_sweep.phases),
                "respiration_converged": int(np.count_nonzero(self.respiration_sweep.converged)),
                "cardiac_phases": 0 if self.cardiac_sweep is None else len(self.cardiac_sweep.phases),
            },
            "parameters": dict(self.parameters),
            "notes": list(self.notes),
        }


def _finite_or_none(x):
    x = float(x)
    return x if math.isfinite(x) else None
