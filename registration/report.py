"""Registration outputs: ``registration.json``, sweep CSVs, the paper's plots; and reading them back.

Files written by :func:`write_registration` into ``OUT_DIR`` (all atomically,
no patient identity, UTF-8, ``\\n`` line ends):

``registration.json``
    :meth:`RegistrationResult.to_dict` plus ``format`` (``"heartreg-registration"``),
    ``format_version`` (2) and ``files``.  Every attribute of the result but
    ``timings_s`` is stored under its own name, exactly, so that
    :func:`read_registration` gives back an equal :class:`RegistrationResult`
    (the sweeps too: they are read from here, not from the CSVs).  Transforms
    are 4 x 4 row-major lists mapping the reference-probe frame to the model's
    heart frame (mm); angles in degrees.  Lists of numbers are written on one
    line each.
``sweep.csv``
    One row per swept respiration phase at phi_C* (paper Figs. 2B, 6, 7):
    ``respiration_phase, rms_mm, tx_mm, ty_mm, tz_mm, rx_deg, ry_deg, rz_deg,
    translation_distance_mm, rotation_distance_deg, iterations``.
    ``t*`` and ``r*`` are the registration parameters of paper Fig. 6 in the
    heart frame: the correction ``dT = T inv(T0)`` as the displacement it gives
    the pivot (the surface centroid, ``pivot_heart_mm`` in the JSON) and its
    intrinsic X-Y-Z Euler angles.  ``translation_distance_mm`` is the norm of
    ``(tx, ty, tz)`` and ``rotation_distance_deg`` the geodesic angle of ``dT``
    (paper Fig. 7, eq. 10).
``cardiac_sweep.csv``
    The same columns with ``cardiac_phase`` first, phi_C swept at phi_R* (Fig. 2A);
    only when the cardiac sweep was run.
``phase_evidence.csv``
    The evidence behind phi_R* per swept phase (:func:`phase_evidence_csv_text`).
``fig2_rms.png``, ``fig6_parameters.png``, ``fig7_distances.png``, ``fig9_delta.png``
    The paper's Figs. 2, 6, 7 and 9 for this registration
    (:mod:`registration.figures`); Fig. 7 shades each estimator's 90 % interval of phi_R*.
``fig10_phase.png``
    The shape estimator's cost terms over phi_R and the bootstrap phases.
``fig8_view.png``
    The 3-D view of :mod:`registration.view` when a model is given (drawn
    by matplotlib: no OpenGL needed).
``ProbeTo*.tfm``, ``points_registered.mrk.json``, ``fiducials_touched.mrk.json``
    The same registration for 3D Slicer (:mod:`registration.slicer`,
    ``docs/slicer.md``).

Format version 1 (heartreg before format 2) is still read: its keys
``respiration_phase_estimate``/``respiration_phase_alternatives`` and the
summary ``static`` and ``sweep`` objects are converted, the sweeps come from
``sweep.csv``/``cardiac_sweep.csv`` (6 decimals; first column ``phase_r`` or
``phase_c``).  What version 1 never stored reads as NaN and the result says so
in its ``notes``: the predicted points and normals, the mean positions, the
static comparison's projected points, the sweeps' transforms, Euler angles and
per-point distances, and the phase estimates' cost curves and bootstrap
phases; a sweep's ``converged`` is ``iterations`` below the ICP limit.
"""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

import numpy as np

from hrcore.errors import HeartregError
from hrcore.geometry import is_rigid
from hrcore.output import staged_output
from imaging.files import write_text_atomic
from registration.figures import write_plots
from registration.result import RegistrationResult
from registration.slicer import write_slicer_files
from registration.spatiotemporal import PhaseSweep

__all__ = [
    "REPORT_FORMAT", "REPORT_VERSION", "SWEEP_COLUMNS", "RegistrationFileError", "write_registration",
    "read_registration", "sweep_csv_text", "phase_evidence_csv_text",
]

REPORT_FORMAT = "heartreg-registration"
REPORT_VERSION = 2
JSON_FILE = "registration.json"
SWEEP_COLUMNS = (
    "rms_mm",
    "tx_mm",
    "ty_mm",
    "tz_mm",
    "rx_deg",
    "ry_deg",
    "rz_deg",
    "translation_distance_mm",
    "rotation_distance_deg",
    "iterations",
)
#: Notes added to a result read from a format-1 file.
V1_NOTE = ("read from a format-1 registration.json: the predicted points and normals, the mean positions, "
           "the static projections, the sweeps' transforms and per-point distances and the phase estimates' "
           "curves were not stored and are NaN")


class RegistrationFileError(HeartregError, ValueError):
    """A ``registration.json`` (or its sweep CSV) that cannot be read back."""


def sweep_csv_text(sweep: PhaseSweep) -> str:
    """The CSV text of one sweep (header ``respiration_phase`` or ``cardiac_phase``, then SWEEP_COLUMNS)."""
    first = "respiration_phase" if sweep.kind == "respiration" else "cardiac_phase"
    lines = [",".join((first,) + SWEEP_COLUMNS)]
    t = sweep.correction_translation_mm
    e = sweep.correction_euler_xyz_deg
    for i, phase in enumerate(sweep.phases):
        values = (
            f"{phase:.4f}",
            f"{sweep.rms_mm[i]:.6f}",
            *(f"{x:.6f}" for x in t[i]),
            *(f"{x:.6f}" for x in e[i]),
            f"{sweep.translation_distance_mm[i]:.6f}",
            f"{sweep.rotation_distance_deg[i]:.6f}",
            str(int(sweep.iterations[i])),
        )
        lines.append(",".join(values))
    return "\n".join(lines) + "\n"


def write_registration(
    result: RegistrationResult, out_dir, *, overwrite: bool = False, inputs=(), model=None, view: bool = True,
    fiducials_probe_mm=None,
) -> dict:
    """Write the registration's files into the folder ``out_dir``, atomically (module docstring).

    Everything is written into a staging folder beside ``out_dir`` that
    replaces it in one rename (:func:`hrcore.output.staged_output`): a failure
    or a signal leaves ``out_dir`` as it was, and nothing of an earlier run
    survives in it (no stale figure or CSV of another run).

    Parameters
    ----------
    result : RegistrationResult
    out_dir : str or Path
        The output folder; created if missing.  An existing non-empty folder
        is refused unless ``overwrite``.
    overwrite : bool
        Replace an existing non-empty ``out_dir`` (``--overwrite``).
    inputs : iterable of str or Path
        The inputs (model and session folders): ``out_dir`` may not be, lie
        in or contain one of them.
    model : HeartModel, optional
        The registered model; needed for the 3-D view ``fig8_view.png``.
    view : bool
        Draw the 3-D view (when ``model`` is given).
    fiducials_probe_mm : (n, 3) float, mm, optional
        The session's touched fiducials, written for 3D Slicer.

    Returns
    -------
    dict
        ``{name: Path}`` of the files written (in ``out_dir``), and
        ``"notes"``: a list of reasons for files skipped (e.g. a view that failed to draw).

    Raises
    ------
    hrcore.output.OutputError
        A refused ``out_dir`` (not empty without ``overwrite``, an input, not
        writable) or a full disk.

    Examples
    --------
    ``result`` and ``model`` from :func:`register_session` and
    :func:`modeling.read_model` (skipped here, the repository ships no session):

    >>> from registration import read_registration, write_registration
    >>> paths = write_registration(result, "out/registration", model=model)  # doctest: +SKIP
    >>> paths["json"], paths["fig8"]  # doctest: +SKIP
    (PosixPath('out/registration/registration.json'), PosixPath('out/registration/fig8_view.png'))
    >>> write_registration(result, "out/registration", model=model)  # doctest: +SKIP
    Traceback (most recent call last):
        ...
    hrcore.output.OutputError: ... out/registration is not empty; choose an empty folder or pass --overwrite
    >>> paths = write_registration(result, "out/registration", model=model, overwrite=True)  # doctest: +SKIP
    >>> read_registration("out/registration").respiration_phase == result.respiration_phase  # doctest: +SKIP
    True
    """
    if not isinstance(result, RegistrationResult):
        raise TypeError(f"result must be a RegistrationResult, got {type(result).__name__}")
    out = Path(out_dir)
    with staged_output(out, inputs=inputs, overwrite=overwrite, earlier=(JSON_FILE,)) as stage:
        paths = _write_files(result, stage, model=model, view=view, fiducials_probe_mm=fiducials_probe_mm)
    return _moved(paths, stage, out)


def _moved(value, stage: Path, out: Path):
    """``value`` (paths, nested in dicts) with the staging folder replaced by ``out``."""
    if isinstance(value, dict):
        return {k: _moved(v, stage, out) for k, v in value.items()}
    if isinstance(value, Path):
        return out / value.relative_to(stage)
    return value


def _write_files(result: RegistrationResult, out: Path, *, model, view, fiducials_probe_mm) -> dict:
    paths: dict = {}
    payload = {"format": REPORT_FORMAT, "format_version": REPORT_VERSION}
    payload.update(result.to_dict())
    payload["files"] = {"sweep": "sweep.csv"}
    if result.phase_estimates:
        payload["files"]["phase_evidence"] = "phase_evidence.csv"
    if result.cardiac_sweep is not None:
        payload["files"]["cardiac_sweep"] = "cardiac_sweep.csv"
    paths["json"] = out / JSON_FILE
    write_text_atomic(paths["json"], json_text(payload))
    paths["sweep"] = out / "sweep.csv"
    write_text_atomic(paths["sweep"], sweep_csv_text(result.respiration_sweep))
    if result.cardiac_sweep is not None:
        paths["cardiac_sweep"] = out / "cardiac_sweep.csv"
        write_text_atomic(paths["cardiac_sweep"], sweep_csv_text(result.cardiac_sweep))
    if result.phase_estimates:
        payload_files = "phase_evidence.csv"
        paths["phase_evidence"] = out / payload_files
        write_text_atomic(paths["phase_evidence"], phase_evidence_csv_text(result))
    paths.update(write_plots(result, out))
    paths["slicer"] = write_slicer_files(
        result, out, fiducials_probe_mm=fiducials_probe_mm,
        T_patient_from_heart=None if model is None else model.T_patient_from_heart,
    )
    notes = []
    if model is not None and view:
        from modeling.render import RenderError
        from registration.view import render_registration_png

        try:
            paths["fig8"] = render_registration_png(model, result, out / "fig8_view.png")
        except RenderError as exc:
            notes.append(f"fig8_view.png skipped: {exc}")
    paths["notes"] = notes
    return paths


def phase_evidence_csv_text(result: RegistrationResult) -> str:
    """The evidence behind phi_R*, one row per swept phase.

    Columns: ``respiration_phase``, then per estimator (``shape``, ``eq10``) its cost
    (``J - min J`` for shape, unitless; translation distance minus its minimum,
    mm, for eq. 10) and the share of bootstrap resamples that chose the phase;
    then the shape estimator's terms ``cost_heart``, ``cost_fiducial``,
    ``cost_prior``.
    """
    phases = result.respiration_sweep.phases
    by = {e.method: e for e in result.phase_estimates}
    cols, data = ["respiration_phase"], [phases]
    for method in ("shape", "eq10"):
        e = by.get(method)
        if e is None:
            continue
        share = np.array([np.mean(np.isclose(e.bootstrap_phases, p % 1.0)) for p in phases])
        cols += [f"{method}_cost", f"{method}_bootstrap_share"]
        data += [e.cost, share]
    if "shape" in by:
        e = by["shape"]
        cols += ["cost_heart", "cost_fiducial", "cost_prior"]
        data += [e.cost_heart, e.cost_fiducial, e.cost_prior]
    rows = np.column_stack(data)
    lines = [",".join(cols)] + [",".join(f"{v:.6g}" for v in row) for row in rows]
    return "\n".join(lines) + "\n"


def json_text(payload) -> str:
    """JSON text with one key per line and every list of numbers on one line."""
    return _dumps(payload, 0) + "\n"


def _dumps(obj, level: int) -> str:
    pad, inner = " " * level, " " * (level + 1)
    if isinstance(obj, dict) and obj:
        items = [f"{inner}{json.dumps(str(k))}: {_dumps(v, level + 1)}" for k, v in obj.items()]
        return "{\n" + ",\n".join(items) + "\n" + pad + "}"
    if isinstance(obj, (list, tuple)) and any(isinstance(v, (dict, list, tuple)) for v in obj):
        return "[\n" + ",\n".join(inner + _dumps(v, level + 1) for v in obj) + "\n" + pad + "]"
    if isinstance(obj, (list, tuple)):
        return "[" + ", ".join(json.dumps(v, allow_nan=False) for v in obj) + "]"
    return json.dumps(obj, allow_nan=False)


def read_registration(out_dir) -> RegistrationResult:
    """Read the ``registration.json`` of :func:`write_registration` back.

    Parameters
    ----------
    out_dir : str or Path
        The output folder of :func:`write_registration` (``heartreg register -o``).

    Returns
    -------
    RegistrationResult
        Equal to the one written (format 2), field by field and bit for bit,
        except ``timings_s`` (not stored: empty).  A format-1 file gives NaN for
        what it never stored (module docstring) and says so in ``notes``.

    Raises
    ------
    RegistrationFileError
        One line naming the file: missing, unreadable, not JSON, another
        format or format version, or a missing or bad field.

    Examples
    --------
    The round trip of a registration (``result`` from :func:`register_session`;
    skipped here, the repository ships no session):

    >>> from registration import read_registration, write_registration
    >>> paths = write_registration(result, "out/registration", view=False)  # doctest: +SKIP
    >>> again = read_registration("out/registration")  # doctest: +SKIP
    >>> bool((again.T_heart_from_probe == result.T_heart_from_probe).all())  # doctest: +SKIP
    True

    A folder without ``registration.json`` is refused in one line:

    >>> read_registration("no_such_folder")
    Traceback (most recent call last):
        ...
    registration.report.RegistrationFileError: no_such_folder/registration.json not found: give the output folder of heartreg register
    """
    path = Path(out_dir) / JSON_FILE
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise RegistrationFileError(f"{path} not found: give the output folder of heartreg register") from None
    except OSError as exc:
        raise RegistrationFileError(f"{path}: cannot read it ({exc.strerror or exc})") from None
    except ValueError as exc:
        raise RegistrationFileError(f"{path}: not JSON ({exc}); re-run heartreg register") from None
    fmt = data.get("format") if isinstance(data, dict) else None
    if fmt != REPORT_FORMAT:
        raise RegistrationFileError(f"{path}: not a heartreg registration (format {fmt!r}, expected {REPORT_FORMAT!r})")
    version = data.get("format_version")
    if version not in (1, REPORT_VERSION):
        raise RegistrationFileError(
            f"{path}: format version {version!r} is not one this heartreg reads (1 or {REPORT_VERSION}); "
            "update heartreg or re-run heartreg register"
        )
    try:
        if version == 1:
            data = _upgrade_v1(data, path.parent)
        result = RegistrationResult.from_dict(data)
    except KeyError as exc:
        raise RegistrationFileError(f"{path}: missing field {exc.args[0]!r}; re-run heartreg register") from None
    except OSError as exc:
        raise RegistrationFileError(
            f"{exc.filename or path}: cannot read it ({exc.strerror or exc}); a format-1 registration "
            "needs its sweep CSVs beside registration.json"
        ) from None
    except (TypeError, ValueError, IndexError, AttributeError) as exc:
        raise RegistrationFileError(f"{path}: bad field ({exc}); re-run heartreg register") from None
    _check_values(result, path)
    return result


def _check_values(result: RegistrationResult, path: Path) -> None:
    """Refuse, naming the field, a transform that is not a finite rigid one or a phase outside [0, 1].

    A sweep's transform may be all NaN (format 1 never stored them); a bootstrap phase NaN (likewise).
    """
    transforms = [("T_heart_from_probe", result.T_heart_from_probe, False),
                  ("T0_heart_from_probe", result.T0_heart_from_probe, False),
                  ("static.T_static_heart_from_probe", result.static.T_static_heart_from_probe, False)]
    phases = [("cardiac_phase", result.cardiac_phase, False), ("respiration_phase", result.respiration_phase, False)]
    for key, sweep in (("respiration_sweep", result.respiration_sweep), ("cardiac_sweep", result.cardiac_sweep)):
        if sweep is not None:
            transforms.append((f"{key}.T_heart_from_probe", sweep.T_heart_from_probe, True))
            phases += [(f"{key}.fixed_phase", sweep.fixed_phase, False), (f"{key}.phases", sweep.phases, False)]
    for k, e in enumerate(result.phase_estimates):
        phases += [(f"phase_estimates[{k}].respiration_phase", e.respiration_phase, False),
                   (f"phase_estimates[{k}].interval", e.interval, False),
                   (f"phase_estimates[{k}].bootstrap_phases", e.bootstrap_phases, True)]
        if e.breath_hold_phase is not None:
            phases.append((f"phase_estimates[{k}].breath_hold_phase", e.breath_hold_phase, False))
    for name, value, nan_ok in transforms:
        T = np.asarray(value, dtype=float).reshape(-1, 4, 4)
        bad = ~is_rigid(T) & ~(nan_ok & np.isnan(T).all(axis=(1, 2)))
        if bad.any():
            at = f"[{int(np.argmax(bad))}]" if np.ndim(value) == 3 else ""
            raise RegistrationFileError(
                f"{path}: field {name}{at} is not a finite rigid transform (rotation orthonormal, last row "
                "0 0 0 1); the file is damaged: re-run heartreg register"
            )
    for name, value, nan_ok in phases:
        v = np.atleast_1d(np.asarray(value, dtype=float))
        bad = ~((v >= 0.0) & (v <= 1.0)) & ~(nan_ok & np.isnan(v))
        if bad.any():
            k = int(np.argmax(bad))
            raise RegistrationFileError(
                f"{path}: field {name}{f'[{k}]' if np.ndim(value) else ''} = {float(v[k])!r} is not a phase "
                "in [0, 1]; the file is damaged: re-run heartreg register"
            )


def _upgrade_v1(data: dict, folder: Path) -> dict:
    """A format-1 payload in the form of format 2 (module docstring)."""
    d = dict(data)
    ids = [int(i) for i in d["point_ids"]]
    nan3 = [[None] * 3 for _ in ids]
    max_it = int(dict(d["parameters"].get("icp_options") or {}).get("max_iterations", 50))
    files = d.get("files") or {}
    d["respiration_sweep"] = _v1_sweep(folder / files.get("sweep", "sweep.csv"), "respiration",
                                       d["cardiac_phase"], d["pivot_heart_mm"], max_it)
    card = files.get("cardiac_sweep")
    d["cardiac_sweep"] = None if card is None else _v1_sweep(folder / card, "cardiac", d["respiration_phase"],
                                                             d["pivot_heart_mm"], max_it)
    st = d["static"]
    d["static"] = {
        "T_static_heart_from_probe": st["T_heart_from_probe"], "rms_static_mm": st["rms_mm"],
        "mean_delta_mm": d["delta_static_mean_mm"], "delta_mm": [d["delta_static_mm"][str(i)] for i in ids],
        "projected_static_mm": nan3, "projected_spatiotemporal_mm": nan3,
    }
    for key in ("points_probe_mm", "normals_probe", "mean_points_probe_mm"):
        d[key] = nan3
    phases = np.asarray(d["respiration_sweep"]["phases"], dtype=float)
    estimates = [d.get("respiration_phase_estimate"), *(d.get("respiration_phase_alternatives") or [])]
    d["phase_estimates"] = [_v1_estimate(e, phases) for e in estimates if e]
    d["notes"] = [*d["notes"], V1_NOTE]
    return d


def _v1_estimate(e: dict, phases: np.ndarray) -> dict:
    nan_m = [None] * phases.size
    return {
        "method": e["method"], "evidence": e["evidence"], "respiration_phase": e["phase"],
        "index": int(np.argmin(np.abs(phases - float(e["phase"])))), "interval": e["interval"],
        "interval_offsets": e["interval_offsets"], "confidence": e["confidence"], "decided": e["decided"],
        "bootstrap_phases": [None] * int(e["n_bootstrap"]), "cost": nan_m, "cost_heart": nan_m,
        "cost_fiducial": nan_m, "cost_prior": nan_m,
        "transform_mm": e["transform_90_mm"], "transform_deg": e["transform_90_deg"],
    }


def _v1_sweep(path: Path, kind: str, fixed_phase, pivot_mm, max_iterations: int) -> dict:
    """A sweep CSV (either version's first column) in the JSON form of format 2."""
    rows = list(csv.reader(io.StringIO(path.read_text(encoding="utf-8"))))
    firsts = ("phase_r", "respiration_phase") if kind == "respiration" else ("phase_c", "cardiac_phase")
    if not rows or rows[0][0] not in firsts or tuple(rows[0][1:]) != SWEEP_COLUMNS:
        raise ValueError(f"{path.name}: header {rows[0] if rows else []} is not a {kind} sweep's")
    a = np.array(rows[1:], dtype=float).reshape(-1, len(SWEEP_COLUMNS) + 1)
    m = a.shape[0]
    iterations = a[:, -1].astype(int)
    return {
        "kind": kind, "fixed_phase": fixed_phase, "phases": a[:, 0].tolist(), "rms_mm": a[:, 1].tolist(),
        "T_heart_from_probe": np.full((m, 4, 4), None).tolist(),
        "correction_translation_mm": a[:, 2:5].tolist(), "correction_euler_xyz_deg": a[:, 5:8].tolist(),
        "translation_distance_mm": a[:, 8].tolist(), "rotation_distance_deg": a[:, 9].tolist(),
        "euler_xyz_deg": np.full((m, 3), None).tolist(), "iterations": iterations.tolist(),
        "converged": [bool(i < max_iterations) for i in iterations], "pivot_mm": pivot_mm,
        "distances_mm": None, "signed_distances_mm": None,
    }
