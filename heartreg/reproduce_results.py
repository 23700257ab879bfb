"""The results of a reproduction of Wood et al. 2018: one row per trial, the summary, the paper's numbers.

Shared by the experiment (:mod:`heartreg.reproduce`, which fills them from the
pipeline's outputs) and its report (:mod:`heartreg.reproduce_report`,
:mod:`heartreg.reproduce_figures`, which only read them).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from hrcore.errors import HeartregError

#: |phi_R* - truth| within this counts as "near the image phase" (cycles).
TOL_PHASE_R = 0.05

#: The paper's results over the six trials (sections 2.2.2, 2.3, 3).
PAPER = {
    "image_phase_range": (0.61, 0.67),
    "phi_r_near_truth": "5 of 6 trials near 0.3",
    "mean_min_translation_mm": 9.9,
    "mean_min_translation_phase": 0.27,
    "mean_rotation_at_min_deg": 8.2,
    "rms_mm": 2.0,
    "mean_delta_range_mm": (1.7, 8.8),
    "mean_delta_mm": 4.2,
}


class ReproduceError(HeartregError, ValueError):
    """The reproduction cannot run as asked (bad trial list, a foreign case in the way)."""


def check_request(trials, *, size, seed, n_points, phase_step) -> list[int]:
    """The trials asked for, as a list, once the request is checked (the trials check it again on their workers:
    here it is one line before any work).

    Raises
    ------
    ReproduceError, UsageError
        Unknown or repeated trials, an unknown size, a negative seed, a point count or a phase step (``--step``)
        out of range.
    """
    from heartreg.phantom.config import MAX_POINTS, PAPER_TABLE1, SIZES
    from registration.pipeline import sweep_phases

    trials = [int(k) for k in trials]
    if not trials:
        raise ReproduceError("trials (--trials) must name at least one of 1..6")
    if any(k not in PAPER_TABLE1 for k in trials) or len(set(trials)) != len(trials):
        raise ReproduceError(f"trials (--trials) must be distinct numbers among 1..6 (Table 1), got {trials}")
    if size not in SIZES:
        raise ReproduceError(f"size must be one of {sorted(SIZES)}, got {size!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ReproduceError(f"seed must be a non-negative integer (--seed), got {seed!r}")
    if n_points is not None and (isinstance(n_points, bool) or not isinstance(n_points, (int, np.integer))
                                 or not 3 <= n_points <= MAX_POINTS):
        raise ReproduceError(f"n_points must be an integer within 3..{MAX_POINTS} (--points), got {n_points!r}")
    sweep_phases(phase_step)  # a UsageError naming --step
    return trials


@dataclass(frozen=True, eq=False)
class TrialResult:
    """One trial's results: its table row and the curves behind the figures.

    Attributes
    ----------
    trial : int
    row : dict
        The trial's table row (column name -> value; see :data:`COLUMNS`).
    truth_rows : list of tuple
        :func:`heartreg.demo.truth_rows` of the run.
    phases_r, phases_c : (m,) float64
        Respiration and cardiac sweep phases.
    rms_r_mm, rms_c_mm : (m,) float64, mm
        RMS point-to-surface error over each sweep.
    translation_distance_mm, rotation_distance_deg : (m,) float64
        Distance of the registration from T0 over the respiration sweep.
    correction_translation_mm, correction_euler_xyz_deg : (m, 3) float64
        Components of ``T inv(T0)`` over the respiration sweep (heart frame, Fig. 6).
    delta_mm : (n,) float64, mm
        delta_i per registered point (Fig. 9).
    slice_position_mm, slice_phase : (k,) float64
        Cardiac phase per CT slice (Fig. 4).
    timings_s : dict
    """

    trial: int
    row: dict
    truth_rows: list
    phases_r: np.ndarray
    phases_c: np.ndarray
    rms_r_mm: np.ndarray
    rms_c_mm: np.ndarray
    translation_distance_mm: np.ndarray
    rotation_distance_deg: np.ndarray
    correction_translation_mm: np.ndarray
    correction_euler_xyz_deg: np.ndarray
    delta_mm: np.ndarray
    slice_position_mm: np.ndarray
    slice_phase: np.ndarray
    timings_s: dict = field(default_factory=dict)


#: (key, header, unit/meaning) of the per-trial row, in CSV order.
COLUMNS = (
    ("trial", "trial", ""),
    ("points_used", "points used", "registered attachment points"),
    ("points_excluded", "points excluded", ""),
    ("heart_rate_hz", "heart rate (Hz)", "mean over points, from the session ECG"),
    ("resp_rate_hz", "resp. rate (Hz)", "mean over points, from the flows"),
    ("paper_heart_rate_hz", "paper heart rate (Hz)", "Table 1"),
    ("paper_resp_rate_hz", "paper resp. rate (Hz)", "Table 1"),
    ("phi_c", "phi_C* ours", "mean slice phase"),
    ("phi_c_truth", "phi_C* truth", "phantom"),
    ("phi_c_paper", "phi_C* paper", "Table 1"),
    ("phase_source", "R-peak source", ""),
    ("euler_fit_a_deg", "alpha fit", "deg"),
    ("euler_fit_b_deg", "beta fit", "deg"),
    ("euler_fit_g_deg", "gamma fit", "deg"),
    ("euler_preset_a_deg", "alpha preset", "deg"),
    ("euler_preset_b_deg", "beta preset", "deg"),
    ("euler_preset_g_deg", "gamma preset", "deg"),
    ("euler_paper_a_deg", "alpha paper", "deg"),
    ("euler_paper_b_deg", "beta paper", "deg"),
    ("euler_paper_g_deg", "gamma paper", "deg"),
    ("frame_z_error_deg", "frame z-axis error (deg)", "fitted vs true heart axis"),
    ("phi_r", "phi_R* ours", "eq. 10"),
    ("phi_r_truth", "phi_R* truth", "phantom breath-hold phase"),
    ("phi_r_error", "phi_R* error", "wrapped, cycles"),
    ("phi_r_within", "within 0.05", ""),
    ("min_translation_mm", "min translation (mm)", "distance from T0 at phi_R*"),
    ("rotation_at_min_deg", "rotation at min (deg)", "distance from T0 at phi_R*"),
    ("rms_at_phi_r_mm", "RMS at phi_R* (mm)", ""),
    ("rms_min_mm", "RMS min over phi_R (mm)", ""),
    ("rms_max_mm", "RMS max over phi_R (mm)", ""),
    ("rms_argmin_phase", "phi_R of min RMS", "eq. 9 applied to phi_R"),
    ("sweep_unconverged", "ICP unconverged phases", "of the respiration sweep"),
    ("icp_weak_long_axis", "ICP weakest: turn about z", "|z-rotation component| of the final ICP's weakest direction"),
    ("icp_converged", "final ICP converged", ""),
    ("mean_delta_mm", "mean delta (mm)", "static vs spatiotemporal, paper 2.3.2"),
    ("fre_mm", "FRE (mm)", "fiducial registration error, RMS"),
    ("t0_error_mm", "T0 error (mm)", "fiducial registration vs truth, at the surface centroid"),
    ("t0_error_deg", "T0 error (deg)", "fiducial registration vs truth, rotation"),
    ("t0_error_along_path", "T0 error along resp. path", "|cos| with the sweep locus' main axis"),
    ("resp_path_mm", "resp. path (mm)", "peak-to-peak of the sweep locus along its main axis"),
    ("final_error_mm", "final T error (mm)", "vs truth, at the heart origin"),
    ("final_error_deg", "final T error (deg)", ""),
    ("static_error_mm", "static T error (mm)", "mean-position registration vs truth"),
    ("static_error_deg", "static T error (deg)", ""),
    ("miss_reason", "miss reason", "empty when phi_R* is within 0.05"),
    ("case_reused", "case reused", ""),
    ("time_phantom_s", "phantom time (s)", ""),
    ("time_pipeline_s", "pipeline time (s)", ""),
)


def _mean_curve(trials, attr, phases_attr="phases_r"):
    """Mean over trials of a per-phase curve; the trials must share the phase grid."""
    grids = [getattr(t, phases_attr) for t in trials]
    for g in grids[1:]:
        if g.shape != grids[0].shape or not np.allclose(g, grids[0]):
            raise ReproduceError("the trials' sweeps use different phase grids; run them with one step")
    return grids[0], np.mean([getattr(t, attr) for t in trials], axis=0)


def _summary(trials: Sequence[TrialResult]) -> dict:
    rows = [t.row for t in trials]
    phases, mean_t = _mean_curve(trials, "translation_distance_mm")
    _, mean_r = _mean_curve(trials, "rotation_distance_deg")
    _, mean_rms = _mean_curve(trials, "rms_r_mm")
    i = int(np.argmin(mean_t))

    def mean(key):
        return float(np.mean([r[key] for r in rows]))

    deltas = [r["mean_delta_mm"] for r in rows]
    return {
        "n_trials": len(rows),
        "phi_r_within": int(sum(r["phi_r_within"] for r in rows)),
        "misses": [r["trial"] for r in rows if not r["phi_r_within"]],
        "phi_c_range": [float(min(r["phi_c"] for r in rows)), float(max(r["phi_c"] for r in rows))],
        "mean_curve_min_translation_mm": float(mean_t[i]),
        "mean_curve_min_phase": float(phases[i]),
        "mean_curve_rotation_at_min_deg": float(mean_r[i]),
        "mean_of_min_translation_mm": mean("min_translation_mm"),
        "mean_of_rotation_at_min_deg": mean("rotation_at_min_deg"),
        "mean_rms_mm": float(np.mean(mean_rms)),
        "mean_rms_range_mm": [float(mean_rms.min()), float(mean_rms.max())],
        "mean_delta_mm": float(np.mean(deltas)),
        "mean_delta_range_mm": [float(min(deltas)), float(max(deltas))],
        "mean_final_error_mm": mean("final_error_mm"),
        "mean_static_error_mm": mean("static_error_mm"),
        "mean_t0_error_mm": mean("t0_error_mm"),
        "mean_t0_error_deg": mean("t0_error_deg"),
        "mean_final_error_deg": mean("final_error_deg"),
        "mean_static_error_deg": mean("static_error_deg"),
        "sweep_unconverged": int(sum(r["sweep_unconverged"] for r in rows)),
        "sweep_phases": int(sum(len(t.phases_r) for t in trials)),
        "mean_frame_z_error_deg": mean("frame_z_error_deg"),
        "mean_icp_weak_long_axis": mean("icp_weak_long_axis"),
        "final_icp_unconverged": [r["trial"] for r in rows if not r["icp_converged"]],
    }


def path_axis(locus_mm):
    """Main axis (unit (3,)) and peak-to-peak extent (mm) of a (m, 3) locus."""
    centred = locus_mm - locus_mm.mean(axis=0)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    axis = vt[0]
    along = centred @ axis
    return axis, float(along.max() - along.min())


def miss_reason(row) -> str:
    """Why eq. 10 missed the image phase in a trial's row ('' when it did not)."""
    if row["phi_r_within"]:
        return ""
    share = row["t0_error_along_path"]
    head = (f"phi_R* = {row['phi_r']:.2f} vs truth {row['phi_r_truth']:.2f}: "
            f"{100 * share:.0f} % of the {row['t0_error_mm']:.1f} mm fiducial (T0) error lies along "
            f"the respiratory path ({row['resp_path_mm']:.1f} mm peak to peak)")
    if share >= 0.5:
        return head + ", so a wrong respiration phase cancels part of it and eq. 10 is drawn away"
    return head + "; the error is mostly across the path, so this check does not explain the miss"
