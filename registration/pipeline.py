"""The registration pipeline: a heart model and a session in, one registration out.

Wood et al. 2018, sections 2.2.4, 2.2.5 and 2.3.  For every attachment point of
the session:

1. R-peaks are detected in the point's ECG (:func:`imaging.ecg.detect_r_peaks`)
   and the cardiac phase of each sample follows from them; the starts of
   expiration are found in the ventilator flows
   (:func:`imaging.respiration.expiration_onsets`) and give the respiration
   phase.  Samples outside the covered events have no phase (NaN): they are
   dropped and counted, never extrapolated.
2. A point with fewer than ``min_beats`` complete heartbeats or ``min_breaths``
   complete breaths, or whose signals give no events at all, is *excluded* and
   the reason is recorded (never silently).
3. The AM dual Fourier model (paper eq. 6-8) is fitted by linear least squares;
   phases that leave part of the cycle empty are recorded as a note.

Then the fiducial registration ``T0`` (heart frame <- probe frame) of the
touched staples onto the model's fiducials, the sweep over the respiration
phase at the map's cardiac phase phi_C* with the empirical phi_R* of eq. 10,
the sweep over the cardiac phase at phi_R* (paper Fig. 2A), the final
``T_heart_from_probe`` with the ICP's degeneracy report, and the comparison
with the static (mean-position) registration (paper 2.3.2).
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np

from imaging.ecg import cardiac_phase, detect_r_peaks
from imaging.events import SignalError
from imaging.respiration import expiration_onsets, respiration_phase
from modeling.model import HeartModel
from registration.fiducial import FiducialError, register_fiducials
from registration.icp import SurfaceIndex, icp
from registration.motion_model import (
    CoverageWarning,
    Harmonics,
    MotionModel,
    MotionModelError,
    fit_motion_model,
)
from registration.session import PointRecord, Session
from registration.spatiotemporal import (
    PhaseSweep,
    StaticComparison,
    compare_static,
    register_spatiotemporal,
    surface_centroid,
    sweep_phase,
)
from registration.transforms import euler_xyz_deg_from_matrix

__all__ = [
    "RegistrationError",
    "PointFit",
    "IcpReport",
    "RegistrationResult",
    "sweep_phases",
    "point_phases",
    "register_session",
    "MIN_BEATS",
    "MIN_BREATHS",
]

#: Fewest complete heartbeats (R-peak to R-peak) a record must hold.
MIN_BEATS = 4
#: Fewest complete breaths (start of expiration to the next) a record must hold.
MIN_BREATHS = 2
#: The paper's sweep step (0, 0.01, ..., 1).
DEFAULT_STEP = 0.01


class RegistrationError(ValueError):
    """The model and the session cannot be registered (no usable point, no fiducials)."""


def _version() -> str:
    try:
        from importlib.metadata import version

        return version("heartreg")
    except Exception:  # noqa: BLE001 - not installed: still register
        return "0+unknown"


def _frozen(a) -> np.ndarray:
    a = np.array(a, copy=True)
    a.setflags(write=False)
    return a


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
    phase_c : float
        The map's cardiac phase phi_C* (from the model).
    phase_c_source : str
        Where phi_C* came from.
    phase_r : float
        The estimated respiration phase phi_R* (paper eq. 10).
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
    parameters : dict
        Everything that shaped the result (JSON values; treat as read-only).
    timings_s : dict
        Seconds per stage (treat as read-only).
    notes : tuple of str
        Warnings worth a user's attention.
    n_faces : int
        Faces of the model surface.
    version : str
        heartreg version.
    """

    phase_c: float
    phase_c_source: str
    phase_r: float
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
        T_static = st.T_static
        return {
            "version": self.version,
            "frames": "T_heart_from_probe maps reference-probe mm to the model's heart frame mm",
            "cardiac_phase": self.phase_c,
            "cardiac_phase_source": self.phase_c_source,
            "respiration_phase": self.phase_r,
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
                "T_heart_from_probe": T_static.tolist(),
                "euler_xyz_deg": [float(x) for x in euler_xyz_deg_from_matrix(T_static)],
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
            "timings_s": dict(self.timings_s),
            "notes": list(self.notes),
        }


def _finite_or_none(x):
    x = float(x)
    return x if math.isfinite(x) else None


def sweep_phases(step: float) -> np.ndarray:
    """Phases 0, step, ..., 1 (both ends included, as the paper's sweep).

    Parameters
    ----------
    step : float, cycles
        Must divide 1 into a whole number of steps (0.01 gives 101 phases).

    Returns
    -------
    (round(1 / step) + 1,) float64
    """
    step = float(step)
    if not (0.0 < step <= 0.5):
        raise ValueError(f"step must be in (0, 0.5] cycles, got {step}")
    n = 1.0 / step
    if abs(n - round(n)) > 1e-6:
        raise ValueError(f"step must divide one cycle evenly (e.g. 0.01, 0.02, 0.05), got {step}")
    return np.linspace(0.0, 1.0, int(round(n)) + 1)


def _as_harmonics(harmonics) -> Harmonics:
    if isinstance(harmonics, Harmonics):
        return harmonics
    values = tuple(harmonics)
    if len(values) != 4:
        raise ValueError(f"harmonics must be a Harmonics or (Hc, Hr, Hmc, Hmr), got {harmonics!r}")
    hc, hr, hmc, hmr = values
    return Harmonics(cardiac=hc, respiratory=hr, coupled_cardiac=hmc, coupled_respiratory=hmr)


def point_phases(record: PointRecord):
    """Cardiac and respiration phase of every sample of one record.

    Parameters
    ----------
    record : PointRecord

    Returns
    -------
    phase_c, phase_r : (n,) float64, cycles
        NaN where the phase is undefined.
    r_peaks_s, onsets_s : (m,) float64, s
        Detected R-peaks and starts of expiration.

    Raises
    ------
    imaging.events.SignalError
        The ECG or the flows give fewer than two events.
    """
    t = record.time_s
    peaks = detect_r_peaks(record.ecg_mv, record.rate_hz, start_s=float(t[0]))
    onsets = expiration_onsets(
        rate_hz=record.rate_hz,
        flow_exp_lpm=record.flow_exp_lpm,
        flow_insp_lpm=record.flow_insp_lpm,
        start_s=float(t[0]),
    )
    return cardiac_phase(t, peaks.times_s), respiration_phase(t, onsets), peaks.times_s, onsets


def _fit_point(record, harmonics, min_beats, min_breaths, coverage_bins):
    """(MotionModel, PointFit) or raise _Excluded(reason)."""
    try:
        phase_c, phase_r, peaks, onsets = point_phases(record)
    except SignalError as exc:
        raise _Excluded(f"{record.file}: {exc}") from None
    n_beats, n_breaths = peaks.size - 1, onsets.size - 1
    if n_beats < min_beats:
        raise _Excluded(
            f"{record.file}: {n_beats} complete heartbeat(s) detected, fewer than "
            f"min_beats = {min_beats}; record longer or check the ECG lead"
        )
    if n_breaths < min_breaths:
        raise _Excluded(
            f"{record.file}: {n_breaths} complete breath(s) detected, fewer than "
            f"min_breaths = {min_breaths}; record at least {min_breaths + 1} starts of expiration"
        )
    notes = []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", CoverageWarning)
        try:
            model = fit_motion_model(
                phase_c, phase_r, record.T_probe_from_robot,
                harmonics=harmonics, coverage_bins=coverage_bins,
            )
        except MotionModelError as exc:
            raise _Excluded(f"{record.file}: {exc}") from None
    for w in caught:
        if issubclass(w.category, CoverageWarning):
            notes.append(f"point {record.point_id}: {w.message}")
    fit = PointFit(
        point_id=record.point_id,
        surface_point=record.surface_point,
        n_samples=record.n_samples,
        n_used=model.n_samples,
        n_nan_phase=model.n_dropped,
        n_beats=int(n_beats),
        n_breaths=int(n_breaths),
        heart_rate_hz=float(n_beats / (peaks[-1] - peaks[0])),
        resp_rate_hz=float(n_breaths / (onsets[-1] - onsets[0])),
        residual_rms_mm=_frozen(model.residual_rms_mm),
        residual_rms_3d_mm=float(model.residual_rms_3d_mm),
        residual_rms_deg=float(model.residual_rms_deg),
        condition_number=float(model.condition_number),
        notes=tuple(notes),
    )
    return model, fit


class _Excluded(Exception):
    """Internal: a point left out, with the reason as message."""


def _progress(enabled: bool, total: int, desc: str):
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="point", leave=False)


def register_session(
    model: HeartModel,
    session: Session,
    *,
    harmonics: Harmonics | Sequence[int] = Harmonics(),
    phase_step: float = DEFAULT_STEP,
    cardiac_sweep: bool = True,
    cardiac_phase_step: float | None = None,
    icp_options: Mapping | None = None,
    min_beats: int = MIN_BEATS,
    min_breaths: int = MIN_BREATHS,
    coverage_bins: int = 10,
    max_fre_mm: float = 3.0,
    progress: bool = False,
) -> RegistrationResult:
    """Register a session to a heart model in space and in respiration phase.

    Parameters
    ----------
    model : HeartModel
        The map: mesh in the heart frame, phi_C*, fiducials (heart frame, in
        the documented order).
    session : Session
        From :func:`registration.session.read_session`.
    harmonics : Harmonics or (Hc, Hr, Hmc, Hmr)
        Fourier harmonics of the motion models (paper: 5, 4, 2, 1).
    phase_step : float, cycles
        Step of both sweeps (0.01: 101 phases, as the paper).
    cardiac_sweep : bool
        Also sweep phi_C at phi_R* (paper Fig. 2A).
    cardiac_phase_step : float, cycles, optional
        Step of the cardiac sweep when other than ``phase_step`` (its systolic
        phases, far from the map's shape, take the most ICP iterations).
    icp_options : mapping, optional
        Keyword arguments of :func:`registration.icp.icp` (method, trim_fraction,
        huber_mm, tolerances ...).
    min_beats, min_breaths : int
        Fewest complete heartbeats and breaths a record must hold to be used.
    coverage_bins : int
        Phase bins checked for coverage (a note per point with empty bins).
    max_fre_mm : float, mm
        Above this FRE in the documented order the fiducial correspondence is
        searched (see :func:`registration.fiducial.register_fiducials`).
    progress : bool
        A progress bar on stderr over the points.

    Returns
    -------
    RegistrationResult

    Raises
    ------
    RegistrationError
        The model has no fiducials or another number than the session, fewer
        than 3 points can be used, or the fiducials cannot be registered.
    """
    if not isinstance(model, HeartModel):
        raise TypeError(f"model must be a HeartModel, got {type(model).__name__}")
    if not isinstance(session, Session):
        raise TypeError(f"session must be a Session, got {type(session).__name__}")
    harmonics = _as_harmonics(harmonics)
    phases = sweep_phases(phase_step)
    phases_c = phases if cardiac_phase_step is None else sweep_phases(cardiac_phase_step)
    for name, value in (("min_beats", min_beats), ("min_breaths", min_breaths)):
        if int(value) != value or value < 1:
            raise ValueError(f"{name} must be a positive integer, got {value!r}")
    options = dict(icp_options or {})
    options.pop("T_init", None)
    timings: dict[str, float] = {}
    notes: list[str] = []
    t_start = time.perf_counter()

    # ---- fiducials first: a mismatch is a hard error, so fail before the slow work
    fid_model = model.fiducials_heart_mm
    fid_probe = session.fiducials_probe_mm
    if fid_model.shape[0] == 0:
        raise RegistrationError(
            "the model has no fiducials, so there is no initial registration T0; "
            "re-make the model from a CT that shows the chest staples"
        )
    if fid_model.shape[0] != fid_probe.shape[0]:
        raise RegistrationError(
            f"the model has {fid_model.shape[0]} fiducials but the session touched "
            f"{fid_probe.shape[0]}: every staple of the model must be touched once, in "
            "the documented order (rows superior to inferior, within a row right to left)"
        )
    t = time.perf_counter()
    try:
        fid = register_fiducials(fid_probe, fid_model, max_fre_mm=max_fre_mm)
    except FiducialError as exc:
        raise RegistrationError(f"fiducial registration failed: {exc}") from exc
    T0 = fid.T_target_from_source
    timings["fiducials"] = time.perf_counter() - t
    if fid.reordered:
        notes.append(
            f"the touched fiducials did not fit in the documented order; the assignment "
            f"{[int(i) for i in fid.order]} was found by search (FRE {fid.fre_rms_mm:.2f} mm)"
        )
    if fid.ambiguous:
        notes.append("the fiducial assignment is ambiguous (symmetric layout): check T0 visually")
    if fid.fre_rms_mm > max_fre_mm:
        notes.append(f"fiducial registration error {fid.fre_rms_mm:.2f} mm exceeds {max_fre_mm:g} mm")

    # ---- phases and motion models per point
    t = time.perf_counter()
    exclusions = list(session.exclusions)
    models: list[MotionModel] = []
    fits: list[PointFit] = []
    bar = _progress(progress, len(session.points), "motion models")
    try:
        for record in session.points:
            try:
                m, f = _fit_point(record, harmonics, min_beats, min_breaths, coverage_bins)
            except _Excluded as exc:
                exclusions.append((record.point_id, str(exc)))
            else:
                models.append(m)
                fits.append(f)
                notes.extend(f.notes)
            if bar is not None:
                bar.update()
    finally:
        if bar is not None:
            bar.close()
    timings["motion_models"] = time.perf_counter() - t
    if len(models) < 3:
        reasons = "; ".join(f"point {i}: {r}" for i, r in exclusions[:5])
        raise RegistrationError(
            f"only {len(models)} point(s) could be modelled, ICP needs at least 3 "
            f"({len(exclusions)} excluded: {reasons}); record more points"
        )
    if exclusions:
        notes.append(f"{len(exclusions)} point(s) excluded (see exclusions)")

    # ---- sweeps
    t = time.perf_counter()
    surface = SurfaceIndex(model.mesh.vertices, model.mesh.faces)
    pivot = surface_centroid(surface)
    timings["surface_index"] = time.perf_counter() - t
    t = time.perf_counter()
    reg = register_spatiotemporal(
        models, surface, T0, model.cardiac_phase,
        phases_r=phases, pivot_mm=pivot, cardiac_sweep=False, icp_options=options,
    )
    timings["respiration_sweep"] = time.perf_counter() - t
    card = None
    if cardiac_sweep:
        t = time.perf_counter()
        card = sweep_phase(
            models, surface, T0, fixed_phase=reg.phase_r, kind="cardiac",
            phases=phases_c, pivot_mm=pivot, icp_options=options,
        )
        timings["cardiac_sweep"] = time.perf_counter() - t
    resp = reg.respiration_sweep
    if not resp.converged.all():
        bad = resp.phases[~resp.converged]
        notes.append(
            f"ICP did not converge at {bad.size} respiration phase(s) (e.g. {bad[0]:.2f}); "
            "raise icp max_iterations"
        )
    if resp.best_index in (0, resp.phases.size - 1):
        notes.append("phi_R* lies at the end of the sweep (0 and 1 are the same phase)")

    # ---- final ICP again, for its degeneracy report (same seed and points: same T)
    t = time.perf_counter()
    final = icp(reg.points_source_mm, surface, T_init=T0, **options)
    report = IcpReport(
        hessian_eigenvalues=_frozen(final.hessian_eigenvalues),
        weakest_direction=_frozen(final.weakest_direction),
        condition_number=float(final.condition_number),
        degenerate=bool(final.degenerate),
        iterations=int(final.iterations),
        converged=bool(final.converged),
        rms_inlier_mm=float(final.rms_inlier_mm),
    )
    if report.degenerate:
        notes.append(
            "the final ICP is degenerate: the points can slide along the surface "
            "(see icp.weakest_direction); spread the points over more of the heart"
        )
    static = compare_static(models, surface, T0, reg.T_map_from_source, reg.points_source_mm,
                            icp_options=options)
    timings["static"] = time.perf_counter() - t

    normals = np.stack([m.predict_normal(model.cardiac_phase, reg.phase_r)[0] for m in models])
    timings["total"] = time.perf_counter() - t_start
    params = {
        "harmonics": {
            "cardiac": harmonics.cardiac,
            "respiratory": harmonics.respiratory,
            "coupled_cardiac": harmonics.coupled_cardiac,
            "coupled_respiratory": harmonics.coupled_respiratory,
        },
        "phase_step": float(phase_step),
        "cardiac_sweep": bool(cardiac_sweep),
        "cardiac_phase_step": float(phase_step if cardiac_phase_step is None else cardiac_phase_step),
        "icp_options": {k: (v.value if hasattr(v, "value") else v) for k, v in options.items()},
        "min_beats": int(min_beats),
        "min_breaths": int(min_breaths),
        "coverage_bins": int(coverage_bins),
        "max_fre_mm": float(max_fre_mm),
        "session_format_version": int(session.format_version),
        "session_sample_rate_hz": float(session.sample_rate_hz),
    }
    return RegistrationResult(
        phase_c=float(model.cardiac_phase),
        phase_c_source=model.cardiac_phase_source,
        phase_r=float(reg.phase_r),
        T_heart_from_probe=_frozen(reg.T_map_from_source),
        T0_heart_from_probe=_frozen(T0),
        fre_mm=float(fid.fre_rms_mm),
        fiducial_residuals_mm=_frozen(fid.residuals_mm),
        fiducials_reordered=bool(fid.reordered),
        fiducials_ambiguous=bool(fid.ambiguous),
        rms_mm=float(reg.rms_mm),
        translation_distance_mm=float(reg.translation_distance_mm),
        rotation_distance_deg=float(reg.rotation_distance_deg),
        euler_xyz_deg=_frozen(euler_xyz_deg_from_matrix(reg.T_map_from_source)),
        respiration_sweep=resp,
        cardiac_sweep=card,
        static=static,
        point_ids=_frozen(np.array([f.point_id for f in fits], dtype=np.int64)),
        points_probe_mm=_frozen(reg.points_source_mm),
        normals_probe=_frozen(normals),
        mean_points_probe_mm=_frozen(np.stack([m.mean_position_mm for m in models])),
        point_fits=tuple(fits),
        exclusions=tuple((int(i), str(r)) for i, r in exclusions),
        icp=report,
        parameters=params,
        timings_s={k: float(v) for k, v in timings.items()},
        notes=tuple(notes),
        n_faces=int(model.mesh.n_faces),
    )
