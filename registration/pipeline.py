"""The registration pipeline: a heart model and a session in, one registration out.

Wood et al. 2018, sections 2.2.4, 2.2.5 and 2.3.  The phases and motion
model of every attachment point of the session
(:func:`registration.point_models.fit_point_models`: points without enough
heartbeats or breaths are excluded with the reason, never silently); the
fiducial registration ``T0`` (heart frame <- probe frame) of the touched
staples onto the model's fiducials; the sweep over the respiration
phase at the map's cardiac phase phi_C* with the empirical phi_R* of eq. 10,
the sweep over the cardiac phase at phi_R* (paper Fig. 2A), the final
``T_heart_from_probe`` with the ICP's degeneracy report, and the comparison
with the static (mean-position) registration (paper 2.3.2).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from hrcore.errors import HeartregError, UsageError
from hrcore.geometry import apply_to_points, frozen
from imaging.events import SignalError
from modeling.model import HeartModel
from registration.fiducial import FiducialError, register_fiducials
from registration.options import MIN_BEATS, MIN_BREATHS, RegistrationOptions
from registration.icp import SurfaceIndex, icp
from registration.plausibility import assess_coverage, assess_trust
from registration.result import IcpReport, RegistrationResult
from registration.point_models import fit_point_models, respiration_of
from registration.session import Session
from registration.slice_phase import point_cardiac_phases, predict_at_point_phases
from registration.spatiotemporal import (
    compare_static,
    _points_at,
    surface_centroid,
    sweep_phase,
)
from registration.temporal import (
    TemporalError,
    TemporalEstimator,
    estimate_phase,
    fiducial_curve,
    paper_phase,
)
from registration.transforms import euler_xyz_deg_from_matrix

__all__ = [
    "RegistrationError",
    "sweep_phases",
    "register_session",
    "MIN_BEATS",
    "MIN_BREATHS",
    "RegistrationOptions",
]

#: The finest sweep step: 1001 phases (finer only costs time and memory).
MIN_PHASE_STEP = 0.001


class RegistrationError(HeartregError, ValueError):
    """The model and the session cannot be registered (no usable point, no fiducials)."""


def sweep_phases(step: float) -> np.ndarray:
    """Phases 0, step, ..., 1 (both ends included, as the paper's sweep).

    Parameters
    ----------
    step : float, cycles
        Must divide 1 into a whole number of steps (0.01 gives 101 phases),
        at least :data:`MIN_PHASE_STEP`.

    Returns
    -------
    (round(1 / step) + 1,) float64
    """
    step = float(step)
    if not (MIN_PHASE_STEP <= step <= 0.5):
        raise UsageError(
            f"step (--step) must be in [{MIN_PHASE_STEP:g}, 0.5] cycles (0.01: the paper's 101 phases), got {step:g}"
        )
    n = 1.0 / step
    if abs(n - round(n)) > 1e-6:
        raise UsageError(f"step (--step) must divide one cycle evenly (e.g. 0.01, 0.02, 0.05), got {step}")
    return np.linspace(0.0, 1.0, int(round(n)) + 1)


#: ICP's iteration limit when ``icp_options`` gives none (``registration.icp.icp``).
ICP_MAX_ITERATIONS = 50


@dataclass(frozen=True)
class _Chosen:
    respiration_phase: float
    T_heart_from_probe: np.ndarray
    rms_mm: float
    translation_distance_mm: float
    rotation_distance_deg: float
    points_probe_mm: np.ndarray


def _trace_curve(trace, fid_model, phases, order):
    """The traced staples over the breath (:func:`registration.temporal.fiducial_curve`)."""
    phase_r, _ = respiration_of(trace)
    return fiducial_curve(trace.fiducial, trace.stylus_probe_mm, phase_r, fid_model, phases, order=order)


def register_session(
    model: HeartModel,
    session: Session,
    *,
    options: RegistrationOptions | None = None,
    progress: bool = False,
    **overrides,
) -> RegistrationResult:
    """Register a session to a heart model in space and in respiration phase.

    Parameters
    ----------
    model : HeartModel
        The map: mesh in the heart frame, phi_C*, fiducials (heart frame, in
        the documented order).
    session : Session
        From :func:`registration.session.read_session`.
    options : RegistrationOptions, optional
        How to register (:class:`registration.options.RegistrationOptions`:
        harmonics, sweep steps, ICP options, the phi_R* estimator, ...);
        default: its defaults.
    **overrides
        Fields of :class:`RegistrationOptions` replaced for this call, e.g.
        ``harmonics=(3, 2, 1, 1)``.
    progress : bool
        A progress bar on stderr over the points.

    Returns
    -------
    RegistrationResult

    Raises
    ------
    RegistrationError
        The model's cardiac phase is unknown, the model has no fiducials or
        another number than the session, fewer
        than 3 points can be used, or the fiducials cannot be registered.

    Examples
    --------
    On a case written by ``heartreg phantom case`` and its model (``heartreg
    model``); a registration takes seconds to minutes, hence skipped here:

    >>> from modeling import read_model
    >>> from registration import RegistrationOptions, read_session, register_session
    >>> model = read_model("out/model")  # doctest: +SKIP
    >>> session = read_session("case/session")  # doctest: +SKIP
    >>> result = register_session(model, session, options=RegistrationOptions(phase_step=0.02))  # doctest: +SKIP
    >>> 0.0 <= result.respiration_phase <= 1.0, result.T_heart_from_probe.shape  # doctest: +SKIP
    (True, (4, 4))
    >>> result.trust.level in ("ok", "caution", "poor")  # doctest: +SKIP
    True
    """
    if not isinstance(model, HeartModel):
        raise TypeError(f"model must be a HeartModel, got {type(model).__name__}")
    if not isinstance(session, Session):
        raise TypeError(f"session must be a Session, got {type(session).__name__}")
    if model.cardiac_phase is None:
        raise RegistrationError(
            f"the model's cardiac phase is unknown ({model.cardiac_phase_source}); "
            "give the CT's phase (0..1) with --cardiac-phase"
        )
    opts = RegistrationOptions.of(options, **overrides)
    harmonics = opts.harmonics
    estimator = TemporalEstimator(opts.estimator)
    phase_step, cardiac_sweep, cardiac_phase_step = opts.phase_step, opts.cardiac_sweep, opts.cardiac_phase_step
    icp_options, min_beats, min_breaths = opts.icp_options, opts.min_beats, opts.min_breaths
    coverage_bins, max_fre_mm = opts.coverage_bins, opts.max_fre_mm
    breath_hold_phase, breath_hold_sd = opts.breath_hold_phase, opts.breath_hold_sd
    # the CT's cardiac phase slice by slice, when the model carries it (registration/slice_phase.py)
    slice_phases = getattr(model, "slice_phases", None) if opts.slice_phases else None
    phases = sweep_phases(phase_step)
    phases_c = phases if cardiac_phase_step is None else sweep_phases(cardiac_phase_step)
    options = dict(icp_options or {})
    options.pop("T_init", None)
    timings: dict[str, float] = {}
    notes: list[str] = list(session.notes)  # what reading the session dropped (invalid PLUS poses), kept with the result
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
        raise RegistrationError(f"fiducial registration of session {session.path} failed: {exc} (source: the "
                                "session's touched staples, target: the model's fiducials)") from exc
    T0 = fid.T_heart_from_probe
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
    longest = max((record.time_s.shape[0] for record in session.points), default=harmonics.n_terms)
    if longest < harmonics.n_terms:  # no point can have a model: say so once, not once per point
        h = harmonics
        raise RegistrationError(
            "harmonics (--harmonics HC HR HMC HMR) "
            f"{h.cardiac} {h.respiratory} {h.coupled_cardiac} {h.coupled_respiratory} "
            f"need {h.n_terms} Fourier terms, more than the longest point's {longest} samples: lower them "
            "(the paper's 5 4 2 1 need 27)"
        )
    t = time.perf_counter()
    models, fits, exclusions, point_notes = fit_point_models(
        session, harmonics, min_beats=min_beats, min_breaths=min_breaths, coverage_bins=coverage_bins,
        progress=progress,
    )
    notes.extend(point_notes)
    timings["motion_models"] = time.perf_counter() - t
    if len(models) < 3:
        reasons = "; ".join(f"point {i}: {r}" for i, r in exclusions[:5]) + ("; ..." if len(exclusions) > 5 else "")
        excluded = f" ({len(exclusions)} excluded: {reasons})" if exclusions else ""
        raise RegistrationError(
            f"only {len(models)} point(s) could be modelled, ICP needs at least 3{excluded}; record more points"
        )
    if exclusions:
        notes.append(f"{len(exclusions)} point(s) excluded (see exclusions)")
    means = np.stack([m.mean_position_mm for m in models])
    means_map = apply_to_points(T0, means)
    coverage = assess_coverage(means_map, model.mesh.vertices)
    notes.extend(coverage.notes)

    # ---- sweeps
    t = time.perf_counter()
    surface = SurfaceIndex(model.mesh.vertices, model.mesh.faces)
    pivot = surface_centroid(surface)
    timings["surface_index"] = time.perf_counter() - t
    t = time.perf_counter()
    # each point at its slices' cardiac phase when the CT's are given (registration/slice_phase.py)
    point_pc = None if slice_phases is None else point_cardiac_phases(means_map, model.T_heart_from_patient, slice_phases)
    resp = sweep_phase(
        None if point_pc is not None else models, surface, T0, fixed_phase=model.cardiac_phase, kind="respiration",
        phases=phases, pivot_mm=pivot, icp_options=options,
        points=None if point_pc is None else predict_at_point_phases(models, point_pc, phases),
    )
    timings["respiration_sweep"] = time.perf_counter() - t

    # ---- phi_R*: both estimators, the chosen one decides
    t = time.perf_counter()
    curve = None
    if session.fiducial_trace is not None:
        try:
            curve = _trace_curve(session.fiducial_trace, fid_model, phases, fid.order)
        except (SignalError, TemporalError) as exc:
            notes.append(f"the fiducial trace was not used: {exc}")
    vertices = model.mesh.vertices
    paper = paper_phase(phases, resp.T_heart_from_probe, fid_probe, fid_model, pivot, vertices, order=fid.order)
    try:
        shape = estimate_phase(
            phases, resp.distances_mm, resp.T_heart_from_probe, vertices, fiducials=curve,
            breath_hold_phase=breath_hold_phase, breath_hold_sd=breath_hold_sd, points_mm=means_map,
        )
    except TemporalError as exc:  # too few points for its interval: only eq. 10's choice can stand
        if estimator is TemporalEstimator.SHAPE:
            raise
        shape = None
        notes.append(f"the shape estimator (reported beside eq. 10) was not run: it needs at least 7 registered "
                     f"points, got {resp.distances_mm.shape[1]}")
    chosen, other = (shape, paper) if estimator is TemporalEstimator.SHAPE else (paper, shape)
    timings["phase_estimate"] = time.perf_counter() - t
    if not chosen.decided:
        notes.append(
            f"the data cannot decide phi_R* ({estimator.value}): its {100 * chosen.confidence:.0f} % "
            f"interval is {chosen.width:.2f} of a cycle wide; {chosen.advice()}"
        )
    best = chosen.index
    reg = _Chosen(
        respiration_phase=float(chosen.respiration_phase),
        T_heart_from_probe=resp.T_heart_from_probe[best].copy(),
        rms_mm=float(resp.rms_mm[best]),
        translation_distance_mm=float(resp.translation_distance_mm[best]),
        rotation_distance_deg=float(resp.rotation_distance_deg[best]),
        points_probe_mm=(_points_at(models, model.cardiac_phase, chosen.respiration_phase) if point_pc is None
                          else predict_at_point_phases(models, point_pc, [chosen.respiration_phase]))[0],
    )
    card = None
    if cardiac_sweep:
        t = time.perf_counter()
        card = sweep_phase(
            models, surface, T0, fixed_phase=reg.respiration_phase, kind="cardiac",
            phases=phases_c, pivot_mm=pivot, icp_options=options,
        )
        timings["cardiac_sweep"] = time.perf_counter() - t
    if not resp.converged.all():
        bad = resp.phases[~resp.converged]
        limit = options.get("max_iterations", ICP_MAX_ITERATIONS)
        notes.append(
            f"ICP did not converge within {limit} iterations at {bad.size} respiration phase(s) "
            f"(e.g. {bad[0]:.2f}); raise the limit (--icp-max-iterations)"
        )

    # ---- final ICP again, for its degeneracy report (same seed and points: same T)
    t = time.perf_counter()
    final = icp(reg.points_probe_mm, surface, T_init=T0, **options)
    report = IcpReport(
        hessian_eigenvalues=frozen(final.hessian_eigenvalues),
        weakest_direction=frozen(final.weakest_direction),
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
    if not report.converged:
        notes.append(
            f"the final ICP did not converge within {options.get('max_iterations', ICP_MAX_ITERATIONS)} "
            "iterations; raise the limit (--icp-max-iterations)"
        )
    static = compare_static(models, surface, T0, reg.T_heart_from_probe, reg.points_probe_mm,
                            icp_options=options)
    timings["static"] = time.perf_counter() - t

    normals = np.stack([m.predict_normal(model.cardiac_phase, reg.respiration_phase)[0] for m in models])
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
        "estimator": estimator.value,
        "breath_hold_phase": None if breath_hold_phase is None else float(breath_hold_phase),
        "breath_hold_sd": float(breath_hold_sd),
        "slice_phases": slice_phases is not None,
        "session_format_version": int(session.format_version),
        "session_sample_rate_hz": float(session.sample_rate_hz),
        "session_pose_source": session.pose_source,
    }
    return RegistrationResult(
        cardiac_phase=float(model.cardiac_phase),
        cardiac_phase_source=model.cardiac_phase_source,
        respiration_phase=float(reg.respiration_phase),
        T_heart_from_probe=frozen(reg.T_heart_from_probe),
        T0_heart_from_probe=frozen(T0),
        fre_mm=float(fid.fre_rms_mm),
        fiducial_residuals_mm=frozen(fid.residuals_mm),
        fiducials_reordered=bool(fid.reordered),
        fiducials_ambiguous=bool(fid.ambiguous),
        rms_mm=float(reg.rms_mm),
        translation_distance_mm=float(reg.translation_distance_mm),
        rotation_distance_deg=float(reg.rotation_distance_deg),
        euler_xyz_deg=frozen(euler_xyz_deg_from_matrix(reg.T_heart_from_probe)),
        respiration_sweep=resp,
        cardiac_sweep=card,
        static=static,
        phase_estimates=(chosen, other) if other is not None else (chosen,),
        point_ids=frozen(np.array([f.point_id for f in fits], dtype=np.int64)),
        points_probe_mm=frozen(reg.points_probe_mm),
        normals_probe=frozen(normals),
        mean_points_probe_mm=frozen(np.stack([m.mean_position_mm for m in models])),
        point_fits=tuple(fits),
        exclusions=tuple((int(i), str(r)) for i, r in exclusions),
        icp=report,
        trust=assess_trust(
            coverage=coverage, outlier_samples_per_point={f.point_id: f.n_outlier_samples for f in fits},
            n_excluded=len(exclusions), phase_estimate=chosen, icp_converged=report.converged,
            icp_degenerate=report.degenerate, sweep_unconverged=int(np.count_nonzero(~resp.converged)),
            fre_mm=float(fid.fre_rms_mm), max_fre_mm=max_fre_mm, fiducials_ambiguous=bool(fid.ambiguous),
            rms_mm=float(reg.rms_mm), correction_mm=float(reg.translation_distance_mm),
            correction_deg=float(reg.rotation_distance_deg),
            invalid_samples_per_point={p.point_id: (p.n_invalid, p.n_samples + p.n_invalid) for p in session.points},
        ),
        parameters=params,
        timings_s={k: float(v) for k, v in timings.items()},
        notes=tuple(notes),
        n_faces=int(model.mesh.n_faces),
    )
