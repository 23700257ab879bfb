"""``heartreg demo``: the whole chain on the bundled sample, against its truth.

The bundled ``sample_dicom/`` is a phantom case (CT study, ``qrs.csv``,
``truth.json``) written by ``heartreg phantom sample_dicom --preset
wood2018-trial1 --seed 0 --no-session``.  A case's own ``session/`` is used
when it has one; otherwise (the bundled sample: 55 MB of CSV, too large to
commit) the phantom writes it again from the configuration and seed its
``truth.json`` records (``config``: preset, points, respiration phase, chest
wall, ... as ``heartreg phantom`` was given them), so it is the session that
case would have had.  If the sample is not beside the package (an installed
wheel), the phantom writes the whole case first.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from hrcore.errors import UsageError
from hrcore.geometry import invert
from imaging.files import write_text_atomic

__all__ = ["SAMPLE_DIR", "format_table", "pose_error", "run_demo", "truth_rows"]

#: the committed sample, beside the package in a source checkout
SAMPLE_DIR = Path(__file__).resolve().parents[1] / "sample_dicom"

# tolerances of the stage issues (see the README's accuracy table)
TOL_PHASE_C = 0.005
TOL_PHASE_R = 0.05
TOL_Z_DEG, TOL_X_DEG = 2.0, 5.0
TOL_FIDUCIAL_MM = 0.35  # sample voxels are 1.95 x 1.95 x 2.5 mm (0.1 mm at full size; tests/modeling/test_build.py)
TOL_T_MM, TOL_T_DEG = 2.0, 2.0
TOL_SURFACE_MEAN_MM, TOL_SURFACE_P95_MM = 0.3, 0.8


def _angle_deg(a, b) -> float:
    return float(np.degrees(np.arccos(np.clip(np.dot(a, b), -1.0, 1.0))))


def pose_error(T, T_true, point_probe):
    """Error of ``T`` against ``T_true`` at a probe-frame point.

    Returns
    -------
    vector : (3,) float64, mm
        ``T p - T_true p``, heart frame.
    distance_mm, rotation_deg : float
        Its norm and the geodesic rotation between the two.
    """
    from registration import rotation_distance_deg

    p = np.append(point_probe, 1.0)
    vec = (T @ p - T_true @ p)[:3]
    return vec, float(np.linalg.norm(vec)), float(rotation_distance_deg(T, T_true))


def _rigid_error(T, T_true):
    """Translation error at the heart frame's origin (mm) and rotation error (deg)."""
    pivot = invert(T_true)[:3, 3]  # the heart origin in the probe frame
    _, distance_mm, rotation_deg = pose_error(T, T_true, pivot)
    return distance_mm, rotation_deg


def truth_rows(run, truth: dict) -> list[tuple]:
    """Recovered vs truth: ``(quantity, recovered, truth, error, tolerance, within)``."""
    from heartreg.phantom import heart_from_truth

    report, build, reg = run.phase_report, run.model_build, run.registration
    model = build.model
    rows = []
    err = report.volume_cardiac_phase - truth["cardiac_phase"]
    rows.append(("cardiac phase phi_C*", report.volume_cardiac_phase, truth["cardiac_phase"], err, TOL_PHASE_C,
                 abs(err) <= TOL_PHASE_C))
    err = reg.respiration_phase - truth["respiration_phase"]
    rows.append(("respiration phase phi_R*", reg.respiration_phase, truth["respiration_phase"], err, TOL_PHASE_R,
                 abs(err) <= TOL_PHASE_R))

    R = model.T_patient_from_heart[:3, :3]
    axes = np.asarray(truth["heart_axes_patient"])
    e, e_true = model.frame.euler_xyz_deg, truth["heart_euler_xyz_deg"]
    for k, name in enumerate("XYZ"):
        rows.append((f"heart frame Euler {name} (deg)", float(e[k]), float(e_true[k]), float(e[k] - e_true[k]), "", ""))
    z_err, x_err = _angle_deg(R[:, 2], axes[:, 2]), _angle_deg(R[:, 0], axes[:, 0])
    rows.append(("heart frame z axis (deg)", z_err, 0.0, z_err, TOL_Z_DEG, z_err <= TOL_Z_DEG))
    rows.append(("heart frame x axis (deg)", x_err, 0.0, x_err, TOL_X_DEG, x_err <= TOL_X_DEG))

    heart = heart_from_truth(truth)  # the case's own configuration (its respiration phase, anatomy, ...)
    vertices = model.mesh_patient().vertices
    d = np.abs(heart.surface_distance(vertices, truth["cardiac_phase"]))
    rows.append(("mesh to true surface, mean (mm)", float(d.mean()), 0.0, float(d.mean()), TOL_SURFACE_MEAN_MM,
                 float(d.mean()) <= TOL_SURFACE_MEAN_MM))
    p95 = float(np.percentile(d, 95))
    rows.append(("mesh to true surface, p95 (mm)", p95, 0.0, p95, TOL_SURFACE_P95_MM, p95 <= TOL_SURFACE_P95_MM))
    fid = np.linalg.norm(np.asarray(model.fiducials_patient_mm) - truth["fiducials_patient_mm"], axis=1)
    rows.append(("CT fiducials, worst of 9 (mm)", float(fid.max()), 0.0, float(fid.max()), TOL_FIDUCIAL_MM,
                 bool(fid.max() <= TOL_FIDUCIAL_MM)))

    T_true = model.T_heart_from_patient @ np.asarray(truth["T_patient_from_probe"])
    t_err, r_err = _rigid_error(reg.T_heart_from_probe, T_true)
    rows.append(("final T, translation at heart origin (mm)", t_err, 0.0, t_err, TOL_T_MM, t_err <= TOL_T_MM))
    rows.append(("final T, rotation (deg)", r_err, 0.0, r_err, TOL_T_DEG, r_err <= TOL_T_DEG))
    t0_err, r0_err = _rigid_error(reg.T0_heart_from_probe, T_true)
    rows.append(("fiducial seed T0, translation (mm)", t0_err, 0.0, t0_err, "", ""))
    rows.append(("fiducial FRE (mm)", reg.fre_mm, "", "", "", ""))
    ts_err, _ = _rigid_error(reg.static.T_static_heart_from_probe, T_true)
    rows.append(("static (mean-position) T, translation (mm)", ts_err, 0.0, ts_err, "> final", ts_err > t_err))
    rows.append(("delta static vs spatiotemporal, mean (mm)", reg.static.mean_delta_mm, "", "", "", ""))
    rows.append(("RMS point-to-surface at phi* (mm)", reg.rms_mm, "", "", "", ""))
    return rows


def format_table(rows) -> str:
    def fmt(v):
        if isinstance(v, bool):
            return "yes" if v else "NO"
        if isinstance(v, (float, np.floating)):
            return f"{v:.4g}"
        return str(v)

    header = ("quantity", "recovered", "truth", "error", "tolerance", "within")
    table = [header] + [tuple(fmt(v) for v in row) for row in rows]
    widths = [max(len(r[i]) for r in table) for i in range(len(header))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths)) for r in table]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def run_demo(out_dir, *, sample_dir=None, progress: bool = True) -> tuple[object, list]:
    """Run the chain on the bundled sample (or the phantom case ``sample_dir``) and compare with its truth.

    The case's own ``session/`` when it has one, else the session the phantom
    writes from ``truth.json``'s configuration and seed into
    ``OUT_DIR/session_case/``.  Returns the pipeline result and the recovered-vs-truth rows; writes
    ``OUT_DIR/demo_table.txt`` and ``OUT_DIR/demo.json`` beside the run's files.
    """
    from heartreg.phantom import make_phantom, write_session
    from heartreg.phantom.config import config_from_dict
    from heartreg.pipeline import run_pipeline
    from hrcore.errors import read_json_object
    from hrcore.output import check_output_path, staged_output

    if sample_dir is not None:  # checked before anything is created
        sample = Path(sample_dir)
        if not (sample / "truth.json").exists() or not (sample / "ct").is_dir():
            raise UsageError(
                f"--sample {sample} is not a phantom case (needs ct/ and truth.json, "
                "as 'heartreg phantom OUT' writes)"
            )
    out_dir = Path(out_dir)
    if sample_dir is None:  # the bundled sample, else one the demo writes into its folder
        sample = SAMPLE_DIR if (SAMPLE_DIR / "truth.json").exists() else out_dir / "sample"
    # the demo's own sample (also when given back as --sample) is part of its output, not an input
    own_sample = sample.resolve() == (out_dir / "sample").resolve()
    # an earlier demo's folder or a new one, never the sample's (nothing is written before this check)
    check_output_path(out_dir, inputs=() if own_sample else (sample,), what="demo folder", overwrite=True,
                      earlier=("demo.json", "session_case/recipe.json", "sample/truth.json"))
    if own_sample and not (sample / "truth.json").exists():
        print(f"bundled sample not found; writing it with the phantom into {sample}", file=sys.stderr)
        make_phantom(sample, preset="wood2018-trial1", seed=0, session=False, progress=progress)
    fix = "give a case that 'heartreg phantom OUT' wrote"
    truth = read_json_object(sample / "truth.json", keys=("preset", "seed", "config"), what="phantom truth",
                             error=UsageError, fix=fix)
    seed = truth["seed"]
    try:
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0 or not isinstance(truth["config"], dict):
            raise TypeError(f"seed {seed!r}")
        # every setting of the case (preset, --points, --resp-phase, --chest-wall-mm, anatomy): one record
        config = config_from_dict(truth["config"])
    except (TypeError, ValueError) as exc:
        raise UsageError(f"{sample / 'truth.json'} does not describe a phantom case ({exc}); {fix}") from None
    if (sample / "session" / "session.json").exists():  # the case's own session
        session_dir = sample / "session"
    else:
        session_root = out_dir / "session_case"
        session_dir = session_root / "session"
        recipe = {"config": truth["config"], "seed": seed}
        marker = session_root / "recipe.json"
        if not (session_dir / "session.json").exists() or (
            not marker.exists() or json.loads(marker.read_text()) != recipe
        ):
            if progress:
                print("writing the intra-operative session with the phantom (the case's configuration and seed, "
                      "truth.json)", file=sys.stderr)
            # staged whole: an interrupt leaves the earlier session or none
            with staged_output(session_root, overwrite=True, earlier=("recipe.json", "session/session.json"),
                               what="demo session folder") as stage:
                write_session(stage, config, seed=seed, progress=progress)
                write_text_atomic(stage / "recipe.json", json.dumps(recipe) + "\n")

    made = []  # the rows the report shows, made once (the true surface's sampling takes seconds)

    def report_rows(r):
        made.append(truth_rows(r, truth))
        return made[-1]

    run = run_pipeline(
        sample / "ct", session_dir, out_dir, overwrite=True, progress=progress,
        truth_rows=report_rows,
    )
    rows = made[-1]
    text = format_table(rows)
    write_text_atomic(out_dir / "demo_table.txt", text + "\n")
    write_text_atomic(out_dir / "demo.json", json.dumps(
        {"rows": [[r[0]] + [v if not isinstance(v, (np.floating, np.bool_)) else v.item() for v in r[1:]]
                  for r in rows], "timings_s": run.timings_s}, indent=1, default=float) + "\n")
    return run, rows
