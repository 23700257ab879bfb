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

from hrcore.jsonarrays import bool_array, float_array, int_array, json_floats
from registration.plausibility import Trust
from registration.spatiotemporal import PhaseSweep, StaticComparison
from registration.phase_estimate import TemporalEstimate
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

    @classmethod
    def from_dict(cls, data: dict) -> "PointFit":
        """The inverse of :meth:`to_dict` (a ``null`` condition number reads as infinity)."""
        ints = ("point_id", "surface_point", "n_samples", "n_used", "n_nan_phase", "n_beats", "n_breaths",
                "n_outlier_samples")
        floats = ("heart_rate_hz", "resp_rate_hz", "residual_rms_3d_mm", "residual_rms_deg")
        return cls(
            **{k: int(data[k]) for k in ints},
            **{k: float(data[k]) for k in floats},
            residual_rms_mm=float_array(data["residual_rms_mm"], (3,)),
            condition_number=_float_or_inf(data["condition_number"]),
            notes=tuple(str(n) for n in data["notes"]),
        )


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

    @classmethod
    def from_dict(cls, data: dict) -> "IcpReport":
        """The inverse of :meth:`to_dict`."""
        return cls(
            hessian_eigenvalues=float_array(data["hessian_eigenvalues"], (6,)),
            weakest_direction=float_array(data["weakest_direction"], (6,)),
            condition_number=_float_or_inf(data["condition_number"]),
            degenerate=bool(data["degenerate"]),
            iterations=int(data["iterations"]),
            converged=bool(data["converged"]),
            rms_inlier_mm=float(data["rms_inlier_mm"]),
        )


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
        """JSON-ready form, the body of ``registration.json`` (format version 2).

        Every attribute but ``timings_s`` is stored under its own name (sweeps,
        static comparison, point fits and phase estimates as nested objects
        whose keys are their attribute names), exactly: floats as their
        shortest exact decimal, non-finite array entries as ``null``.  Derived
        values for a reader of the file are added beside them
        (``euler_xyz_deg`` of T0 and of the static registration,
        ``translation_mm``, ``pivot_heart_mm``, ``n_points``,
        ``delta_static_mm`` per point id, ``delta_static_mean_mm``).
        Transforms are nested lists, row-major; angles in degrees; lengths in mm.
        """
        st = self.static
        return {
            "version": self.version,
            "frames": "T_heart_from_probe maps reference-probe mm to the model's heart frame mm",
            "trust": self.trust.to_dict(),
            "cardiac_phase": self.cardiac_phase,
            "cardiac_phase_source": self.cardiac_phase_source,
            "respiration_phase": self.respiration_phase,
            "T_heart_from_probe": json_floats(self.T_heart_from_probe),
            "T0_heart_from_probe": json_floats(self.T0_heart_from_probe),
            "euler_xyz_deg": json_floats(self.euler_xyz_deg),
            "translation_mm": json_floats(self.T_heart_from_probe[:3, 3]),
            "T0_euler_xyz_deg": json_floats(euler_xyz_deg_from_matrix(self.T0_heart_from_probe)),
            "rms_mm": self.rms_mm,
            "translation_distance_mm": self.translation_distance_mm,
            "rotation_distance_deg": self.rotation_distance_deg,
            "pivot_heart_mm": json_floats(self.respiration_sweep.pivot_mm),
            "fre_mm": self.fre_mm,
            "fiducial_residuals_mm": json_floats(self.fiducial_residuals_mm),
            "fiducials_reordered": self.fiducials_reordered,
            "fiducials_ambiguous": self.fiducials_ambiguous,
            "static": static_to_dict(st),
            "delta_static_mean_mm": self.delta_static_mean_mm,
            "delta_static_mm": {str(int(i)): float(d) for i, d in zip(self.point_ids, st.delta_mm)},
            "icp": self.icp.to_dict(),
            "n_points": self.n_points,
            "point_ids": [int(i) for i in self.point_ids],
            "point_fits": [p.to_dict() for p in self.point_fits],
            "exclusions": [{"point_id": int(i), "reason": r} for i, r in self.exclusions],
            "n_faces": self.n_faces,
            "parameters": dict(self.parameters),
            "notes": list(self.notes),
            "points_probe_mm": json_floats(self.points_probe_mm),
            "normals_probe": json_floats(self.normals_probe),
            "mean_points_probe_mm": json_floats(self.mean_points_probe_mm),
            "phase_estimates": [e.to_dict() for e in self.phase_estimates],
            "respiration_sweep": sweep_to_dict(self.respiration_sweep),
            "cardiac_sweep": None if self.cardiac_sweep is None else sweep_to_dict(self.cardiac_sweep),
        }

    @classmethod
    def from_dict(cls, data: dict) -> "RegistrationResult":
        """The inverse of :meth:`to_dict` (``timings_s`` is empty: it is not stored).

        Raises
        ------
        KeyError, TypeError, ValueError
            A missing field or a value of the wrong kind or shape
            (:func:`registration.report.read_registration` turns them into one
            line naming the file).
        """
        ids = int_array(data["point_ids"], (-1,))
        n = ids.shape[0]
        card = data["cardiac_sweep"]
        return cls(
            cardiac_phase=float(data["cardiac_phase"]),
            cardiac_phase_source=str(data["cardiac_phase_source"]),
            respiration_phase=float(data["respiration_phase"]),
            T_heart_from_probe=float_array(data["T_heart_from_probe"], (4, 4)),
            T0_heart_from_probe=float_array(data["T0_heart_from_probe"], (4, 4)),
            fre_mm=float(data["fre_mm"]),
            fiducial_residuals_mm=float_array(data["fiducial_residuals_mm"], (-1,)),
            fiducials_reordered=bool(data["fiducials_reordered"]),
            fiducials_ambiguous=bool(data["fiducials_ambiguous"]),
            rms_mm=float(data["rms_mm"]),
            translation_distance_mm=float(data["translation_distance_mm"]),
            rotation_distance_deg=float(data["rotation_distance_deg"]),
            euler_xyz_deg=float_array(data["euler_xyz_deg"], (3,)),
            respiration_sweep=sweep_from_dict(data["respiration_sweep"]),
            cardiac_sweep=None if card is None else sweep_from_dict(card),
            static=static_from_dict(data["static"], n),
            point_ids=ids,
            points_probe_mm=float_array(data["points_probe_mm"], (n, 3)),
            normals_probe=float_array(data["normals_probe"], (n, 3)),
            mean_points_probe_mm=float_array(data["mean_points_probe_mm"], (n, 3)),
            point_fits=tuple(PointFit.from_dict(p) for p in data["point_fits"]),
            exclusions=tuple((int(e["point_id"]), str(e["reason"])) for e in data["exclusions"]),
            icp=IcpReport.from_dict(data["icp"]),
            trust=Trust.from_dict(data["trust"]),
            phase_estimates=tuple(TemporalEstimate.from_dict(e) for e in data["phase_estimates"]),
            parameters=dict(data["parameters"]),
            notes=tuple(str(x) for x in data["notes"]),
            n_faces=int(data["n_faces"]),
            version=str(data["version"]),
        )


# ------------------------------------------------------------------ nested values
_SWEEP_FLOATS = ("phases", "rms_mm", "T_heart_from_probe", "translation_distance_mm", "rotation_distance_deg",
                 "correction_translation_mm", "correction_euler_xyz_deg", "euler_xyz_deg", "pivot_mm")


def sweep_to_dict(sweep: PhaseSweep) -> dict:
    """A :class:`PhaseSweep` as JSON values, keys equal to its attribute names."""
    out = {"kind": sweep.kind, "fixed_phase": float(sweep.fixed_phase)}
    out.update({k: json_floats(getattr(sweep, k)) for k in _SWEEP_FLOATS})
    out["iterations"] = [int(i) for i in sweep.iterations]
    out["converged"] = [bool(c) for c in sweep.converged]
    for k in ("distances_mm", "signed_distances_mm"):
        value = getattr(sweep, k)
        out[k] = None if value is None else json_floats(value)
    return out


def sweep_from_dict(data: dict) -> PhaseSweep:
    """The inverse of :func:`sweep_to_dict`."""
    m = len(data["phases"])
    shapes = {"phases": (m,), "rms_mm": (m,), "T_heart_from_probe": (m, 4, 4), "translation_distance_mm": (m,),
              "rotation_distance_deg": (m,), "correction_translation_mm": (m, 3),
              "correction_euler_xyz_deg": (m, 3), "euler_xyz_deg": (m, 3), "pivot_mm": (3,)}
    kind = str(data["kind"])
    if kind not in ("respiration", "cardiac"):
        raise ValueError(f"sweep kind must be 'respiration' or 'cardiac', got {kind!r}")
    return PhaseSweep(
        kind=kind,
        fixed_phase=float(data["fixed_phase"]),
        **{k: float_array(data[k], shapes[k]) for k in _SWEEP_FLOATS},
        iterations=int_array(data["iterations"], (m,)),
        converged=bool_array(data["converged"], (m,)),
        **{k: None if data[k] is None else float_array(data[k], (m, -1))
           for k in ("distances_mm", "signed_distances_mm")},
    )


def static_to_dict(st: StaticComparison) -> dict:
    """A :class:`StaticComparison` as JSON values (plus its transform's Euler angles)."""
    return {
        "T_static_heart_from_probe": json_floats(st.T_static_heart_from_probe),
        "euler_xyz_deg": json_floats(euler_xyz_deg_from_matrix(st.T_static_heart_from_probe)),
        "rms_static_mm": float(st.rms_static_mm),
        "mean_delta_mm": float(st.mean_delta_mm),
        "delta_mm": json_floats(st.delta_mm),
        "projected_static_mm": json_floats(st.projected_static_mm),
        "projected_spatiotemporal_mm": json_floats(st.projected_spatiotemporal_mm),
    }


def static_from_dict(data: dict, n: int) -> StaticComparison:
    """The inverse of :func:`static_to_dict` for ``n`` points."""
    return StaticComparison(
        T_static_heart_from_probe=float_array(data["T_static_heart_from_probe"], (4, 4)),
        rms_static_mm=float(data["rms_static_mm"]),
        projected_static_mm=float_array(data["projected_static_mm"], (n, 3)),
        projected_spatiotemporal_mm=float_array(data["projected_spatiotemporal_mm"], (n, 3)),
        delta_mm=float_array(data["delta_mm"], (n,)),
        mean_delta_mm=float(data["mean_delta_mm"]),
    )


def _float_or_inf(x) -> float:
    return math.inf if x is None else float(x)


def _finite_or_none(x):
    x = float(x)
    return x if math.isfinite(x) else None
