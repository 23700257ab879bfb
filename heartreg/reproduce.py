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

import contextlib
import json
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from heartreg.batch.cluster import DEFAULT_MEMORY_LIMIT
from heartreg.demo import pose_error
from heartreg.phantom.config import PAPER_TABLE1
from heartreg.reproduce_results import (
    COLUMNS,
    PAPER,
    TOL_PHASE_R,
    ReproduceError,
    TrialResult,
    _summary,
    check_request,
    miss_reason,
    path_axis,
)
from hrcore.errors import read_json_object
from hrcore.output import clean_stale_staging, staged_output
from imaging.phase_io import read_phase_report
from modeling.model import read_model
from registration.phase_estimate import wrap_phase
from registration.report import read_registration

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
]

#: The paper's six porcine trials.
TRIALS = (1, 2, 3, 4, 5, 6)

#: The paper's table is reproduced under the paper's conditions: each staple
#: touched once (a format-1 session) with the chest wall still, so that T0's
#: error is the CT-to-surgery skin shift alone, as the paper's ~10 mm.  The
#: breathing chest and the fiducial traces are evaluated by
#: ``heartreg evaluate-temporal`` (:mod:`heartreg.temporal_eval`).
PAPER_CONDITIONS = {"chest_wall_ap_mm": 0.0, "fiducial_trace_breaths": 0.0}
#: ... and registered as the paper: eq. 10's phi_R*, the paper's harmonics
#: (5, 4, 2, 1), every point at the model's phi_C* (``RegistrationOptions`` fields).
PAPER_REGISTRATION = {"estimator": "eq10", "harmonics": (5, 4, 2, 1), "slice_phases": False}

#: What a trial writes into ``OUT_DIR/trialN`` beside its phantom case, staged and
#: moved in in this order: a trial is finished when its ``trial.json`` is there.
TRIAL_PARTS = ("run", "trial.json")
#: What the reproduction writes into ``OUT_DIR`` beside the trial folders.
REPORT_PARTS = ("figures.json", "fig2_rms.png", "fig4_phases.png", "fig6_parameters.png", "fig7_distances.png",
                "fig9_delta.png", "reproduction.csv", "reproduction.md", "reproduction.json", "reproduction.html")


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


# ----------------------------------------------------------------- per trial
def _ensure_case(case_dir: Path, preset: str, size: str, seed: int, n_points, progress: bool):
    """Make the phantom case, or reuse one with the same preset, size, seed and points."""
    from heartreg.phantom import make_phantom

    truth = _existing_case(case_dir, preset, size, seed, n_points)
    if truth is not None:
        return truth, True
    overrides = {} if n_points is None else {"n_points": n_points}
    overrides.update(PAPER_CONDITIONS)
    # no truth.json: anything else there is a half-written case, replace it
    truth = make_phantom(case_dir, preset=preset, size=size, seed=seed, progress=progress,
                         overwrite=True, **overrides)
    return truth, False


def _existing_case(case_dir: Path, preset: str, size: str, seed: int, n_points):
    """The truth of the phantom case in ``case_dir`` if it is the one asked for, None if there is none.

    Raises
    ------
    ReproduceError
        Another phantom case is there.
    """
    truth_path = case_dir / "truth.json"
    if truth_path.exists():
        truth = read_json_object(truth_path, what="phantom truth", error=ReproduceError,
                                 fix="delete that case folder and run again")
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
        return truth
    return None


def _trial_row(trial: int, files: dict, truth: dict, truth_rows: list) -> dict:
    """The table row of one trial from the pipeline's files (``files`` from :func:`_read_run`)."""
    from heartreg.phantom.config import PAPER_IMAGE_PHASE

    phases, model, reg, sweep = files["phases"], files["model"], files["registration"], files["sweep"]
    paper = PAPER_TABLE1[trial]
    preset = f"wood2018-trial{trial}"
    T = {"final": reg.T_heart_from_probe, "T0": reg.T0_heart_from_probe,
         "static": reg.static.T_static_heart_from_probe}

    T_true = model.T_heart_from_patient @ np.asarray(truth["T_patient_from_probe"])
    T_probe_from_heart = np.linalg.inv(T_true)
    origin_probe = T_probe_from_heart[:3, 3]  # the fitted heart origin, probe frame
    centroid_probe = (T_probe_from_heart @ np.append(sweep.pivot_mm, 1.0))[:3]
    _, final_mm, final_deg = pose_error(T["final"], T_true, origin_probe)
    _, static_mm, static_deg = pose_error(T["static"], T_true, origin_probe)
    # T0's error at the sweep's pivot, heart frame: the quantity eq. 10 measures
    t0_vec, t0_mm, t0_deg = pose_error(T["T0"], T_true, centroid_probe)
    locus = sweep.correction_translation_mm
    axis, path_mm = path_axis(locus)
    along = float(abs(t0_vec @ axis) / t0_mm) if t0_mm > 0 else 0.0

    by_name = {r[0]: r for r in truth_rows}
    fits = reg.point_fits
    e_fit = [float(x) for x in model.euler_xyz_deg]
    e_preset = [float(x) for x in truth["heart_euler_xyz_deg"]]
    phi_r_err = float(wrap_phase(reg.respiration_phase - truth["respiration_phase"]))
    i_rms = int(np.argmin(sweep.rms_mm))
    row = {
        "trial": trial,
        "points_used": reg.n_points,
        "points_excluded": len(reg.exclusions),
        "heart_rate_hz": float(np.mean([f.heart_rate_hz for f in fits])),
        "resp_rate_hz": float(np.mean([f.resp_rate_hz for f in fits])),
        "paper_heart_rate_hz": paper[1],
        "paper_resp_rate_hz": paper[2],
        "phi_c": float(phases.volume_cardiac_phase),
        "phi_c_truth": float(truth["cardiac_phase"]),
        "phi_c_paper": float(PAPER_IMAGE_PHASE.get(preset, paper[3])),
        "phase_source": phases.source,
        "euler_fit_a_deg": e_fit[0], "euler_fit_b_deg": e_fit[1], "euler_fit_g_deg": e_fit[2],
        "euler_preset_a_deg": e_preset[0], "euler_preset_b_deg": e_preset[1], "euler_preset_g_deg": e_preset[2],
        "euler_paper_a_deg": paper[4][0], "euler_paper_b_deg": paper[4][1], "euler_paper_g_deg": paper[4][2],
        "frame_z_error_deg": float(by_name["heart frame z axis (deg)"][1]),
        "phi_r": float(reg.respiration_phase),
        "phi_r_truth": float(truth["respiration_phase"]),
        "phi_r_error": phi_r_err,
        "phi_r_within": bool(abs(phi_r_err) <= TOL_PHASE_R + 1e-9),
        "min_translation_mm": float(reg.translation_distance_mm),
        "rotation_at_min_deg": float(reg.rotation_distance_deg),
        "rms_at_phi_r_mm": float(reg.rms_mm),
        "rms_min_mm": float(np.min(sweep.rms_mm)),
        "rms_max_mm": float(np.max(sweep.rms_mm)),
        "rms_argmin_phase": float(sweep.phases[i_rms]),
        "sweep_unconverged": int(np.count_nonzero(~sweep.converged)),
        "icp_weak_long_axis": float(abs(reg.icp.weakest_direction[2])),
        "icp_converged": bool(reg.icp.converged),
        "mean_delta_mm": float(reg.delta_static_mean_mm),
        "fre_mm": float(reg.fre_mm),
        "t0_error_mm": t0_mm,
        "t0_error_deg": t0_deg,
        "t0_error_along_path": along,
        "resp_path_mm": path_mm,
        "final_error_mm": final_mm,
        "final_error_deg": final_deg,
        "static_error_mm": static_mm,
        "static_error_deg": static_deg,
    }
    row["miss_reason"] = miss_reason(row)
    return row


def _read_run(run_dir: Path) -> dict:
    """The pipeline's output files that the reproduction reads."""
    reg = read_registration(run_dir / "registration")
    return {
        "phases": read_phase_report(run_dir / "phases"),
        "model": read_model(run_dir / "model"),
        "registration": reg,
        "sweep": reg.respiration_sweep,
        "cardiac_sweep": reg.cardiac_sweep,
    }


def _trial_result(trial: int, trial_dir: Path, truth: dict, truth_rows: list, extra: dict,
                  timings: dict) -> TrialResult:
    """One trial's results from its pipeline outputs in ``trial_dir/run``."""
    files = _read_run(trial_dir / "run")
    row = _trial_row(trial, files, truth, truth_rows)
    row.update(extra)
    reg, sweep, card = files["registration"], files["sweep"], files["cardiac_sweep"]
    empty = np.empty(0)
    return TrialResult(
        trial=trial,
        row=row,
        truth_rows=[tuple(_plain(v) for v in r) for r in truth_rows],
        phases_r=sweep.phases,
        phases_c=empty if card is None else card.phases,
        rms_r_mm=sweep.rms_mm,
        rms_c_mm=empty if card is None else card.rms_mm,
        translation_distance_mm=sweep.translation_distance_mm,
        rotation_distance_deg=sweep.rotation_distance_deg,
        correction_translation_mm=sweep.correction_translation_mm,
        correction_euler_xyz_deg=sweep.correction_euler_xyz_deg,
        delta_mm=reg.static.delta_mm,
        slice_position_mm=np.array([s.position_mm for s in files["phases"].slices]),
        slice_phase=files["phases"].phases,
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


# ----------------------------------------------------------------- tables
def _run_trial(k, trial_dir, *, size, seed, n_points, phase_step, progress, say) -> TrialResult:
    """Make (or reuse) trial ``k``'s phantom case, run the pipeline on it, write ``trial.json``."""
    from heartreg.demo import truth_rows as make_truth_rows
    from heartreg.pipeline import run_pipeline
    from registration.options import RegistrationOptions

    preset = f"wood2018-trial{k}"
    t = time.perf_counter()
    truth, reused = _ensure_case(trial_dir / "case", preset, size, seed, n_points, progress)
    t_phantom = time.perf_counter() - t
    say(f"phantom {preset} {'reused' if reused else 'written'} ({t_phantom:.1f} s); running the pipeline")
    t = time.perf_counter()
    # the run and trial.json staged beside the case, moved in at the end (trial.json last)
    with staged_output(trial_dir, parts=TRIAL_PARTS, overwrite=True, what="trial folder") as stage:
        run = run_pipeline(trial_dir / "case" / "ct", trial_dir / "case" / "session", stage / "run",
                           registration_options=RegistrationOptions(phase_step=phase_step, **PAPER_REGISTRATION),
                           progress=progress)
        t_pipeline = time.perf_counter() - t
        truth_rows = make_truth_rows(run, truth)
        timings = {"phantom": t_phantom, "pipeline": t_pipeline, **run.timings_s}
        del run  # the volume and the mesh: free them before the next trial
        extra = {"case_reused": reused, "time_phantom_s": t_phantom, "time_pipeline_s": t_pipeline}
        result = _trial_result(k, stage, truth, truth_rows, extra, timings)
        (stage / "trial.json").write_text(json.dumps(
            {"row": {key: _plain(v) for key, v in result.row.items()}, "truth_rows": result.truth_rows,
             "timings_s": result.timings_s}, indent=1) + "\n", encoding="utf-8")
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
    again = "run the reproduction again without report_only (--report-only)"
    truth = read_json_object(truth_path, what="phantom truth", error=ReproduceError, fix=again)
    want = {"preset": f"wood2018-trial{k}", "size": size, "seed": seed}
    have = {key: truth.get(key) for key in want}
    if n_points is not None:
        want["n_points"], have["n_points"] = n_points, truth.get("config", {}).get("n_points")
    if have != want:
        raise ReproduceError(f"{trial_dir} holds a run of {have}, not {want}")
    saved = read_json_object(trial_json, keys=("row", "truth_rows", "timings_s"), what="trial record",
                             error=ReproduceError, fix=again)
    try:
        extra = {key: saved["row"][key] for key in ("case_reused", "time_phantom_s", "time_pipeline_s")}
    except (KeyError, TypeError):
        raise ReproduceError(f"{trial_json}: its row lacks the trial's times; {again}") from None
    return _trial_result(k, trial_dir, truth, saved["truth_rows"], extra, saved["timings_s"])


def _trial_task(k: int, out_dir: str, size: str, seed: int, n_points, phase_step: float):
    """One trial as a Dask task: paths in, its result and log lines out (its warnings among them, one line each:
    the worker printed them as Python does, file, line and source, an audit)."""
    lines = []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("default")
        result = _run_trial(k, Path(out_dir) / f"trial{k}", size=size, seed=seed, n_points=n_points,
                            phase_step=phase_step, progress=False, say=lines.append)
    return result, lines + [f"warning: {' '.join(str(w.message).split())}" for w in caught]


def _run_trials(trials, out: Path, *, size, seed, n_points, phase_step, workers, scheduler, memory_limit,
                progress, say) -> list[TrialResult]:
    """Run the trials on the batch machinery (:mod:`heartreg.batch.cluster`), in parallel, in trial order."""
    from heartreg.batch.cluster import TaskFailure, open_client, run_tasks

    for k in trials:  # a foreign case in the way is refused before any cluster starts
        _existing_case(out / f"trial{k}" / "case", f"wood2018-trial{k}", size, seed, n_points)
    results = {}
    folders = [out / f"trial{k}" for k in trials] + [out]
    new = [f for f in folders if not f.exists()]
    try:
        with open_client(workers=workers, scheduler=scheduler, memory_limit=memory_limit, log=say) as client:
            for n, (name, value) in enumerate(run_tasks(
                    client, _trial_task, trials, names=[f"trial{k}" for k in trials],
                    args=(str(out.resolve()), size, seed, n_points, phase_step), progress=progress,
                    desc="trials"), 1):
                k = int(name.removeprefix("trial"))
                if isinstance(value, TaskFailure):
                    raise ReproduceError(f"trial {k} failed: {value.error}")
                result, lines = value
                for line in lines:
                    say(f"[trial {k}, {n}/{len(trials)} done] {line}")
                results[k] = result
    except BaseException:
        # the workers are gone (an interrupt stops them mid-write): their staging folders are those of killed
        # processes, removed now rather than by the next run, and so are the folders this run made for them
        for folder in folders:
            clean_stale_staging(folder)
        for folder in new:
            with contextlib.suppress(OSError):
                folder.rmdir()  # if empty
        raise
    return [results[k] for k in trials]


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
    workers: int | None = None,
    scheduler: str | None = None,
    memory_limit: str = DEFAULT_MEMORY_LIMIT,
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
        A progress bar of the trials on stderr.
    log : callable, optional
        Receives one line per step (the CLI prints it on stderr).
    workers, scheduler, memory_limit
        Where the trials run, in parallel: as ``heartreg batch``
        (:func:`heartreg.batch.open_client`): local worker processes (default
        the usable cores), or a running Dask scheduler's workers.

    Returns
    -------
    Reproduction

    Raises
    ------
    ReproduceError
        Unknown or repeated trials, a different phantom case in the way, or
        (``rerun=False``) no earlier run to read.
    """
    from heartreg.reproduce_figures import figure_data, plot_figures
    from heartreg.reproduce_report import csv_text, markdown, page_html

    trials = check_request(trials, size=size, seed=seed, n_points=n_points, phase_step=phase_step)
    say = log if log is not None else (lambda msg: None)
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ReproduceError(f"{out} exists and is not a folder; choose an output folder")
    t_all = time.perf_counter()

    if rerun:
        results = _run_trials(trials, out, size=size, seed=seed, n_points=n_points, phase_step=phase_step,
                              workers=workers, scheduler=scheduler, memory_limit=memory_limit,
                              progress=progress, say=say)
    else:
        results = [_load_trial(k, out / f"trial{k}", size=size, seed=seed, n_points=n_points) for k in trials]

    summary = _summary(results)
    figs = figure_data(results)
    timings = {"total": time.perf_counter() - t_all}  # one total for the JSON, the page and the summary printed
    timings.update({f"trial{t.trial}": t.timings_s["phantom"] + t.timings_s["pipeline"] for t in results})
    if not rerun:
        timings["trials (earlier run)"] = sum(t.timings_s["phantom"] + t.timings_s["pipeline"] for t in results)
    # the report files staged together and moved in at the end, the page last
    with staged_output(out, parts=REPORT_PARTS, overwrite=True, what="reproduction folder") as stage:
        staged = {"figures_json": stage / "figures.json"}
        staged["figures_json"].write_text(json.dumps(figs) + "\n", encoding="utf-8")
        staged.update(plot_figures(figs, stage))
        staged["csv"] = stage / "reproduction.csv"
        staged["csv"].write_text(csv_text(results), encoding="utf-8")
        staged["markdown"] = stage / "reproduction.md"
        staged["markdown"].write_text(markdown(results, summary, size=size, seed=seed, command=command),
                                      encoding="utf-8")
        staged["json"] = stage / "reproduction.json"
        staged["json"].write_text(json.dumps({
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
        }, indent=1) + "\n", encoding="utf-8")
        staged["html"] = stage / "reproduction.html"
        staged["html"].write_text(page_html(results, summary, staged, size=size, seed=seed, command=command,
                                            timings=timings), encoding="utf-8")
    paths = {key: out / p.name for key, p in staged.items()}
    return Reproduction(out_dir=out, size=size, seed=seed, trials=tuple(results), summary=summary,
                        paths=paths, timings_s=timings)
