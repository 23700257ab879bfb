"""``heartreg reproduce``: the paper's experiment on the six phantom presets.

For every trial ``N`` of Wood et al. 2018 (Table 1) the phantom writes a case
with the preset ``wood2018-trialN`` (reused when ``truth.json`` is already
there), the whole chain runs on it (:func:`heartreg.pipeline.run_pipeline`)
and the results are set beside the phantom's truth and the paper's numbers::

    OUT_DIR/trialN/case/          phantom case: ct/, qrs.csv, session/, truth.json
    OUT_DIR/trialN/run/           pipeline outputs (phases/, model/, registration/, report.html)
    OUT_DIR/trialN/trial.json     this trial's row and its recovered-vs-truth rows
    OUT_DIR/reproduction.csv      one row per trial, every column
    OUT_DIR/reproduction.json     rows, summary over trials, the paper's numbers, timings
    OUT_DIR/reproduction.md       the two tables beside the paper's (Markdown)
    OUT_DIR/figures.json          the data behind every figure, curve by curve
    OUT_DIR/fig2_rms.png, fig4_phases.png, fig6_parameters.png, fig7_distances.png,
    OUT_DIR/fig9_delta.png        the paper's figures, all trials + mean
    OUT_DIR/reproduction.html     one self-contained page with all of it

``reproduce(..., rerun=False)`` (``heartreg reproduce --report-only``) re-draws
the tables, figures and page from an earlier run's files without running
anything: every number is read from the pipeline's outputs in either case.

Which trials "miss" (phi_R* more than :data:`TOL_PHASE_R` from the truth) is
explained from the data: the share of the fiducial registration's error that
lies along the heart's respiratory path (the main axis of the translation
locus that the sweep's registrations trace over phi_R).  An error along that
path is partly cancelled by a wrong respiration phase, so the empirical metric
(paper eq. 10) is drawn away from the truth.
"""

from __future__ import annotations

import csv
import html
import io
import json
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from imaging.files import atomic_path, write_text_atomic

__all__ = [
    "COLUMNS",
    "PAPER",
    "PAPER_TABLE1",
    "TRIALS",
    "TOL_PHASE_R",
    "ReproduceError",
    "TrialResult",
    "Reproduction",
    "reproduce",
    "figure_data",
]

#: The paper's six porcine trials.
TRIALS = (1, 2, 3, 4, 5, 6)

#: |phi_R* - truth| within this counts as "near the image phase" (cycles).
TOL_PHASE_R = 0.05

#: Wood et al. 2018, Table 1: points, heart rate (Hz), respiration rate (Hz),
#: image phase phi_C*, X-Y-Z intrinsic Euler angles of the map frame (deg).
#: Kept here, from the paper, independently of the phantom's presets.
PAPER_TABLE1 = {
    1: (101, 1.08, 0.20, 0.66, (-22.9, 2.2, -43.8)),
    2: (108, 1.36, 0.20, 0.61, (-14.6, 5.1, -63.5)),
    3: (98, 1.59, 0.17, 0.64, (-19.5, 11.2, -59.0)),
    4: (44, 1.42, 0.17, 0.66, (-26.0, 12.7, -86.0)),
    5: (84, 1.37, 0.17, 0.64, (-27.6, 14.0, -55.6)),
    6: (95, 1.03, 0.17, 0.67, (-25.7, 16.1, -78.4)),
}

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


class ReproduceError(ValueError):
    """The reproduction cannot run as asked (bad trial list, a foreign case in the way)."""


def _wrap(d):
    """Phase difference wrapped into [-0.5, 0.5) cycles."""
    return (np.asarray(d, dtype=float) + 0.5) % 1.0 - 0.5


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


@dataclass(frozen=True, eq=False)
class Reproduction:
    """The whole experiment: trials, summary over them, files written."""

    out_dir: Path
    size: str
    seed: int
    trials: tuple[TrialResult, ...]
    summary: dict
    paths: dict
    timings_s: dict


# ----------------------------------------------------------------- columns
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


# ----------------------------------------------------------------- per trial
def _ensure_case(case_dir: Path, preset: str, size: str, seed: int, n_points, progress: bool):
    """Make the phantom case, or reuse one with the same preset, size, seed and points."""
    from heartreg.phantom import make_phantom

    truth_path = case_dir / "truth.json"
    if truth_path.exists():
        truth = json.loads(truth_path.read_text())
        want = {"preset": preset, "size": size, "seed": seed}
        have = {k: truth.get(k) for k in want}
        if n_points is not None:
            want["n_points"] = n_points
            have["n_points"] = truth.get("config", {}).get("n_points")
        if have != want or "session" not in truth:
            raise ReproduceError(
                f"{case_dir} holds another phantom case ({have}, session "
                f"{'yes' if 'session' in truth else 'no'}), not {want}; choose another output "
                "folder or delete that case"
            )
        return truth, True
    overrides = {} if n_points is None else {"n_points": n_points}
    # no truth.json: anything else there is a half-written case, replace it
    truth = make_phantom(case_dir, preset=preset, size=size, seed=seed, progress=progress,
                         overwrite=True, **overrides)
    return truth, False


def _pose_error(T, T_true, point_probe):
    """Error of ``T`` against ``T_true`` at a probe-frame point: (vector mm, norm mm, angle deg)."""
    from registration import rotation_distance_deg

    p = np.append(point_probe, 1.0)
    vec = (T @ p - T_true @ p)[:3]
    return vec, float(np.linalg.norm(vec)), float(rotation_distance_deg(T, T_true))


def _path_axis(locus_mm):
    """Main axis (unit (3,)) and peak-to-peak extent (mm) of a (m, 3) locus."""
    centred = locus_mm - locus_mm.mean(axis=0)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    axis = vt[0]
    along = centred @ axis
    return axis, float(along.max() - along.min())


def _miss_reason(row) -> str:
    if row["phi_r_within"]:
        return ""
    share = row["t0_error_along_path"]
    head = (f"phi_R* = {row['phi_r']:.2f} vs truth {row['phi_r_truth']:.2f}: "
            f"{100 * share:.0f} % of the {row['t0_error_mm']:.1f} mm fiducial (T0) error lies along "
            f"the respiratory path ({row['resp_path_mm']:.1f} mm peak to peak)")
    if share >= 0.5:
        return head + ", so a wrong respiration phase cancels part of it and eq. 10 is drawn away"
    return head + "; the error is mostly across the path, so this check does not explain the miss"


def _read_csv(path: Path) -> dict:
    """Columns of a CSV file with a header, as float arrays."""
    data = np.genfromtxt(path, delimiter=",", names=True, ndmin=1)
    return {name: np.asarray(data[name], dtype=float) for name in data.dtype.names}


def _trial_row(trial: int, files: dict, truth: dict, truth_rows: list) -> dict:
    """The table row of one trial from the pipeline's files (``files`` from :func:`_read_run`)."""
    from heartreg.phantom.config import PAPER_IMAGE_PHASE

    phases, model, reg, sweep = files["phases"], files["model"], files["registration"], files["sweep"]
    paper = PAPER_TABLE1[trial]
    preset = f"wood2018-trial{trial}"
    T = {name: np.asarray(v, dtype=float) for name, v in (
        ("final", reg["T_heart_from_probe"]), ("T0", reg["T0_heart_from_probe"]),
        ("static", reg["static"]["T_heart_from_probe"]))}

    T_true = np.asarray(model["T_heart_from_patient"], dtype=float) @ np.asarray(truth["T_patient_from_probe"])
    T_probe_from_heart = np.linalg.inv(T_true)
    origin_probe = T_probe_from_heart[:3, 3]  # the fitted heart origin, probe frame
    centroid_probe = (T_probe_from_heart @ np.append(reg["pivot_heart_mm"], 1.0))[:3]
    _, final_mm, final_deg = _pose_error(T["final"], T_true, origin_probe)
    _, static_mm, static_deg = _pose_error(T["static"], T_true, origin_probe)
    # T0's error at the sweep's pivot, heart frame: the quantity eq. 10 measures
    t0_vec, t0_mm, t0_deg = _pose_error(T["T0"], T_true, centroid_probe)
    locus = np.stack([sweep["tx_mm"], sweep["ty_mm"], sweep["tz_mm"]], axis=1)
    axis, path_mm = _path_axis(locus)
    along = float(abs(t0_vec @ axis) / t0_mm) if t0_mm > 0 else 0.0

    by_name = {r[0]: r for r in truth_rows}
    fits = reg["point_fits"]
    e_fit = [float(x) for x in model["euler_xyz_deg"]]
    e_preset = [float(x) for x in truth["heart_euler_xyz_deg"]]
    phi_r_err = float(_wrap(reg["respiration_phase"] - truth["respiration_phase"]))
    i_rms = int(np.argmin(sweep["rms_mm"]))
    row = {
        "trial": trial,
        "points_used": int(reg["n_points"]),
        "points_excluded": len(reg["exclusions"]),
        "heart_rate_hz": float(np.mean([f["heart_rate_hz"] for f in fits])),
        "resp_rate_hz": float(np.mean([f["resp_rate_hz"] for f in fits])),
        "paper_heart_rate_hz": paper[1],
        "paper_resp_rate_hz": paper[2],
        "phi_c": float(phases["volume_cardiac_phase"]),
        "phi_c_truth": float(truth["cardiac_phase"]),
        "phi_c_paper": float(PAPER_IMAGE_PHASE.get(preset, paper[3])),
        "phase_source": phases["source"],
        "euler_fit_a_deg": e_fit[0], "euler_fit_b_deg": e_fit[1], "euler_fit_g_deg": e_fit[2],
        "euler_preset_a_deg": e_preset[0], "euler_preset_b_deg": e_preset[1], "euler_preset_g_deg": e_preset[2],
        "euler_paper_a_deg": paper[4][0], "euler_paper_b_deg": paper[4][1], "euler_paper_g_deg": paper[4][2],
        "frame_z_error_deg": float(by_name["heart frame z axis (deg)"][1]),
        "phi_r": float(reg["respiration_phase"]),
        "phi_r_truth": float(truth["respiration_phase"]),
        "phi_r_error": phi_r_err,
        "phi_r_within": bool(abs(phi_r_err) <= TOL_PHASE_R + 1e-9),
        "min_translation_mm": float(reg["translation_distance_mm"]),
        "rotation_at_min_deg": float(reg["rotation_distance_deg"]),
        "rms_at_phi_r_mm": float(reg["rms_mm"]),
        "rms_min_mm": float(np.min(sweep["rms_mm"])),
        "rms_max_mm": float(np.max(sweep["rms_mm"])),
        "rms_argmin_phase": float(sweep["phase_r"][i_rms]),
        "sweep_unconverged": int(reg["sweep"]["respiration_phases"] - reg["sweep"]["respiration_converged"]),
        "icp_weak_long_axis": float(abs(reg["icp"]["weakest_direction"][2])),
        "icp_converged": bool(reg["icp"]["converged"]),
        "mean_delta_mm": float(reg["delta_static_mean_mm"]),
        "fre_mm": float(reg["fre_mm"]),
        "t0_error_mm": t0_mm,
        "t0_error_deg": t0_deg,
        "t0_error_along_path": along,
        "resp_path_mm": path_mm,
        "final_error_mm": final_mm,
        "final_error_deg": final_deg,
        "static_error_mm": static_mm,
        "static_error_deg": static_deg,
    }
    row["miss_reason"] = _miss_reason(row)
    return row


def _read_run(run_dir: Path) -> dict:
    """The pipeline's output files that the reproduction reads."""
    reg_dir = run_dir / "registration"
    files = {
        "phases": json.loads((run_dir / "phases" / "phases.json").read_text()),
        "slices": _read_csv(run_dir / "phases" / "phases.csv"),
        "model": json.loads((run_dir / "model" / "model.json").read_text()),
        "registration": json.loads((reg_dir / "registration.json").read_text()),
        "sweep": _read_csv(reg_dir / "sweep.csv"),
    }
    card = reg_dir / "cardiac_sweep.csv"
    files["cardiac_sweep"] = _read_csv(card) if card.exists() else None
    return files


def _trial_result(trial: int, trial_dir: Path, truth: dict, truth_rows: list, extra: dict,
                  timings: dict) -> TrialResult:
    """One trial's results from its pipeline outputs in ``trial_dir/run``."""
    files = _read_run(trial_dir / "run")
    row = _trial_row(trial, files, truth, truth_rows)
    row.update(extra)
    reg, sweep, card = files["registration"], files["sweep"], files["cardiac_sweep"]
    empty = np.empty(0)
    delta = reg["delta_static_mm"]
    return TrialResult(
        trial=trial,
        row=row,
        truth_rows=[tuple(_plain(v) for v in r) for r in truth_rows],
        phases_r=sweep["phase_r"],
        phases_c=empty if card is None else card["phase_c"],
        rms_r_mm=sweep["rms_mm"],
        rms_c_mm=empty if card is None else card["rms_mm"],
        translation_distance_mm=sweep["translation_distance_mm"],
        rotation_distance_deg=sweep["rotation_distance_deg"],
        correction_translation_mm=np.stack([sweep[c] for c in ("tx_mm", "ty_mm", "tz_mm")], axis=1),
        correction_euler_xyz_deg=np.stack([sweep[c] for c in ("rx_deg", "ry_deg", "rz_deg")], axis=1),
        delta_mm=np.array([delta[str(i)] for i in reg["point_ids"]], dtype=float),
        slice_position_mm=files["slices"]["position_mm"],
        slice_phase=files["slices"]["cardiac_phase"],
        timings_s=dict(timings),
    )


def _plain(v):
    """JSON-ready scalar."""
    if isinstance(v, (np.bool_,)):
        return bool(v)
    if isinstance(v, np.integer):
        return int(v)
    if isinstance(v, np.floating):
        return float(v)
    return v


# ----------------------------------------------------------------- summary
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


# ----------------------------------------------------------------- tables
def _fmt(v, digits=2) -> str:
    if isinstance(v, (bool, np.bool_)):
        return "yes" if v else "**no**"
    if isinstance(v, (float, np.floating)):
        return f"{v:.{digits}f}"
    return str(v)


def _md_table(header, rows) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    for r in rows:
        lines.append("| " + " | ".join(str(c).replace("|", "\\|") for c in r) + " |")
    return "\n".join(lines)


def _table_a(trials):
    """Table 1 beside the paper: header and rows of formatted strings."""
    header = ["trial", "points", "heart rate (Hz) ours / paper", "resp. rate (Hz) ours / paper",
              "phi_C* ours / truth / paper", "Euler X-Y-Z fitted (deg)", "preset (deg)", "paper (deg)",
              "z-axis error (deg)"]
    rows = []
    for t in trials:
        r = t.row
        rows.append([
            str(r["trial"]),
            f"{r['points_used']}" + (f" (+{r['points_excluded']} excl.)" if r["points_excluded"] else ""),
            f"{r['heart_rate_hz']:.2f} / {r['paper_heart_rate_hz']:.2f}",
            f"{r['resp_rate_hz']:.2f} / {r['paper_resp_rate_hz']:.2f}",
            f"{r['phi_c']:.3f} / {r['phi_c_truth']:.3f} / {r['phi_c_paper']:.2f}",
            ", ".join(f"{r[f'euler_fit_{k}_deg']:.1f}" for k in "abg"),
            ", ".join(f"{r[f'euler_preset_{k}_deg']:.1f}" for k in "abg"),
            ", ".join(f"{r[f'euler_paper_{k}_deg']:.1f}" for k in "abg"),
            f"{r['frame_z_error_deg']:.2f}",
        ])
    return header, rows


def _table_b(trials, summary):
    """Registration results beside the paper's: header and rows of formatted strings."""
    header = ["trial", "phi_R* ours / truth", "within ±0.05", "min translation (mm)", "rotation at min (deg)",
              "RMS over phi_R (mm)", "mean delta (mm)", "T0 error (mm, deg)", "final T error (mm, deg)",
              "static T error (mm, deg)"]
    rows = []
    for t in trials:
        r = t.row
        rows.append([
            str(r["trial"]), f"{r['phi_r']:.2f} / {r['phi_r_truth']:.2f}", _fmt(r["phi_r_within"]),
            f"{r['min_translation_mm']:.2f}", f"{r['rotation_at_min_deg']:.2f}",
            f"{r['rms_min_mm']:.2f}–{r['rms_max_mm']:.2f}", f"{r['mean_delta_mm']:.2f}",
            f"{r['t0_error_mm']:.2f}, {r['t0_error_deg']:.2f}",
            f"{r['final_error_mm']:.2f}, {r['final_error_deg']:.2f}",
            f"{r['static_error_mm']:.2f}, {r['static_error_deg']:.2f}",
        ])
    s = summary
    rows.append([
        "**mean**", f"{s['phi_r_within']} of {s['n_trials']} within", "",
        f"{s['mean_curve_min_translation_mm']:.2f} at phi_R {s['mean_curve_min_phase']:.2f} (mean curve)",
        f"{s['mean_curve_rotation_at_min_deg']:.2f}",
        f"{s['mean_rms_range_mm'][0]:.2f}–{s['mean_rms_range_mm'][1]:.2f} (mean curve)",
        f"{s['mean_delta_mm']:.2f} ({s['mean_delta_range_mm'][0]:.2f}–{s['mean_delta_range_mm'][1]:.2f})",
        f"{s['mean_t0_error_mm']:.2f}, {s['mean_t0_error_deg']:.2f}",
        f"{s['mean_final_error_mm']:.2f}, {s['mean_final_error_deg']:.2f}",
        f"{s['mean_static_error_mm']:.2f}, {s['mean_static_error_deg']:.2f}",
    ])
    p = PAPER
    rows.append([
        "**paper**", "≈0.3 in 5 of 6", "5 of 6",
        f"{p['mean_min_translation_mm']} at phi_R {p['mean_min_translation_phase']} (mean curve)",
        f"{p['mean_rotation_at_min_deg']}", f"≈{p['rms_mm']:g}, flat",
        f"{p['mean_delta_mm']} ({p['mean_delta_range_mm'][0]}–{p['mean_delta_range_mm'][1]})",
        "–", "– (no ground truth)", "–",
    ])
    return header, rows


def _csv_text(trials) -> str:
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow([k for k, _, _ in COLUMNS])
    for t in trials:
        writer.writerow([_csv_cell(t.row.get(k, "")) for k, _, _ in COLUMNS])
    return buf.getvalue()


def _csv_cell(v):
    if isinstance(v, (bool, np.bool_)):
        return "true" if v else "false"
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    return v


def _markdown(trials, summary, *, size, seed, command) -> str:
    ha, ra = _table_a(trials)
    hb, rb = _table_b(trials, summary)
    misses = [t.row for t in trials if not t.row["phi_r_within"]]
    out = [
        "# Wood et al. 2018 reproduced on the phantom",
        "",
        f"Phantom size `{size}`, seed {seed}, trials {', '.join(str(t.trial) for t in trials)}."
        + (f" Command: `{command}`." if command else ""),
        "",
        "## Table 1 beside the paper",
        "",
        "Rates from the session's ECG and flows; phi_C* the mean slice phase of the CT; "
        "Euler angles of the fitted heart frame against the phantom preset and the paper.",
        "",
        _md_table(ha, ra),
        "",
        "## Registration beside the paper (sections 2.3 and 3)",
        "",
        "phi_R* by eq. 10 (minimum translation distance from the fiducial registration T0); "
        "distances from T0 at the surface centroid; delta = static vs spatiotemporal surface point "
        "(paper 2.3.2); errors against the phantom's truth, translation at the heart origin.",
        "",
        _md_table(hb, rb),
        "",
    ]
    if misses:
        out += ["Misses (phi_R* more than 0.05 from the truth):", ""]
        out += [f"- trial {r['trial']}: {r['miss_reason']}" for r in misses]
        out.append("")
    out += ["## Where our synthetic numbers differ from the paper and why", ""]
    out += ["- " + html.unescape(item.replace("<b>", "**").replace("</b>", "**"))
            for item in _differences(trials, summary)]
    out.append("")
    stages = ("phantom", "phases", "model", "registration", "pipeline")
    out += ["## Time per trial (s)", "",
            _md_table(["trial", *stages, "case reused"],
                      [[str(t.trial), *(f"{t.timings_s.get(k, float('nan')):.1f}" for k in stages),
                        _fmt(bool(t.row["case_reused"])).replace("**", "")] for t in trials]),
            "", "(phantom: writing the case, 0 when reused; pipeline = phases + model + registration + report.)", ""]
    return "\n".join(out)


# ----------------------------------------------------------------- figures
def _series(label, x, y, kind="trial"):
    return {"label": label, "kind": kind, "x": [float(v) for v in x], "y": [float(v) for v in y]}


def _panel(title, xlabel, ylabel, series, **extra):
    return {"title": title, "xlabel": xlabel, "ylabel": ylabel, "series": series, **extra}


def figure_data(trials: Sequence[TrialResult]) -> dict:
    """The data behind every figure: ``{fig: {"title", "panels": [panel, ...]}}``.

    Each panel holds ``series``: dicts with ``label``, ``kind`` (``"trial"``,
    ``"mean"``, ``"marker"`` or ``"window"``), ``x`` and ``y``.  Per-trial curves
    come first, in trial order, then the mean, then markers.
    """
    trials = list(trials)
    names = [f"trial {t.trial}" for t in trials]
    figs = {}

    # Fig. 2: RMS over phi_C (at phi_R*) and over phi_R (at phi_C*)
    panels = []
    have_c = all(t.phases_c.size for t in trials)
    if have_c:
        xc, mc = _mean_curve(trials, "rms_c_mm", "phases_c")
        s = [_series(n, t.phases_c, t.rms_c_mm) for n, t in zip(names, trials)]
        s.append(_series("mean", xc, mc, "mean"))
        panels.append(_panel("(A) cardiac phase swept at each trial's phi_R*", "cardiac phase phi_C",
                             "RMS point-to-surface error (mm)", s))
    xr, mr = _mean_curve(trials, "rms_r_mm")
    s = [_series(n, t.phases_r, t.rms_r_mm) for n, t in zip(names, trials)]
    s.append(_series("mean", xr, mr, "mean"))
    panels.append(_panel(f"({'B' if have_c else 'A'}) respiration phase swept at each trial's phi_C*",
                         "respiration phase phi_R", "RMS point-to-surface error (mm)", s))
    figs["fig2"] = {"title": "Registration RMS error across phase, all trials (cf. Wood et al. 2018, Fig. 2)",
                    "panels": panels}

    # Fig. 6: correction components over phi_R
    panels = []
    for attr, what, unit, comps in (
        ("correction_translation_mm", "translation", "mm", ("x", "y", "z")),
        ("correction_euler_xyz_deg", "rotation", "deg", ("alpha (X)", "beta (Y)", "gamma (Z)")),
    ):
        for j, comp in enumerate(comps):
            s = [_series(n, t.phases_r, getattr(t, attr)[:, j]) for n, t in zip(names, trials)]
            s.append(_series("mean", xr, np.mean([getattr(t, attr)[:, j] for t in trials], axis=0), "mean"))
            panels.append(_panel(f"{what} {comp}", "respiration phase phi_R", unit, s))
    figs["fig6"] = {"title": "Registration parameters T inv(T0) across respiration phase, heart frame "
                             "(cf. Fig. 6: A translation, B rotation)", "panels": panels}

    # Fig. 7: distance magnitudes over phi_R, minima marked
    panels = []
    _, mt = _mean_curve(trials, "translation_distance_mm")
    _, mrot = _mean_curve(trials, "rotation_distance_deg")
    i_mean = int(np.argmin(mt))
    for attr, mean_curve, title, unit in (
        ("translation_distance_mm", mt, "(A) translation distance from T0", "mm"),
        ("rotation_distance_deg", mrot, "(B) rotation distance from T0", "deg"),
    ):
        s = [_series(n, t.phases_r, getattr(t, attr)) for n, t in zip(names, trials)]
        s.append(_series("mean", xr, mean_curve, "mean"))
        idx = [int(np.argmin(t.translation_distance_mm)) for t in trials]
        s.append(_series("phi_R* per trial", [t.phases_r[i] for t, i in zip(trials, idx)],
                         [getattr(t, attr)[i] for t, i in zip(trials, idx)], "marker"))
        s.append(_series("mean at its minimum translation", [xr[i_mean]], [mean_curve[i_mean]], "marker"))
        panels.append(_panel(title, "respiration phase phi_R", unit, s))
    figs["fig7"] = {"title": "Distance of the registration from the fiducial seed T0 (cf. Fig. 7, eq. 10)",
                    "panels": panels}

    # Fig. 9: delta per point per trial, mean as a square
    s = [_series(n, np.full(t.delta_mm.size, float(t.trial)), t.delta_mm) for n, t in zip(names, trials)]
    s.append(_series("mean per trial", [t.trial for t in trials], [t.delta_mm.mean() for t in trials], "marker"))
    figs["fig9"] = {"title": "Static vs spatiotemporal registration: delta per point (cf. Fig. 9)",
                    "panels": [_panel("", "trial", "delta (mm)", s)]}

    # Fig. 4: cardiac phase per slice, per trial
    panels = []
    for n, t in zip(names, trials):
        s = [_series(n, t.slice_position_mm, t.slice_phase),
             _series("phi_C* (mean)", [t.slice_position_mm.min(), t.slice_position_mm.max()],
                     [t.row["phi_c"]] * 2, "mean"),
             _series("motion-free window 0.6-0.8", [0.6, 0.8], [0.6, 0.8], "window")]
        panels.append(_panel(f"{n}: phi_C* = {t.row['phi_c']:.3f} (paper {t.row['phi_c_paper']:.2f})",
                             "slice position (mm)", "cardiac phase", s))
    figs["fig4"] = {"title": "Cardiac phase of every CT slice (cf. Fig. 4)", "panels": panels}
    return figs


_DPI = 110
_STYLE = """
body { font-family: -apple-system, Segoe UI, Helvetica, Arial, sans-serif; margin: 2em auto;
       max-width: 1150px; color: #222; line-height: 1.45; }
h2 { border-bottom: 1px solid #ddd; padding-bottom: .2em; margin-top: 2em; }
table { border-collapse: collapse; margin: .8em 0; font-size: .9em; }
th, td { border: 1px solid #ccc; padding: .3em .6em; text-align: left; vertical-align: top; }
th { background: #f3f3f3; } td.num { text-align: right; font-variant-numeric: tabular-nums; }
.ok { color: #1a7f37; font-weight: 600; } .miss { color: #b42318; font-weight: 600; }
img { max-width: 100%; border: 1px solid #eee; margin: .5em 0; } li { margin: .4em 0; }
.note { color: #555; font-size: .9em; }
"""
_MEAN_STYLE = {"color": "black", "linestyle": "--", "linewidth": 2.2}


def _tex(text: str) -> str:
    """Plot text: ``phi_R*`` -> mathtext phi with sub- and superscript."""
    return re.sub(r"phi_([RC])(\*?)", lambda m: f"$\\varphi_{m[1]}{'^*' if m[2] else ''}$", text)


def _colours(n):
    from matplotlib import colormaps

    cmap = colormaps["tab10"]
    return [cmap(i % 10) for i in range(n)]


def _save(fig, path: Path) -> Path:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return path


def _draw_curves(ax, panel, colours):
    k = 0
    for s in panel["series"]:
        if s["kind"] == "trial":
            ax.plot(s["x"], s["y"], color=colours[k], linewidth=1.1, alpha=0.85, label=_tex(s["label"]))
            k += 1
        elif s["kind"] == "mean":
            ax.plot(s["x"], s["y"], label=_tex(s["label"]), **_MEAN_STYLE)
    ax.set_xlabel(_tex(panel["xlabel"]))
    ax.set_ylabel(_tex(panel["ylabel"]))
    ax.set_xlim(0, 1)
    ax.grid(alpha=0.3)
    ax.set_title(_tex(panel["title"]), fontsize=10)


def _plot_figures(figs: dict, out: Path) -> dict:
    from matplotlib.figure import Figure  # no pyplot: no global backend state

    paths = {}
    n_trials = sum(s["kind"] == "trial" for s in figs["fig2"]["panels"][0]["series"])
    colours = _colours(n_trials)

    # Fig. 2
    panels = figs["fig2"]["panels"]
    fig = Figure(figsize=(11, 4.4), dpi=_DPI, layout="constrained")
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    for ax, panel in zip(axes, panels):
        _draw_curves(ax, panel, colours)
        ax.set_ylim(bottom=0, top=1.25 * max(max(s["y"]) for s in panel["series"]))
    axes[-1].legend(fontsize=8, ncol=4, loc="upper right")
    fig.suptitle(figs["fig2"]["title"], fontsize=11)
    paths["fig2"] = _save(fig, out / "fig2_rms.png")

    # Fig. 6: 2 x 3
    panels = figs["fig6"]["panels"]
    fig = Figure(figsize=(13, 7.2), dpi=_DPI, layout="constrained")
    axes = fig.subplots(2, 3)
    for ax, panel in zip(axes.ravel(), panels):
        _draw_curves(ax, panel, colours)
        ax.axhline(0.0, color="grey", linewidth=0.6)
    axes[0, 0].set_title("(A) " + axes[0, 0].get_title(), fontsize=10)
    axes[1, 0].set_title("(B) " + axes[1, 0].get_title(), fontsize=10)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=len(labels), fontsize=9)
    fig.suptitle(figs["fig6"]["title"].replace("T inv(T0)", "$T\\,T_0^{-1}$"), fontsize=11)
    paths["fig6"] = _save(fig, out / "fig6_parameters.png")

    # Fig. 7
    panels = figs["fig7"]["panels"]
    fig = Figure(figsize=(11, 4.6), dpi=_DPI, layout="constrained")
    axes = fig.subplots(1, 2)
    for ax, panel in zip(axes, panels):
        _draw_curves(ax, panel, colours)
        markers = [s for s in panel["series"] if s["kind"] == "marker"]
        per_trial, mean_min = markers[0], markers[1]
        ax.scatter(per_trial["x"], per_trial["y"], c=colours[:len(per_trial["x"])], edgecolors="black",
                   s=40, zorder=3, label=_tex(per_trial["label"]))
        ax.plot(mean_min["x"], mean_min["y"], "s", color="black", markersize=9, zorder=4,
                label=_tex(f"mean curve at phi_R = {mean_min['x'][0]:.2f}: {mean_min['y'][0]:.2f} {panel['ylabel']}"))
        ax.set_ylim(bottom=0, top=1.3 * max(max(s["y"]) for s in panel["series"]))
        ax.legend(fontsize=8, ncol=3, loc="upper center")
    fig.suptitle(figs["fig7"]["title"], fontsize=11)
    paths["fig7"] = _save(fig, out / "fig7_distances.png")

    # Fig. 9
    (panel,) = figs["fig9"]["panels"]
    fig = Figure(figsize=(7.5, 4.6), dpi=_DPI, layout="constrained")
    ax = fig.subplots()
    trial_series = [s for s in panel["series"] if s["kind"] == "trial"]
    for k, s in enumerate(trial_series):
        n = len(s["y"])
        jitter = np.linspace(-0.18, 0.18, n) if n > 1 else np.zeros(1)
        ax.plot(np.asarray(s["x"]) + jitter, s["y"], "o", color=colours[k], markersize=3.5, alpha=0.7)
    means = [s for s in panel["series"] if s["kind"] == "marker"][0]
    ax.plot(means["x"], means["y"], "s", color="black", markerfacecolor="white", markersize=10,
            markeredgewidth=2, label="mean over the trial's points")
    for x, y in zip(means["x"], means["y"]):
        ax.annotate(f"{y:.2f}", (x, y), xytext=(12, 0), textcoords="offset points", va="center", fontsize=8)
    ax.set_xticks(means["x"])
    ax.set_xticklabels([s["label"] for s in trial_series])
    ax.set_xlim(min(means["x"]) - 0.6, max(means["x"]) + 0.8)
    ax.set_ylim(bottom=0)
    ax.set_ylabel(panel["ylabel"])
    ax.grid(alpha=0.3, axis="y")
    ax.legend(fontsize=8, loc="upper left")
    ax.set_title(figs["fig9"]["title"], fontsize=10)
    paths["fig9"] = _save(fig, out / "fig9_delta.png")

    # Fig. 4: one panel per trial, up to 3 per row
    panels = figs["fig4"]["panels"]
    ncols = min(3, len(panels))
    nrows = -(-len(panels) // ncols)
    fig = Figure(figsize=(4.2 * ncols, 3.4 * nrows + 0.6), dpi=_DPI, layout="constrained")
    axes = np.atleast_1d(fig.subplots(nrows, ncols, squeeze=False)).ravel()
    for k, (ax, panel) in enumerate(zip(axes, panels)):
        data, mean, window = panel["series"]
        ax.axhspan(window["y"][0], window["y"][1], color="#2ecc71", alpha=0.15, label=window["label"])
        ax.plot(data["x"], data["y"], ".", color=colours[k], markersize=3)
        ax.plot(mean["x"], mean["y"], label=_tex(mean["label"]), **{**_MEAN_STYLE, "linewidth": 1.4})
        ax.set_ylim(0, 1)
        ax.set_xlabel(panel["xlabel"])
        ax.set_ylabel(panel["ylabel"])
        ax.set_title(_tex(panel["title"]), fontsize=9)
        ax.grid(alpha=0.3)
    for ax in axes[len(panels):]:
        ax.set_visible(False)
    axes[0].legend(fontsize=7, loc="lower left")
    fig.suptitle(figs["fig4"]["title"], fontsize=11)
    paths["fig4"] = _save(fig, out / "fig4_phases.png")
    return paths


# ----------------------------------------------------------------- HTML
def _trials_text(ks) -> str:
    ks = list(ks)
    return ("trial " if len(ks) == 1 else "trials ") + ", ".join(map(str, ks))


def _differences(trials, summary) -> list[str]:
    """The honest section: where our synthetic numbers differ from the paper, and why.

    Every number is read from this run; the reasons name the phantom's settings
    (``heartreg/phantom/config.py``) that produce them.
    """
    s, p = summary, PAPER
    rows = [t.row for t in trials]
    items = []

    rms_lo, rms_hi = s["mean_rms_range_mm"]
    near = [r["trial"] for r in rows if abs(_wrap(r["rms_argmin_phase"] - r["phi_r_truth"])) <= TOL_PHASE_R]
    mirror = [r for r in rows if r["trial"] not in near
              and abs(_wrap(r["rms_argmin_phase"] - (1.0 - r["phi_r_truth"]))) <= TOL_PHASE_R]
    text = (
        f"<b>RMS error is far below the paper's ~{p['rms_mm']:g} mm.</b> The mean curve runs from "
        f"{rms_lo:.2f} to {rms_hi:.2f} mm over phi_R. The map is segmented from a CT whose heart shape is "
        "exact (only voxel noise and partial volume), the robot's points move exactly as the phantom's "
        "analytic surface does, and the tracker noise is 0.2 mm; the paper's 2 mm also carries the "
        "segmentation error of a real heart, its change of shape with the robot in the pericardium and "
        "magnetic-tracker distortion. As in the paper, RMS (eq. 9) is no temporal metric: its minimum over "
        f"phi_R lies within 0.05 of the truth in {len(near)} of {len(rows)} trials"
        + (f" ({_trials_text(near)})" if near else "")
    )
    if mirror:
        lo = min(r["rms_argmin_phase"] for r in mirror)
        hi = max(r["rms_argmin_phase"] for r in mirror)
        text += (
            f" and at the mirror phase 1 - phi_R* in {len(mirror)} ({lo:.2f}–{hi:.2f}). Our curves are not "
            "flat but have two near-equal minima: the phantom's only respiratory change of shape is the "
            "heartbeat's amplitude modulation 1 + 0.2 cos(2 pi phi_R), the same at phi_R and 1 - phi_R; the "
            "rest of its respiratory motion is rigid, which ICP absorbs."
        )
    else:
        text += "."
    items.append(text)

    hits = [r for r in rows if r["phi_r_within"]]
    text = (
        f"<b>The minimum translation distance ({s['mean_curve_min_translation_mm']:.1f} mm on the mean curve, "
        f"at phi_R {s['mean_curve_min_phase']:.2f}; paper {p['mean_min_translation_mm']} mm at "
        f"{p['mean_min_translation_phase']}) is set by construction</b>: each preset shifts the fiducials "
        "against the heart by 8–11 mm (fiducial_shift_mm), the CT-to-surgery error the paper's seed carried; "
        f"T0's error against the truth averages {s['mean_t0_error_mm']:.1f} mm. The agreement with 9.9 mm "
        "echoes the presets, it measures nothing physical."
    )
    if hits:
        gap = max(abs(r["min_translation_mm"] - r["t0_error_mm"]) for r in hits)
        text += (
            f" Where phi_R* is right, the minimum equals T0's true error to within {gap:.2f} mm: eq. 10 "
            "measures the fiducial registration's error, as the paper says of its Fig. 6."
        )
    items.append(text)

    text = (
        f"<b>The rotation distance at the minimum is {s['mean_curve_rotation_at_min_deg']:.1f}° on the mean "
        f"curve (paper {p['mean_rotation_at_min_deg']}°)</b>: the presets turn the fiducials against the heart "
        f"by only 2–3° (fiducial_shift_deg; T0's rotation error against the truth averages "
        f"{s['mean_t0_error_deg']:.1f}°), so there is little rotation to undo; the paper's 8.2° came from real "
        f"CT-to-surgery changes. ICP undoes it: the final rotation error averages {s['mean_final_error_deg']:.2f}°. "
        f"The static (mean-position) registration's averages {s['mean_static_error_deg']:.1f}°, more than T0's; "
        "a plausible cause, not isolated here, is the heartbeat's twist (apex +7°, base -4°) in the mean "
        "positions, which a rigid fit to the diastolic map turns into a rotation."
    )
    items.append(text)

    if s["sweep_unconverged"] or s["final_icp_unconverged"]:
        text = (
            f"<b>ICP stopped at its iteration limit at {s['sweep_unconverged']} of the {s['sweep_phases']} "
            "swept respiration phases</b> (column sweep_unconverged)"
            + (f" and in the final registration of {_trials_text(s['final_icp_unconverged'])}"
               if s["final_icp_unconverged"] else "")
            + ", and the rotation curves of Figs. 6B and 7B jump between some neighbouring phases while the "
            "translation distance that eq. 10 reads moves much less. The final ICP's weakest direction is a "
            f"turn about the heart's long axis (z-rotation component {s['mean_icp_weak_long_axis']:.2f} of the "
            "unit vector on average, registration.json icp.weakest_direction): the phantom's cross-sections are "
            "smooth ellipses, so that turn costs the fit little, the likely place where ICP creeps."
        )
        items.append(text)

    text = (
        f"<b>Mean delta {s['mean_delta_mm']:.2f} mm (per trial {s['mean_delta_range_mm'][0]:.2f}–"
        f"{s['mean_delta_range_mm'][1]:.2f}; paper {p['mean_delta_mm']} mm, "
        f"{p['mean_delta_range_mm'][0]}–{p['mean_delta_range_mm'][1]}).</b> The mean matches, the spread "
        "between trials is narrower: every preset has the same heart, the same breathing amplitudes (10 mm "
        "superior-inferior, 5 mm anterior-posterior) and the same beat, and differs only in rates, frame angles, "
        "point count and fiducial shift, while the paper's pigs differed in all of it. Against the truth the "
        f"static registration errs by {s['mean_static_error_mm']:.2f} mm on average and the spatiotemporal one "
        f"by {s['mean_final_error_mm']:.2f} mm, errors the paper could not measure."
    )
    items.append(text)

    miss = [r for r in rows if not r["phi_r_within"]]
    if miss:
        worse = [r for r in miss if r["final_error_mm"] > r["static_error_mm"]]
        items.append(
            "<b>Misses of phi_R*:</b> "
            + "; ".join(f"trial {r['trial']}: {_esc(r['miss_reason'])}" for r in miss)
            + ". Trial 4's preset puts its fiducial error along the respiratory path by design, to play the "
            "paper's one miss in six; the other presets err left-right, across the path."
            + "".join(f" In trial {r['trial']} the miss leaves the spatiotemporal registration worse than the "
                      f"static one ({r['final_error_mm']:.2f} vs {r['static_error_mm']:.2f} mm)." for r in worse)
        )
    else:
        items.append("<b>No trial missed phi_R*</b> (the paper had one miss in six); trial 4's preset is "
                     "meant to, so a change in the registration or the phantom has moved it.")
    edge = [r for r in rows if r["phi_r_within"] and abs(r["phi_r_error"]) >= TOL_PHASE_R - 0.01 - 1e-9]
    if edge:
        items.append(
            "<b>At the edge of the band:</b> "
            + "; ".join(f"trial {r['trial']} (phi_R* {r['phi_r']:.2f}, error {r['phi_r_error']:+.2f})" for r in edge)
            + " counts as near the truth with the inclusive ±0.05 of the sweep's 0.01 grid; the paper's "
            "'approximately 0.3' gives no tolerance."
        )

    phi_c = s["phi_c_range"]
    items.append(
        f"<b>Image phase phi_C* {phi_c[0]:.3f}–{phi_c[1]:.3f} (paper 0.61–0.67).</b> The phantom gates at the "
        "paper's target 0.7 (gating_target_phase) with a little heart-rate variability, so its slices land near "
        "0.7; the paper's scans landed earlier than their target. Table 1's image phases are informative only."
    )
    items.append(
        "<b>Heart-frame Euler angles match the paper's because the presets are Table 1</b>: the fitted frame's "
        f"long axis is within {s['mean_frame_z_error_deg']:.2f}° of the phantom's on average. The phantom's "
        "heart is a smooth prolate half-spheroid capped by a superellipsoid, an easier shape for the recursive "
        "ellipse fit than a real heart with its atria and vessels."
    )
    items.append(
        "<b>Heart and respiration rates</b> are the presets' (Table 1), measured back from the session's ECG "
        "and flows; the paper's were measured on the animals."
    )
    return items


def _esc(text: str) -> str:
    return html.escape(str(text))


def _html(trials, summary, figs_paths, *, size, seed, command, timings) -> str:
    import base64

    from heartreg.report_html import html_table

    ha, ra = _table_a(trials)
    hb, rb = _table_b(trials, summary)
    rb = [[c.replace("**", "") for c in r] for r in rb]
    parts = [
        "<!doctype html><html><head><meta charset='utf-8'><title>heartreg: Wood et al. 2018 reproduced</title>"
        f"<style>{_STYLE}</style></head><body>",
        "<h1>Wood et al. 2018 reproduced on the phantom</h1>",
        "<p>The paper's experiment (sections 2.2.2, 2.3 and 3) run on the six phantom presets "
        "<code>wood2018-trial1</code>…<code>trial6</code>, which carry Table 1's settings. "
        f"Phantom size <code>{size}</code>, seed {seed}"
        + (f"; command <code>{_esc(command)}</code>" if command else "") + ".</p>",
        "<h2>Table 1 beside the paper</h2>",
        html_table(ha, ra),
        "<h2>Registration beside the paper</h2>",
        "<p class='note'>phi_R* by eq. 10; distances from the fiducial registration T0 at the surface centroid; "
        "delta = static vs spatiotemporal surface point; errors against the phantom's truth "
        "(translation at the heart origin).</p>",
        html_table(hb, rb),
        "<h2>Where our synthetic numbers differ from the paper and why</h2>",
        "<ul>" + "".join(f"<li>{item}</li>" for item in _differences(trials, summary)) + "</ul>",
        "<h2>Figures</h2>",
    ]
    captions = {
        "fig2": "Fig. 2: RMS error across (A) cardiac and (B) respiration phase, all trials; mean dashed.",
        "fig4": "Fig. 4: cardiac phase per CT slice, per trial; motion-free window shaded.",
        "fig6": "Fig. 6: registration parameters across respiration phase (A translation, B rotation); mean dashed.",
        "fig7": "Fig. 7: translation and rotation distance from T0; dots at each trial's phi_R*, square at "
                "the mean curve's minimum.",
        "fig9": "Fig. 9: delta per point per trial (dots) and the trial's mean (square).",
    }
    for name in ("fig2", "fig6", "fig7", "fig9", "fig4"):
        data = base64.b64encode(Path(figs_paths[name]).read_bytes()).decode("ascii")
        parts.append(f'<figure><img alt="{name}" src="data:image/png;base64,{data}">'
                     f'<figcaption class="note">{_esc(captions[name])}</figcaption></figure>')
    parts.append("<p class='note'>Per-trial outputs: trialN/run/report.html. Times (s): "
                 + ", ".join(f"{k} {v:.1f}" for k, v in timings.items()) + ".</p></body></html>")
    return "\n".join(parts) + "\n"


def _run_trial(k, trial_dir, *, size, seed, n_points, phase_step, progress, say) -> TrialResult:
    """Make (or reuse) trial ``k``'s phantom case, run the pipeline on it, write ``trial.json``."""
    from heartreg.demo import truth_rows as make_truth_rows
    from heartreg.pipeline import run_pipeline

    preset = f"wood2018-trial{k}"
    t = time.perf_counter()
    truth, reused = _ensure_case(trial_dir / "case", preset, size, seed, n_points, progress)
    t_phantom = time.perf_counter() - t
    say(f"phantom {preset} {'reused' if reused else 'written'} ({t_phantom:.1f} s); running the pipeline")
    t = time.perf_counter()
    run = run_pipeline(trial_dir / "case" / "ct", trial_dir / "case" / "session", trial_dir / "run",
                       phase_step=phase_step, overwrite=True, progress=progress)
    t_pipeline = time.perf_counter() - t
    truth_rows = make_truth_rows(run, truth)
    timings = {"phantom": t_phantom, "pipeline": t_pipeline, **run.timings_s}
    del run  # the volume and the mesh: free them before the next trial
    extra = {"case_reused": reused, "time_phantom_s": t_phantom, "time_pipeline_s": t_pipeline}
    result = _trial_result(k, trial_dir, truth, truth_rows, extra, timings)
    write_text_atomic(trial_dir / "trial.json", json.dumps(
        {"row": {key: _plain(v) for key, v in result.row.items()}, "truth_rows": result.truth_rows,
         "timings_s": result.timings_s}, indent=1) + "\n")
    r = result.row
    say(f"phi_R* {r['phi_r']:.2f} (truth {r['phi_r_truth']:.2f}), min translation {r['min_translation_mm']:.2f} mm, "
        f"mean delta {r['mean_delta_mm']:.2f} mm, pipeline {t_pipeline:.1f} s")
    return result


def _load_trial(k, trial_dir, *, size, seed, n_points) -> TrialResult:
    """Trial ``k``'s results from an earlier run's files (``trial.json`` and the pipeline outputs)."""
    trial_json = trial_dir / "trial.json"
    truth_path = trial_dir / "case" / "truth.json"
    if not trial_json.exists() or not truth_path.exists():
        raise ReproduceError(
            f"no finished run of trial {k} in {trial_dir} (trial.json or case/truth.json missing); "
            "run the reproduction without report_only (--report-only) first"
        )
    truth = json.loads(truth_path.read_text())
    want = {"preset": f"wood2018-trial{k}", "size": size, "seed": seed}
    have = {key: truth.get(key) for key in want}
    if n_points is not None:
        want["n_points"], have["n_points"] = n_points, truth.get("config", {}).get("n_points")
    if have != want:
        raise ReproduceError(f"{trial_dir} holds a run of {have}, not {want}")
    saved = json.loads(trial_json.read_text())
    extra = {key: saved["row"][key] for key in ("case_reused", "time_phantom_s", "time_pipeline_s")}
    return _trial_result(k, trial_dir, truth, saved["truth_rows"], extra, saved["timings_s"])


# ----------------------------------------------------------------- driver
def reproduce(
    out_dir,
    *,
    size: str = "full",
    seed: int = 0,
    trials: Sequence[int] = TRIALS,
    n_points: int | None = None,
    phase_step: float = 0.01,
    command: str | None = None,
    rerun: bool = True,
    progress: bool = False,
    log: Callable[[str], None] | None = None,
) -> Reproduction:
    """Run the paper's experiment on the phantom presets and write the comparison.

    Parameters
    ----------
    out_dir : path
        Output folder (see the module docstring for its layout).
    size : {'full', 'sample'}
        Phantom CT grid: ``'full'`` is the paper's 512 x 512, 0.49 x 0.49 x 0.625 mm.
    seed : int
        Phantom seed, the same for every trial.
    trials : sequence of int
        Trials of Table 1 to run (1..6), in this order.
    n_points : int, optional
        Attachment points per session instead of the preset's (Table 1's) count.
    phase_step : float, cycles
        Step of the phase sweeps (0.01: the paper's 101 phases).
    command : str, optional
        The command line that asked for this, recorded in the outputs.
    rerun : bool
        Run the phantom (when its case is missing) and the pipeline.  False
        re-renders the tables, figures and page from an earlier run's files in
        ``out_dir`` without running anything.
    progress : bool
        Progress bars of the phantom and the pipeline on stderr.
    log : callable, optional
        Receives one line per step (the CLI prints it on stderr).

    Returns
    -------
    Reproduction

    Raises
    ------
    ReproduceError
        Unknown or repeated trials, a different phantom case in the way, or
        (``rerun=False``) no earlier run to read.
    """
    from heartreg.phantom.config import SIZES

    trials = [int(k) for k in trials]
    if not trials:
        raise ReproduceError("trials must name at least one of 1..6")
    bad = [k for k in trials if k not in PAPER_TABLE1]
    if bad or len(set(trials)) != len(trials):
        raise ReproduceError(f"trials must be distinct numbers among 1..6 (Table 1), got {trials}")
    if size not in SIZES:
        raise ReproduceError(f"size must be one of {sorted(SIZES)}, got {size!r}")
    say = log if log is not None else (lambda msg: None)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t_all = time.perf_counter()

    results = []
    for n, k in enumerate(trials, 1):
        trial_dir = out / f"trial{k}"
        if rerun:
            def step(msg, n=n, k=k):
                say(f"[trial {k}, {n}/{len(trials)}] {msg}")

            result = _run_trial(k, trial_dir, size=size, seed=seed, n_points=n_points, phase_step=phase_step,
                                progress=progress, say=step)
        else:
            result = _load_trial(k, trial_dir, size=size, seed=seed, n_points=n_points)
        results.append(result)

    summary = _summary(results)
    figs = figure_data(results)
    paths = {"figures_json": out / "figures.json"}
    write_text_atomic(paths["figures_json"], json.dumps(figs) + "\n")
    paths.update(_plot_figures(figs, out))
    timings = {"total": time.perf_counter() - t_all}
    timings.update({f"trial{t.trial}": t.timings_s["phantom"] + t.timings_s["pipeline"] for t in results})
    if not rerun:
        timings["trials (earlier run)"] = sum(t.timings_s["phantom"] + t.timings_s["pipeline"] for t in results)

    paths["csv"] = out / "reproduction.csv"
    write_text_atomic(paths["csv"], _csv_text(results))
    paths["markdown"] = out / "reproduction.md"
    write_text_atomic(paths["markdown"], _markdown(results, summary, size=size, seed=seed, command=command))
    paths["json"] = out / "reproduction.json"
    write_text_atomic(paths["json"], json.dumps({
        "format": "heartreg-reproduction",
        "version": 1,
        "command": command,
        "size": size,
        "seed": seed,
        "n_points": n_points,
        "phase_step": phase_step,
        "trials": [{k2: _plain(v) for k2, v in t.row.items()} for t in results],
        "columns": {k2: {"header": h, "meaning": m} for k2, h, m in COLUMNS},
        "summary": summary,
        "paper": {"table1": {str(k2): {"points": v[0], "heart_rate_hz": v[1], "resp_rate_hz": v[2],
                                       "image_phase": v[3], "euler_xyz_deg": list(v[4])}
                             for k2, v in PAPER_TABLE1.items()},
                  **{k2: (list(v) if isinstance(v, tuple) else v) for k2, v in PAPER.items()}},
        "timings_s": timings,
    }, indent=1) + "\n")
    timings["total"] = time.perf_counter() - t_all
    paths["html"] = out / "reproduction.html"
    write_text_atomic(paths["html"], _html(results, summary, paths, size=size, seed=seed, command=command,
                                           timings=timings))
    return Reproduction(out_dir=out, size=size, seed=seed, trials=tuple(results), summary=summary,
                        paths=paths, timings_s=timings)
