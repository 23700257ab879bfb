"""The end-to-end chain on a user's data: study -> phases -> model -> registration.

``run_pipeline(study_dir, session_dir, out_dir)`` writes::

    OUT_DIR/phases/         phases.csv, phases.json, phases.png    (imaging)
    OUT_DIR/model/          heart.ply, heart.stl, model.json, model.png, model_ct.png  (modeling)
                            + heart_lps.stl, HeartToPatient.tfm, fiducials_ct.mrk.json (3D Slicer)
    OUT_DIR/registration/   registration.json, sweep.csv, figures   (registration)
                            + ProbeTo*.tfm, *.mrk.json (3D Slicer)
    OUT_DIR/report.html     one self-contained page with all of it, an interactive 3-D view first
"""

from __future__ import annotations

import dataclasses
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from hrcore.errors import UsageError

__all__ = ["PARTS", "PipelineResult", "check_out_dir", "open_study", "phase_report_extra", "print_note", "run_pipeline"]

#: what a run writes into OUT_DIR (anything else there is left alone).
PARTS = ("phases", "model", "registration", "report.html")
#: ... and the files that mark an earlier pipeline's output (``--overwrite`` replaces nothing else).
EARLIER = ("phases/phases.json", "model/model.json", "registration/registration.json")


def check_out_dir(path, *, what: str = "output folder", must_be_empty: bool = False, create: bool = True) -> Path:
    """Check an output folder before any work: a folder (or nothing) that can be
    written; with ``must_be_empty``, no earlier contents.  Creates it unless
    ``create`` is false."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise UsageError(f"{what} {path} exists and is not a folder; choose a folder")
    if must_be_empty and path.is_dir() and any(path.iterdir()):
        raise UsageError(f"{what} {path} is not empty; choose an empty folder or pass --overwrite")
    if not create:
        return path
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OSError(f"cannot create {what} {path}: {exc.strerror or exc}") from None
    if not os.access(path, os.W_OK):
        raise OSError(f"{what} {path} is not writable")
    return path


def phase_report_extra(volume, study_dir) -> dict:
    """Series identity and the volume's notes for ``phases.json``, without the study
    folder's path nor its files' names (either can identify a patient: a file is
    "a file" in the notes written, :mod:`hrcore.redact`), and with the pseudonyms
    of the study's DICOM UIDs in place of the UIDs (as ``model.json``); not the
    series' description, free text that can name the patient too."""
    from hrcore.redact import file_namer, pseudonym_uid, pseudonymize_uids

    root = str(Path(study_dir).resolve())
    unnamed = file_namer(study_dir)  # file names can name the patient too: "a file"
    notes = []
    for note in volume.notes:
        for prefix in (root + os.sep, str(study_dir).rstrip(os.sep) + os.sep):
            note = note.replace(prefix, "")
        notes.append(pseudonymize_uids(unnamed(note)))
    return {
        "series_instance_uid": pseudonym_uid(volume.series.series_instance_uid),
        "volume_notes": notes,
    }


def print_note(msg: str) -> None:
    """A note on the terminal (stderr), with the study's DICOM UIDs as their pseudonyms, as in every output
    (:mod:`hrcore.redact`): the readers' notes name a series by its UID."""
    from hrcore.redact import pseudonymize_uids

    print(pseudonymize_uids(msg), file=sys.stderr)


def refuse_one_image(study_dir, volume) -> None:
    """A heart model needs a 3-D CT: one DICOM file holding one slice, given for the study, is refused in
    one line saying so (the model's 'the CT spans only 2 mm' did not say what was given)."""
    if volume.shape[0] == 1 and Path(study_dir).is_file():
        raise UsageError(f"{study_dir} is one DICOM image (a single slice), not a study: give the folder that "
                         "holds the whole CT series")


def open_study(study_dir, *, series=None, qrs=None, progress: bool = False, warn=None, phase_required: bool = True,
               memory_factor: float = 1.0):
    """Load a study's volume and its cardiac phase report: ``imaging.load_study``
    then ``imaging.compute_phase_report`` (which reads the study's ECG waveforms
    itself), with the user's R-peak file if given.

    Parameters
    ----------
    study_dir : path
        Folder holding the DICOM study.
    series : int or str, optional
        Series index (from ``list_series``) or SeriesInstanceUID.
    qrs : path, optional
        R-peak times file (CSV, column ``time_s``, AcquisitionTime clock).
    warn : callable, optional
        Receives the report's notes about unreadable ECG waveforms.
    phase_required : bool
        When false, a CT without gating gives ``report`` None and the reason
        instead of a ``GatingError`` (a heart model needs no phase).

    Returns
    -------
    volume : imaging.Volume
    report : imaging.PhaseReport, or str
        The reason the phase is unknown, when ``phase_required`` is false and
        no R-peak source times the slices.
    memory_factor : float
        Passed to ``imaging.load_study``: the caller's peak memory in multiples of
        the volume's int16 bytes (a series needing more than there is is refused).
    """
    from imaging import compute_phase_report, load_study, read_qrs_file

    volume = load_study(study_dir, series=series, progress=progress, prefer_gated=True,
                        memory_factor=memory_factor)
    qrs_s = read_qrs_file(qrs) if qrs else None
    from imaging import GatingError

    try:
        report = compute_phase_report(
            volume, qrs_s=qrs_s, qrs_label="R-peak file given with --qrs" if qrs else ""
        )
    except GatingError as exc:
        if phase_required or qrs:
            raise
        why = getattr(exc, "reason", None)  # the scan says it was not gated (imaging.nominal); the model warns
        return volume, f"no ECG gating ({why or str(exc).split(';')[0]})"
    if warn is not None:
        for note in volume.notes:
            if note.startswith("chose series") and "other CT candidate" in note:
                warn(f"note: {note}")  # said when there was a choice to make
        for note in report.notes:
            if "unreadable" in note:
                warn(f"note: {note}")
    return volume, report


@dataclass(frozen=True)
class PipelineResult:
    """Everything one run produced, with where it was written; ``volume_series_uid``
    is the series UID's pseudonym, as written (:func:`hrcore.redact.pseudonym_uid`)."""

    volume_series_uid: str
    phase_report: object
    model_build: object
    registration: object
    out_dir: Path
    paths: dict = field(default_factory=dict)
    timings_s: dict = field(default_factory=dict)


def run_pipeline(
    study_dir,
    session_dir,
    out_dir,
    *,
    series=None,
    qrs=None,
    mask=None,
    label=None,
    model_options=None,
    registration_options=None,
    view: bool = True,
    overwrite: bool = False,
    progress: bool = True,
    truth_rows=None,
    option_files=(),
) -> PipelineResult:
    """Run phases -> model -> registration and write every output.

    ``model_options`` (:class:`modeling.ModelOptions`) and ``registration_options``
    (:class:`registration.RegistrationOptions`) are those of ``heartreg model`` and
    ``heartreg register`` (default: their defaults); ``view`` draws the
    registration's 3-D view (``--no-view``). ``truth_rows``, if given, is a
    callable ``(PipelineResult) -> list`` of recovered-vs-truth rows to put at the
    top of the HTML report (the demo). ``option_files``: files the options were
    read from (a ``--seed`` or ``--fiducials`` markups file), inputs that the
    output must not hold.
    """
    from imaging import write_phase_report
    from modeling import build_heart_model, write_model
    from modeling.ct_overlay import ct_panels
    from modeling.labelmap import MASK_FILE, write_mask
    from modeling.options import MODEL_MEMORY_FACTOR
    from modeling.render import render_model_pictures
    from modeling.slice_phases import SlicePhases
    from registration import read_session
    from registration.pipeline import register_session, sweep_phases
    from registration.report import write_registration

    from heartreg.report_html import write_html_report

    from hrcore.output import staged_output

    out_dir = Path(out_dir)
    if registration_options is not None:
        sweep_phases(registration_options.phase_step)  # --step refused now, not after the phases and the model
    timings = {}
    log = print_note if progress else (lambda msg: None)
    # everything is written into a staging folder and moved into place at the end
    # (one rename when OUT_DIR is new): a failure or a signal leaves OUT_DIR as it was
    with staged_output(
        out_dir, inputs=(study_dir, session_dir, qrs, mask, *option_files), overwrite=overwrite, parts=PARTS,
        earlier=EARLIER,
    ) as staging:
        t = time.perf_counter()
        log("[1/3] cardiac phase of every CT slice")
        volume, report = open_study(study_dir, series=series, qrs=qrs, progress=progress, warn=log,
                                    memory_factor=MODEL_MEMORY_FACTOR)  # the model is built from it
        refuse_one_image(study_dir, volume)
        session = read_session(session_dir)  # fail early on a bad session, before the slow work
        extra = phase_report_extra(volume, study_dir)
        paths = {"phases": write_phase_report(report, staging / "phases", extra=extra)}
        timings["phases"] = time.perf_counter() - t

        t = time.perf_counter()
        log("[2/3] heart model")
        build = build_heart_model(
            volume,
            cardiac_phase=report.volume_cardiac_phase,
            cardiac_phase_source=report.source,
            slice_phases=SlicePhases.from_report(report, volume.T_patient_from_voxel),
            mask_path=mask,
            label=label,
            options=model_options,
        )
        model_dir = write_model(build.model, staging / "model")
        paths["model"] = model_dir
        paths["mask"] = write_mask(model_dir / MASK_FILE, build.mask, build.T_patient_from_mask)
        mesh = build.model.mesh_patient()
        paths["model_png"], paths["model_ct_png"] = render_model_pictures(  # no OpenGL needed
            build.model, ct_panels(volume.hu, volume.T_patient_from_voxel, mesh.vertices, mesh.faces), model_dir)
        timings["model"] = time.perf_counter() - t

        t = time.perf_counter()
        log("[3/3] spatiotemporal registration")
        result = register_session(build.model, session, options=registration_options, progress=progress)
        paths["registration"] = write_registration(
            result, staging / "registration", model=build.model, view=view,
            fiducials_probe_mm=session.fiducials_probe_mm,
        )
        timings["registration"] = time.perf_counter() - t

        run = PipelineResult(
            volume_series_uid=build.model.source["series_instance_uid"],  # the pseudonym, as model.json
            phase_report=report,
            model_build=build,
            registration=result,
            out_dir=staging,
            paths=paths,
            timings_s=timings,
        )
        rows = truth_rows(run) if truth_rows is not None else None
        paths["report"] = write_html_report(run, staging / "report.html", truth_rows=rows)
    return dataclasses.replace(run, out_dir=out_dir, paths=_moved(paths, staging, out_dir))


def _moved(value, old: Path, new: Path):
    """``value`` (paths, possibly nested in dicts and lists) with ``old`` replaced by ``new``."""
    if isinstance(value, dict):
        return {k: _moved(v, old, new) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(_moved(v, old, new) for v in value)
    if isinstance(value, Path) and value.is_relative_to(old):
        return new / value.relative_to(old)
    return value
