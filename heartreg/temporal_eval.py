"""``heartreg evaluate-temporal``: can the respiration phase be trusted? A grid of phantom cases.

Every case is a pure function of ``(preset, seed, phase_r)`` (:func:`run_case`):
the phantom writes the case with its CT breath-hold at ``phase_r`` into a
temporary folder, the library builds the model and registers the session, and
the result is set against the truth, for both estimators of phi_R*
(``shape``, the default of ``heartreg register``, and the paper's ``eq10``).
The grid (:func:`evaluate`) is the six ``wood2018-trial*`` presets x seeds,
with ``phase_r`` drawn per case away from the paper's 0.3 (:func:`true_phase`);
each case's row is kept in ``OUT/cases/`` so that a run resumes where it
stopped; the cases run on the batch machinery (``--workers``, ``--scheduler``:
a local Dask cluster or a running scheduler, one task and one record per
case)::

    OUT/cases/<preset>_s<seed>.json   one case: its row per estimator
    OUT/cases/<preset>_s<seed>.npz    its sweep's evidence: the shape estimator re-runs from it without
                                      ICP (:mod:`heartreg.temporal_evidence`, ``bench/temporal_rescore.py``)
    OUT/temporal_eval.csv             every case x estimator
    OUT/temporal_eval.md              the summary table (README, docs/reproduction.md)
    OUT/temporal_eval.json            the summary and the rows
    OUT/temporal_eval.png             true vs estimated phi_R* with intervals; T errors

The criteria (:data:`CRITERIA`): phi_R* within +-0.05 of the truth, the final
transform within 2 mm (mean displacement of the model's vertices) and 2 deg,
the 90 % interval covering the truth.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import tempfile
import time
from pathlib import Path
from collections.abc import Callable, Sequence

import numpy as np

from hrcore.errors import UsageError, read_json_object
from hrcore.figlayout import fixed_margins
from hrcore.geometry import apply_to_points
from hrcore.output import staged_output
from imaging.files import write_text_atomic
from registration.phase_estimate import wrap_phase

__all__ = ["GRID_PRESETS", "CRITERIA", "true_phase", "run_case", "summarize", "evaluate"]

GRID_PRESETS = tuple(f"wood2018-trial{k}" for k in range(1, 7))
#: phase tolerance (cycles), transform tolerances (mm, deg).
CRITERIA = {"phase": 0.05, "transform_mm": 2.0, "transform_deg": 2.0}
#: true phases are drawn at least this far (cycles) from the paper's 0.3.
AWAY_FROM = (0.3, 0.1)


def true_phase(preset: str, seed: int) -> float:
    """The case's CT breath-hold phase: uniform on [0, 1), at least 0.1 from 0.3, rounded to 0.01."""
    key = sum(ord(c) for c in preset)
    rng = np.random.default_rng([int(seed), key, 0x7E57])
    while True:
        phase = round(float(rng.uniform(0.0, 1.0)), 2) % 1.0
        if abs(wrap_phase(phase - AWAY_FROM[0])) >= AWAY_FROM[1]:
            return phase


def _transform_error(T, T_true, vertices):
    E = T @ np.linalg.inv(T_true)
    moved = apply_to_points(E, vertices)
    mean_mm = float(np.linalg.norm(moved - vertices, axis=1).mean())
    cos = np.clip((np.trace(E[:3, :3]) - 1) / 2, -1.0, 1.0)
    return mean_mm, float(np.degrees(np.arccos(cos)))


def run_case(preset: str, seed: int, phase_r: float, *, size: str = "sample", work_dir=None,
             slice_phases: bool | None = None, harmonics=None) -> dict:
    """One phantom case, registered by both estimators and scored against the truth.

    Parameters
    ----------
    preset : str
        A phantom preset.
    seed : int
    phase_r : float, cycles
        The CT's breath-hold respiration phase (the truth to recover).
    size : {"sample", "full"}
    work_dir : path, optional
        Where the temporary case folder goes (removed afterwards).
    slice_phases : bool, optional
        Predict each point at the cardiac phase of the CT slices it lies on
        (:mod:`registration.slice_phase`; the model carries them); False: every
        point at phi_C*; None (default): what ``heartreg register`` does
        (``RegistrationOptions.slice_phases``).
    harmonics : Harmonics or (Hc, Hr, Hmc, Hmr), optional
        Of the motion models; None (default): what ``heartreg register`` uses
        (``RegistrationOptions.harmonics``).

    Returns
    -------
    dict
        ``{"preset", "seed", "phase_true", "estimates": [row per estimator]}``;
        each row: phase, error, interval, covered, decided, width, transform
        errors (mm, deg) and the transform's 90 % radius.
    """
    from modeling import build_heart_model
    from registration import read_session
    from registration.mesh_bias import curvature_at_points, vertex_mean_curvature
    from registration.pipeline import register_session
    from modeling.slice_phases import SlicePhases

    from heartreg.phantom.generate import make_phantom
    from heartreg.pipeline import open_study

    tmp = Path(tempfile.mkdtemp(prefix=".temporal-case-", dir=work_dir))
    try:
        truth = make_phantom(tmp / "case", preset=preset, size=size, seed=int(seed),
                             image_resp_phase=float(phase_r))
        volume, report = open_study(tmp / "case" / "ct")
        build = build_heart_model(volume, cardiac_phase=report.volume_cardiac_phase, cardiac_phase_source=report.source,
                                  slice_phases=SlicePhases.from_report(report, volume.T_patient_from_voxel),
                                  target_faces=20000, expected_fiducials=9)
        del volume
        session = read_session(tmp / "case" / "session")
        options = {} if slice_phases is None else {"slice_phases": bool(slice_phases)}
        if harmonics is not None:
            options["harmonics"] = harmonics
        result = register_session(build.model, session, cardiac_sweep=False, **options)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    model = build.model
    T_true = model.T_heart_from_patient @ np.asarray(truth["T_patient_from_probe"])
    vertices = np.asarray(model.mesh.vertices)
    sweep = result.respiration_sweep
    rows = []
    for est in result.phase_estimates:
        t_mm, t_deg = _transform_error(sweep.T_heart_from_probe[est.index], T_true, vertices)
        err = float(wrap_phase(est.respiration_phase - phase_r))
        rows.append({
            "estimator": est.method,
            "phase": est.respiration_phase,
            "phase_error": err,
            "interval_low": float(est.interval[0]),
            "interval_high": float(est.interval[1]),
            "interval_width": est.width,
            "covered": est.contains(phase_r),
            "decided": est.decided,
            "transform_mm": t_mm,
            "transform_deg": t_deg,
            "transform_90_mm": est.transform_mm,
            "phase_ok": abs(err) <= CRITERIA["phase"] + 1e-9,
            "transform_ok": t_mm <= CRITERIA["transform_mm"] and t_deg <= CRITERIA["transform_deg"],
        })
    t0_mm, t0_deg = _transform_error(np.asarray(result.T0_heart_from_probe), T_true, vertices)
    shape = result.phase_estimates[0] if result.phase_estimates[0].method == "shape" else result.phase_estimates[1]
    evidence = {
        **_trace_evidence(model, session, sweep.phases),
        "phases": sweep.phases,
        "points_map_mm": np.asarray(result.points_probe_mm) @ np.asarray(result.T_heart_from_probe)[:3, :3].T
        + np.asarray(result.T_heart_from_probe)[:3, 3], "distances_mm": sweep.distances_mm, "signed_distances_mm": sweep.signed_distances_mm, "T_heart_from_probe": sweep.T_heart_from_probe,
        # the map's curvature at the registered points (registration/mesh_bias.py), for re-scoring
        "curvature_per_mm": curvature_at_points(
            np.asarray(result.points_probe_mm)[None], np.asarray(result.T_heart_from_probe)[None], vertices,
            vertex_mean_curvature(vertices, model.mesh.faces))[0],
        "cost_fiducial": shape.cost_fiducial, "cost_heart": shape.cost_heart, "T_true": T_true,
        "vertices_mm": vertices[:: max(1, vertices.shape[0] // 2000)], "pivot_mm": sweep.pivot_mm,
        # what register_session gives estimate_phase and what the rows are scored on, exactly
        "mean_points_map_mm": apply_to_points(np.asarray(result.T0_heart_from_probe),
                                              np.asarray(result.mean_points_probe_mm)),
        "vertices_all_mm": vertices,
        "fiducials_probe_mm": np.asarray(session.fiducials_probe_mm), "fiducials_heart_mm": model.fiducials_heart_mm,
    }
    h = result.parameters["harmonics"]
    return {"preset": preset, "seed": int(seed), "phase_true": float(phase_r), "size": size,
            "harmonics": [h["cardiac"], h["respiratory"], h["coupled_cardiac"], h["coupled_respiratory"]],
            "T0_mm": t0_mm, "T0_deg": t0_deg, "fre_mm": result.fre_mm,
            "phase_c": float(model.cardiac_phase), "phase_c_true": float(truth["cardiac_phase"]), "estimates": rows, "_evidence": evidence}


def _trace_evidence(model, session, phases) -> dict:
    """The traced staples' fit residuals over the sweep (to re-score an estimator offline)."""
    from registration.fiducial import register_fiducials
    from registration.pipeline import _trace_curve

    if session.fiducial_trace is None:
        return {}
    fid = register_fiducials(session.fiducials_probe_mm, model.fiducials_heart_mm)
    curve = _trace_curve(session.fiducial_trace, model.fiducials_heart_mm, phases, fid.order)
    return {"fiducial_residuals_mm": curve.residuals_mm, "fiducial_trace_rms_mm": curve.trace_rms_mm,
            "fiducial_curve_T": curve.T0_heart_from_probe, "fiducial_curve_source_mm": curve.positions_probe_mm,
            "fiducial_curve_n_samples": curve.n_samples}


def summarize(cases: Sequence[dict]) -> dict:
    """Per estimator: cases, share within each criterion, interval coverage and width."""
    out = {}
    methods = sorted({r["estimator"] for c in cases for r in c["estimates"]}, key=lambda m: m != "shape")
    for method in methods:
        rows = [r for c in cases for r in c["estimates"] if r["estimator"] == method]
        n = len(rows)
        out[method] = {
            "cases": n,
            "phase_within": sum(r["phase_ok"] for r in rows) / n,
            "transform_within": sum(r["transform_ok"] for r in rows) / n,
            "coverage": sum(r["covered"] for r in rows) / n,
            "median_width": float(np.median([r["interval_width"] for r in rows])),
            "undecided": sum(not r["decided"] for r in rows),
            "median_phase_error": float(np.median([abs(r["phase_error"]) for r in rows])),
            "median_transform_mm": float(np.median([r["transform_mm"] for r in rows])),
            "median_transform_deg": float(np.median([r["transform_deg"] for r in rows])),
        }
    return out


def _table(summary: dict, n_cases: int, size: str) -> str:
    names = {"shape": "shape (default)", "eq10": "eq. 10 (paper)"}
    lines = [
        (f"| estimator ({n_cases} cases, {size}) | phi_R* within ±0.05 | final T within 2 mm and 2° "
         "| 90 % interval covers truth | median interval width | undecided | median phase error "
         "| median T error |"),
        "|---|---|---|---|---|---|---|---|",
    ]
    for method, s in summary.items():
        lines.append(
            f"| {names.get(method, method)} | {100 * s['phase_within']:.0f} % | {100 * s['transform_within']:.0f} % "
            f"| {100 * s['coverage']:.0f} % | {s['median_width']:.2f} | {s['undecided']} "
            f"| {s['median_phase_error']:.3f} | {s['median_transform_mm']:.2f} mm, {s['median_transform_deg']:.2f}° |"
        )
    lines.append("")
    lines.append("Targets: ≥ 90 % within ±0.05; ≥ 95 % within 2 mm and 2°; coverage 85–95 %.")
    return "\n".join(lines) + "\n"


def _figure(cases, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.6))
    colors = {"shape": "tab:blue", "eq10": "tab:orange"}
    ax = axes[0]
    for method, dx in (("eq10", 0.004), ("shape", -0.004)):
        rows = [(c["phase_true"], r) for c in cases for r in c["estimates"] if r["estimator"] == method]
        if not rows:
            continue
        x = np.array([t for t, _ in rows]) + dx
        y = np.array([t + r["phase_error"] for t, r in rows])
        lo = np.array([-wrap_phase(r["interval_low"] - r["phase"]) for _, r in rows])
        hi = np.array([wrap_phase(r["interval_high"] - r["phase"]) for _, r in rows])
        lo, hi = np.abs(lo), np.abs(hi)
        ax.errorbar(x, y, yerr=[lo, hi], fmt="o", ms=3, lw=0.8, color=colors[method], alpha=0.8,
                    label=f"{method} (90 % interval)")
    ax.plot([0, 1], [0, 1], "k-", lw=0.8)
    ax.fill_between([0, 1], [-0.05, 0.95], [0.05, 1.05], color="0.85", zorder=0, label="±0.05")
    ax.set_xlim(0, 1)
    ax.set_ylim(-0.1, 1.1)
    ax.set_xlabel("true phi_R* (CT breath-hold)")
    ax.set_ylabel("estimated phi_R* (unwrapped about the truth)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    ax = axes[1]
    for method in ("shape", "eq10"):
        rows = [r for c in cases for r in c["estimates"] if r["estimator"] == method]
        if rows:
            ax.scatter([r["transform_mm"] for r in rows], [r["transform_deg"] for r in rows], s=12,
                       color=colors[method], label=method)
    ax.axvline(2.0, color="k", lw=0.8)
    ax.axhline(2.0, color="k", lw=0.8)
    ax.set_xscale("symlog", linthresh=1.0)
    ax.set_xlim(0.0, max(10.0, 1.2 * ax.get_xlim()[1]))
    ax.set_xticks([t for t in (0, 0.5, 1, 2, 5, 10, 20, 50) if t <= ax.get_xlim()[1]])
    ax.xaxis.set_major_formatter("{x:g}")
    ax.set_ylim(bottom=0.0)
    ax.set_xlabel("final T: mean vertex displacement (mm)")
    ax.set_ylabel("final T: rotation (deg)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fixed_margins(fig, left_in=0.7, right_in=0.15, bottom_in=0.55, top_in=0.15, wspace_in=0.85)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def evaluate(
    out_dir,
    *,
    presets: Sequence[str] = GRID_PRESETS,
    seeds: Sequence[int] = (1, 2, 3, 4, 5, 6),
    size: str = "sample",
    harmonics=None,
    run: bool = True,
    workers: int | None = 0,
    scheduler: str | None = None,
    memory_limit: str | None = None,
    progress: bool = False,
    say: Callable[[str], None] = lambda msg: None,
) -> dict:
    """Run (or resume) the grid and write the table and the figure.

    Parameters
    ----------
    out_dir : path
    presets, seeds : sequences
        The grid; each case's true phase is :func:`true_phase` of (preset, seed).
    size : {"sample", "full"}
    harmonics : Harmonics or (Hc, Hr, Hmc, Hmr), optional
        Of the motion models (``--harmonics``); None: ``heartreg register``'s
        default.  Cases already in ``out_dir/cases`` are kept as they are
        (each records its harmonics): use a new ``out_dir`` for other harmonics.
    run : bool
        False: summarize the cases already in ``out_dir/cases`` only.
    workers : int or None
        0 (default): the cases run one by one in this process.  Otherwise on
        the batch machinery (:func:`heartreg.batch.open_client`,
        :func:`heartreg.batch.run_tasks`): a local Dask cluster of this many
        worker processes (None: the usable cores), or ``scheduler``'s.
    scheduler : str, optional
        Address of a running Dask scheduler.
    memory_limit : str, optional
        Memory limit of each local worker (the batch default).
    progress : bool
        A progress bar on stderr (Dask runs).
    say : callable
        Progress messages: a line per finished case, one per failed case.

    Returns
    -------
    dict
        ``{"summary", "cases", "paths", "table", "failed"}``; ``failed`` maps a
        case's name to its one-line error (a failed case is left out of the
        table and runs again next time).
    """
    from registration.options import RegistrationOptions

    if harmonics is not None:  # checked (a UsageError naming --harmonics) before any case runs
        harmonics = dataclasses.astuple(RegistrationOptions(harmonics=harmonics).harmonics)
    wanted = list(harmonics if harmonics is not None else dataclasses.astuple(RegistrationOptions().harmonics))
    seeds = [int(s) for s in seeds]
    if not seeds or min(seeds) < 1:
        raise UsageError(f"seeds must be 1 or more (--seeds N runs seeds 1..N), got {seeds}")
    if workers is not None and int(workers) < 0:
        raise UsageError(f"workers must be 0 (in this process) or more (--workers), got {workers}")
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise UsageError(f"{out} exists and is not a folder; choose an output folder (-o)")
    if out.is_dir() and any(out.iterdir()) and not ((out / "cases").is_dir() or (out / "temporal_eval.json").is_file()):
        raise UsageError(f"{out} holds other files, not an evaluation (no cases/ folder): choose a new or empty "
                         "output folder (-o)")
    if not run and not (out / "cases").is_dir():
        raise UsageError(f"no case in {out / 'cases'} yet: run without --report-only first")
    todo, have = [], {}
    for preset in presets:
        for seed in seeds:
            path = out / "cases" / f"{preset}_s{seed}.json"
            if path.exists():
                have[path] = _read_case(path)
                if have[path].get("size", size) != size:
                    raise UsageError(f"{out} holds cases of size {have[path]['size']!r}, not {size!r} (--size): "
                                     "choose another output folder for another size")
                if list(have[path].get("harmonics", wanted)) != wanted:
                    raise UsageError(f"{out} holds cases fitted with harmonics {have[path]['harmonics']}, not {wanted} "
                                     "(--harmonics): choose another output folder for other harmonics")
            else:
                todo.append((preset, int(seed), true_phase(preset, int(seed)), size, harmonics))
    failed = {}
    created = [p for p in (out, out / "cases") if not p.exists()]
    try:
        if run and todo:
            _run_cases(out, todo, failed, workers=workers, scheduler=scheduler, memory_limit=memory_limit,
                       progress=progress, say=say)
    finally:
        # a case's work folder left by a worker stopped mid-case (Ctrl-C kills it before its own clean-up)
        for stale in out.glob(".temporal-case-*"):
            shutil.rmtree(stale, ignore_errors=True)
        # a run that wrote no case (refused, interrupted) leaves no empty folder behind
        for folder in reversed(created):
            if folder.is_dir() and not any(folder.iterdir()):
                folder.rmdir()
    cases = []
    for preset in presets:
        for seed in seeds:
            path = out / "cases" / f"{preset}_s{seed}.json"
            if path.exists():
                cases.append(have.get(path) or _read_case(path))
    if not cases:
        return {"summary": {}, "cases": [], "paths": {}, "table": "", "failed": failed}
    summary = summarize(cases)
    table = _table(summary, len(cases), size)
    names = {"md": "temporal_eval.md", "json": "temporal_eval.json", "csv": "temporal_eval.csv",
             "png": "temporal_eval.png"}
    header = ["preset", "seed", "phase_true", "T0_mm", "estimator", "phase", "phase_error", "interval_low",
              "interval_high", "interval_width", "covered", "decided", "transform_mm", "transform_deg",
              "transform_90_mm", "phase_ok", "transform_ok"]
    lines = [",".join(header)]
    for c in cases:
        for r in c["estimates"]:
            row = {**c, **r}
            lines.append(",".join(str(int(v)) if isinstance(v, bool) else
                                  (f"{v:.6g}" if isinstance(v, float) else str(v)) for v in (row[h] for h in header)))
    # the four written first, then each moved into place (a failure while writing them leaves the earlier four)
    with staged_output(out, parts=tuple(names.values()), overwrite=True, what="evaluation folder") as stage:
        write_text_atomic(stage / names["md"], table)
        write_text_atomic(stage / names["json"], json.dumps({"summary": summary, "criteria": CRITERIA,
                                                             "cases": cases}, indent=1) + "\n")
        write_text_atomic(stage / names["csv"], "\n".join(lines) + "\n")
        _figure(cases, stage / names["png"])
    paths = {key: out / name for key, name in names.items()}
    return {"summary": summary, "cases": cases, "paths": paths, "table": table, "failed": failed}


def _run_cases(out: Path, todo, failed: dict, *, workers, scheduler, memory_limit, progress, say) -> None:
    """Run the cases ``todo`` into ``out/cases`` (here, or on Dask workers); ``failed`` gets each failure.
    The folders it makes and leaves empty (a cluster that would not start) :func:`evaluate` removes."""
    (out / "cases").mkdir(parents=True, exist_ok=True)
    if workers == 0 and scheduler is None:
        for k, args in enumerate(todo, 1):
            t = time.perf_counter()
            case = _run_and_save(out, *args)
            say(f"[{k}/{len(todo)}] {_case_line(case)} ({time.perf_counter() - t:.0f} s)")
        return
    from heartreg.batch.cluster import DEFAULT_MEMORY_LIMIT, TaskFailure, open_client, run_tasks

    with open_client(workers=workers, scheduler=scheduler, memory_limit=memory_limit or DEFAULT_MEMORY_LIMIT,
                     log=say) as client:
        names = [f"{a[0]}_s{a[1]}" for a in todo]
        for k, (name, value) in enumerate(run_tasks(client, _case_task, todo, names=names,
                                                    args=(str(out.resolve()),), progress=progress,
                                                    desc="temporal cases"), 1):
            if isinstance(value, TaskFailure):
                failed[name] = value.error
                say(f"[{k}/{len(todo)}] {name} FAILED: {value.error}")
            else:
                say(f"[{k}/{len(todo)}] {_case_line(value)}")


def _read_case(path: Path) -> dict:
    """One case's record in ``OUT/cases/``; one line naming it when it is damaged."""
    return read_json_object(path, keys=("preset", "seed", "estimates"), what="case record",
                            fix="delete it and run again (that case runs anew)")


def _case_line(case: dict) -> str:
    shape = case["estimates"][0]
    return (f"{case['preset']} seed {case['seed']}: truth {case['phase_true']:.2f}, {shape['estimator']} "
            f"{shape['phase']:.2f} [{shape['interval_low']:.2f}, {shape['interval_high']:.2f}], "
            f"T {shape['transform_mm']:.2f} mm")


def _case_task(args, out_dir: str) -> dict:
    """One case as a Dask task (:func:`heartreg.batch.run_tasks`): its record out, its files in ``out_dir``."""
    return _run_and_save(Path(out_dir), *args)


def _run_and_save(out: Path, preset, seed, phase_r, size, harmonics=None) -> dict:
    case = run_case(preset, seed, phase_r, size=size, work_dir=out, harmonics=harmonics)
    evidence = case.pop("_evidence")
    # the sweep's evidence, so that an estimator can be re-scored without re-running the case
    np.savez_compressed(out / "cases" / f"{preset}_s{seed}.npz", **evidence)
    write_text_atomic(out / "cases" / f"{preset}_s{seed}.json", json.dumps(case, indent=1) + "\n")
    return case
