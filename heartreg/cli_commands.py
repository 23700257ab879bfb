"""The commands of the ``heartreg`` command line, one ``_cmd_<name>(args)`` each.

Each takes the parsed arguments (:mod:`heartreg.cli_parser`) and returns the
exit status; :func:`heartreg.cli.main` turns a domain error into one line.
Heavy packages are imported inside each command so that ``heartreg --help``
stays fast.
"""

from __future__ import annotations

import dataclasses
import sys
import warnings
from pathlib import Path

from hrcore.errors import UsageError


def _cmd_phantom(args) -> int:
    from heartreg.phantom.generate import make_phantom

    for flag in ("navigation", "plus"):
        if getattr(args, flag) is not False and args.no_session:
            raise UsageError(f"--{flag} needs the session: drop --no-session")
    overrides = {}
    if args.points is not None:
        overrides["n_points"] = args.points
    if args.resp_phase is not None:
        overrides["image_resp_phase"] = args.resp_phase
    if args.chest_wall_mm is not None:
        overrides["chest_wall_ap_mm"] = args.chest_wall_mm
    truth = make_phantom(
        args.out_dir,
        preset=args.preset,
        size=args.size,
        seed=args.seed,
        session=not args.no_session,
        progress=not args.quiet,
        overwrite=args.overwrite,
        plus=args.plus,
        anatomy=args.anatomy,
        fov_mm=args.fov_mm,
        markers=False if args.no_markers else None,
        stent=True if args.stent else None,
        **overrides,
    )
    out = Path(args.out_dir)
    print(f"phantom {truth['preset']} ({truth['size']}, seed {truth['seed']}) written to {out}")
    print(f"  CT slices        {len(truth['slice_cardiac_phase'])} in {out / 'ct'}")
    print(f"  image phase      phi_C* = {truth['cardiac_phase']:.4f}, phi_R* = {truth['respiration_phase']:.2f}")
    if "session" in truth:
        print(f"  session points   {len(truth['session']['points'])} in {out / 'session'}")
        if args.plus is not False:
            rate = "a frame per sample" if args.plus is True else f"the tracker at {args.plus:g} Hz"
            print(f"  PLUS session     {out / 'session_plus'} (poses in tracking.seq.mha, {rate})")
    if args.navigation:
        from heartreg.phantom.navigation import write_navigation

        nav = write_navigation(out)
        print(f"  navigation       {nav.time_s.size} samples in {out / 'navigation'}, truth {out / 'navigation_truth.csv'}")
    if "anatomy" in truth:
        a = truth["anatomy"]
        extras = [a["heart"]] + ([f"FOV {a['fov_mm']:g} mm"] if a["fov_mm"] else [])
        extras += [] if a["markers"] else ["no skin markers"]
        extras += ["stent in the descending aorta"] if "stent" in a else []
        print(f"  anatomy          {', '.join(extras)}")
    print(f"  truth            {out / 'truth.json'}")
    return 0


def _open_study(args):
    """Load the study's volume and compute its phase report (shared by commands)."""
    from heartreg.pipeline import open_study, print_note

    return open_study(
        args.study_dir, series=args.series, qrs=args.qrs, progress=not args.quiet,
        warn=print_note,
    )


def _needs_dicom_study(args, command: str) -> None:
    """Refuse a NIfTI or NRRD volume where ``command`` reads a DICOM study (phases, pipeline): one line."""
    from imaging.volume_file import is_volume_file

    if is_volume_file(args.study_dir):
        raise UsageError(f"{args.study_dir} is a volume file: {command} reads a DICOM study (its slice times and "
                         "ECG); a NIfTI or NRRD volume has no slice clock: give the DICOM folder, or make the model "
                         "from the volume with 'heartreg model' (and 'heartreg register --cardiac-phase P')")


def _listed(args) -> bool:
    """``--list-series``: list the study's series (True: the command is done); otherwise -o is required."""
    from imaging import list_series
    from imaging.volume_file import is_volume_file

    if args.list_series:
        if is_volume_file(args.study_dir):
            raise UsageError(f"{args.study_dir} is a volume file, one series: --list-series lists a DICOM folder's")
        from hrcore.redact import pseudonym_uid

        for s in list_series(args.study_dir):  # the UID to choose by, and the pseudonym the other lines print
            print(f"[{s.index}] {s.uid} ({pseudonym_uid(s.uid)})  {s.modality:<3} {s.n_slices:>4} images  {s.orientation:<8} {s.description!r}  "
                  f"{s.kind}{('  ' + s.cardiac) if s.cardiac else ''}{(' - ' + s.reason) if s.reason else ''}")
        return True
    if args.out_dir is None:
        raise UsageError("give an output folder with -o OUT_DIR (or --list-series)")
    return False


def _cmd_phases(args) -> int:
    from imaging import write_phase_report

    from hrcore.output import check_output_path

    from heartreg.pipeline import phase_report_extra
    from imaging.phase_io import JSON_FILE as PHASES_JSON

    _needs_dicom_study(args, "phases")
    if _listed(args):
        return 0
    inputs = (args.study_dir, args.qrs)
    check_output_path(args.out_dir, inputs=inputs, what="-o", overwrite=args.overwrite, earlier=(PHASES_JSON,))
    volume, report = _open_study(args)
    extra = phase_report_extra(volume, args.study_dir)
    paths = write_phase_report(report, args.out_dir, extra=extra, overwrite=args.overwrite, inputs=inputs)
    lo, hi = 0.6, 0.8
    print(f"{report.n_slices} slices of series {extra['series_instance_uid']}")  # its pseudonym, as written
    print(f"  R-peak source     {report.source}")
    print(f"  clock             {report.clock}")
    print(f"  volume phase      {report.volume_cardiac_phase:.4f} (mean), {report.circular_mean_phase:.4f} (circular mean)")
    print(f"  slice phases      {report.phases.min():.3f} .. {report.phases.max():.3f}, "
          f"{100 * report.fraction_in_window:.0f} % inside {lo}-{hi}, {len(report.jumps)} jump(s)")
    print(f"  written           {', '.join(str(p) for p in paths.values())}")
    return 0


def _model_options(args):
    """The model options the flags give (their defaults written once, in ModelOptions)."""
    from modeling.options import ModelOptions

    kw = {}
    if args.faces is not None:
        kw["target_faces"] = args.faces
    if isinstance(args.fiducials, Path):
        from modeling.slicer import read_markups

        if args.fiducial_floor_hu is not None:
            raise UsageError("--fiducial-floor-hu tunes the search for skin markers; --fiducials FILE gives them "
                             "instead: give one")

        from registration.session_format import FIDUCIAL_ORDER, N_FIDUCIALS

        kw["fiducials_mm"] = read_markups(args.fiducials).points_lps_mm
        if len(kw["fiducials_mm"]) != N_FIDUCIALS:  # the session touches that many: register needs each once
            raise UsageError(f"--fiducials: the markups file {args.fiducials} holds {len(kw['fiducials_mm'])} placed "
                             f"point(s); heartreg register needs the {N_FIDUCIALS} staples the session touches, one "
                             f"point each ({FIDUCIAL_ORDER}): place exactly {N_FIDUCIALS}")
    elif args.fiducials is not None:
        kw["expected_fiducials"] = None if args.fiducials == 0 else args.fiducials
    if args.fiducial_floor_hu is not None:
        kw["fiducial_floor_hu"] = args.fiducial_floor_hu
    if args.keep_vessels and args.trim_vessels:
        raise UsageError("--keep-vessels and --trim-vessels contradict each other; give one")
    if args.keep_vessels or args.trim_vessels:
        kw["trim_vessels"] = bool(args.trim_vessels)
    if args.seed is not None:
        if args.mask is not None:
            raise UsageError("--seed starts the automatic segmentation; --mask replaces it: give one")
        if isinstance(args.seed, Path):
            from modeling.slicer import read_markups

            points = read_markups(args.seed).points_lps_mm
            if len(points) == 0:
                raise UsageError(f"--seed: the markups file {args.seed} holds no placed point")
            if len(points) > 1:  # the others were ignored without a word (an audit)
                from modeling.build import ModelingWarning

                warnings.warn(f"--seed: the markups file {args.seed} holds {len(points)} points; the first is the "
                              "seed, the others are not used", ModelingWarning, stacklevel=2)
            seed = [float(x) for x in points[0]]
        else:
            seed = list(args.seed)
        kw["segmentation"] = {"seed_patient_mm": seed}
    return ModelOptions(**kw)


def _option_files(args) -> tuple:
    """The files the model's options name (``--seed``, ``--fiducials`` markups): inputs the output must spare."""
    return tuple(v for v in (args.seed, args.fiducials) if isinstance(v, Path))


def _registration_options(args):
    """The registration options the flags give (defaults written once, in RegistrationOptions)."""
    from registration.options import RegistrationOptions

    kw = {"estimator": args.estimator}
    if args.step is not None:
        kw["phase_step"] = args.step
    if args.harmonics is not None:
        kw["harmonics"] = tuple(args.harmonics)
    if args.breath_hold_phase is not None:
        kw["breath_hold_phase"] = args.breath_hold_phase
    if args.no_slice_phases:
        kw["slice_phases"] = False
    if args.icp_max_iterations is not None:
        if args.icp_max_iterations < 1:
            raise UsageError(f"max_iterations (--icp-max-iterations) must be >= 1, got {args.icp_max_iterations}")
        kw["icp_options"] = {"max_iterations": args.icp_max_iterations}
    return RegistrationOptions(**kw)


def _open_model_input(args):
    """The model command's CT (a DICOM study folder, a NIfTI or an NRRD file) and its phase.

    Returns ``(volume, phase, source, slice_phases)``; ``phase`` and
    ``slice_phases`` are None when the CT has no ECG gating (a model needs
    none: its phase is then recorded as unknown).
    """
    from imaging.volume_file import is_nifti_path, is_volume_file, read_volume_file
    from modeling.options import MODEL_MEMORY_FACTOR

    from heartreg.pipeline import open_study, print_note, refuse_one_image

    if is_volume_file(args.study_dir):
        kind, article = ("NIfTI", "a") if is_nifti_path(args.study_dir) else ("NRRD", "an")
        if args.qrs is not None or args.series is not None:
            raise UsageError(f"--qrs and --series apply to DICOM studies, not to the {kind} file {args.study_dir}")
        return (read_volume_file(args.study_dir, memory_factor=MODEL_MEMORY_FACTOR), None,
                f"{article} {kind} volume has no slice clock", None)
    volume, report = open_study(
        args.study_dir, series=args.series, qrs=args.qrs, progress=not args.quiet,
        warn=print_note, phase_required=False, memory_factor=MODEL_MEMORY_FACTOR,
    )
    refuse_one_image(args.study_dir, volume)
    if isinstance(report, str):
        return volume, None, report, None
    from modeling.slice_phases import SlicePhases

    slices = SlicePhases.from_report(report, volume.T_patient_from_voxel)
    return volume, report.volume_cardiac_phase, report.source, slices


def _cmd_model(args) -> int:
    from modeling import build_heart_model, write_model
    from modeling.ct_overlay import ct_panels
    from modeling.labelmap import MASK_FILE, write_mask
    from modeling.model import JSON_FILE as MODEL_JSON
    from modeling.render import render_model_pictures

    if _listed(args):
        return 0
    from hrcore.memory import release_free_memory
    from hrcore.output import check_output_path, staged_output

    if args.label is not None and args.mask is None:
        raise UsageError("--label chooses a label of --mask; give the label map with --mask FILE")
    options = _model_options(args)
    inputs = (args.study_dir, args.qrs, args.mask, *_option_files(args))
    check_output_path(args.out_dir, inputs=inputs, what="model folder", overwrite=args.overwrite,
                      earlier=(MODEL_JSON,))
    volume, phase, phase_source, slice_phases = _open_model_input(args)
    from tqdm import tqdm

    # the stages of build_heart_model (mask, mesh, fiducials, frame), then the write
    bar = tqdm(total=5, desc="model", disable=args.quiet, file=sys.stderr, leave=False)

    def stage(name: str) -> None:  # a stage starts: the one before it is done
        bar.update(0 if name == "mask" else 1)
        bar.set_postfix_str(name)

    build = build_heart_model(
        volume,
        cardiac_phase=phase,
        cardiac_phase_source=phase_source,
        slice_phases=slice_phases,
        mask_path=args.mask,
        label=args.label,
        options=options,
        progress=stage,
    )
    stage("write")
    model = build.model
    series_uid = model.source["series_instance_uid"]  # the UID's pseudonym, as model.json (hrcore.redact)
    mesh = model.mesh_patient()
    panels = ct_panels(volume.hu, volume.T_patient_from_voxel, mesh.vertices, mesh.faces)  # small 2-D planes
    del volume, mesh  # the CT is done with: the pictures' memory comes on top of what is left
    release_free_memory()
    out = Path(args.out_dir)
    # the pictures are drawn inside the staging folder: the model appears complete or not at all
    with staged_output(out, inputs=inputs, what="model folder", overwrite=args.overwrite,
                       earlier=(MODEL_JSON,)) as staging:
        write_model(model, staging, overwrite=True)
        write_mask(staging / MASK_FILE, build.mask, build.T_patient_from_mask)
        render_model_pictures(model, panels, staging)  # matplotlib only: no OpenGL needed
    picture = f"{out / 'model.png'}, over the CT {out / 'model_ct.png'}"
    bar.update(1)
    bar.close()
    e = model.frame.euler_xyz_deg
    print(f"heart model of series {series_uid} written to {out}")
    print(f"  mask              {build.mask_source}")
    print(f"  mesh              {model.mesh.faces.shape[0]} faces, watertight, heart frame (mm)")
    shown = "unknown" if model.cardiac_phase is None else f"{model.cardiac_phase:.4f}"
    print(f"  image phase       phi_C* = {shown} ({phase_source})")
    fit = (f"cycled among {model.frame.cycle} axes up to {model.frame.axis_change_deg:.1f} deg apart, their mean"
           if model.frame.cycle else f"last change {model.frame.axis_change_deg:.3f} deg")
    print(f"  heart frame       Euler XYZ = ({e[0]:.1f}, {e[1]:.1f}, {e[2]:.1f}) deg, "
          f"{model.frame.iterations} iterations, {fit}")
    print(f"  fiducials         {len(model.fiducials_patient_mm)}")
    print("  time              " + ", ".join(f"{k} {v:.2f} s" for k, v in build.timings_s.items()))
    print(f"  picture           {picture}")
    for note in build.notes:
        print(f"  note              {note}")
    return 0


def _cmd_register(args) -> int:
    from modeling.model import read_model
    from registration.pipeline import register_session
    from registration.report import JSON_FILE as REPORT_JSON
    from registration.report import write_registration
    from registration.session import read_session

    from hrcore.output import check_output_path

    options = _registration_options(args)
    inputs = (args.model_dir, args.session_dir)
    check_output_path(args.out_dir, inputs=inputs, overwrite=args.overwrite, earlier=(REPORT_JSON,))
    model = read_model(args.model_dir)
    if args.cardiac_phase is not None:
        if not 0.0 <= args.cardiac_phase < 1.0:
            raise UsageError(f"--cardiac-phase must be a phase in [0, 1), got {args.cardiac_phase}")
        # the given phase replaces the CT's, slice by slice too
        model = dataclasses.replace(model, cardiac_phase=args.cardiac_phase, cardiac_phase_source="--cardiac-phase",
                                    slice_phases=None)
    elif model.cardiac_phase is None:
        raise UsageError(
            f"the cardiac phase of model {args.model_dir} is unknown (its CT was not ECG-gated); "
            "give the CT's phase with --cardiac-phase P (0..1, e.g. 0.7 for mid-diastole)"
        )
    session = read_session(args.session_dir)
    result = register_session(model, session, options=options, progress=not args.quiet)
    # staged, then one rename: a failure or a signal leaves OUT_DIR as it was
    paths = write_registration(result, args.out_dir, overwrite=args.overwrite, inputs=inputs, model=model,
                               view=not args.no_view, fiducials_probe_mm=session.fiducials_probe_mm)
    T = result.T_heart_from_probe
    e = result.euler_xyz_deg
    print(f"registration of {result.n_points} point(s) to a {result.n_faces}-face model, written to {args.out_dir}")
    print(f"  phases            phi_C* = {result.cardiac_phase:.4f} ({result.cardiac_phase_source}), "
          f"phi_R* = {result.respiration_phase:.2f} ({result.phase_estimates[0].method})")
    for estimate in result.phase_estimates:
        print(f"  {estimate.method:<17} {estimate.summary()}")
    print(f"  T_heart_from_probe translation ({T[0, 3]:.2f}, {T[1, 3]:.2f}, {T[2, 3]:.2f}) mm, "
          f"Euler XYZ ({e[0]:.2f}, {e[1]:.2f}, {e[2]:.2f}) deg")
    print(f"  from T0           {result.translation_distance_mm:.2f} mm, {result.rotation_distance_deg:.2f} deg")
    print(f"  errors            RMS {result.rms_mm:.3f} mm, FRE {result.fre_mm:.2f} mm, "
          f"static delta mean {result.delta_static_mean_mm:.2f} mm")
    print(f"  trust             {result.trust.summary()}" + ("; see the notes" if result.trust.reasons else ""))
    print(f"  exclusions        {len(result.exclusions)}"
          + "".join(f"\n    point {i}: {why}" for i, why in result.exclusions))
    for note in list(result.notes) + list(paths["notes"]):
        print(f"  note              {note}")
    print("  time              " + ", ".join(f"{k} {v:.2f} s" for k, v in result.timings_s.items()))
    return 0


def _interrupted_status(kind) -> int:
    """The exit status of a command that kept its output through an interruption: 143 for SIGTERM, 130 for
    Ctrl-C, as :func:`heartreg.cli.main` gives when it handles one."""
    from heartreg.cli import Terminated

    return 143 if issubclass(kind, Terminated) else 130


def _cmd_evaluate_temporal(args) -> int:
    from heartreg.temporal_eval import GRID_PRESETS, evaluate

    presets = [f"wood2018-trial{k}" for k in args.trials] if args.trials else list(GRID_PRESETS)
    say = (lambda msg: print(msg, file=sys.stderr, flush=True)) if not args.quiet else (lambda msg: None)
    result = evaluate(args.out_dir, presets=presets, seeds=range(1, args.seeds + 1), size=args.size,
                      harmonics=args.harmonics, run=not args.report_only, workers=args.workers, scheduler=args.scheduler,
                      memory_limit=args.memory_limit, progress=not args.quiet, say=say)
    for name, error in result["failed"].items():
        print(f"  {name} failed: {error}", file=sys.stderr)
    if not result["cases"]:
        print(f"heartreg evaluate-temporal: error: no case in {args.out_dir}/cases: every case failed", file=sys.stderr)
        return 1
    print(result["table"], end="")
    print(f"written to {args.out_dir} (temporal_eval.md, .csv, .json, .png)")
    return 1 if result["failed"] else 0


def _cmd_pipeline(args) -> int:
    from heartreg.pipeline import run_pipeline

    _needs_dicom_study(args, "pipeline")
    if _listed(args):
        return 0
    run = run_pipeline(
        args.study_dir, args.session_dir, args.out_dir, series=args.series, qrs=args.qrs, mask=args.mask,
        label=args.label, model_options=_model_options(args), registration_options=_registration_options(args),
        view=not args.no_view, overwrite=args.overwrite, progress=not args.quiet, option_files=_option_files(args),
    )
    reg = run.registration
    print(f"pipeline written to {run.out_dir}")
    print(f"  phi_C* = {run.phase_report.volume_cardiac_phase:.4f} ({run.phase_report.source})")
    print(f"  phi_R* = {reg.respiration_phase:.2f}, RMS {reg.rms_mm:.2f} mm, FRE {reg.fre_mm:.2f} mm, "
          f"mean delta vs static {reg.static.mean_delta_mm:.2f} mm")
    print(f"  trust  {reg.trust.summary()}")
    print(f"  report {run.paths['report']}")
    return 0


def _cmd_demo(args) -> int:
    from heartreg.demo import format_table, run_demo

    run, rows = run_demo(args.out_dir, sample_dir=args.sample, progress=not args.quiet)
    print(format_table(rows))
    missed = [r[0] for r in rows if r[5] is False]
    print(f"\nall outputs in {run.out_dir}; open {run.paths['report']} in a browser")
    print("stage times: " + ", ".join(f"{k} {v:.1f} s" for k, v in run.timings_s.items()))
    if missed:  # the demo is a check: a row outside its tolerance fails it
        print("heartreg demo: outside tolerance: " + "; ".join(missed) + f" (see {run.out_dir / 'demo_table.txt'})",
              file=sys.stderr)
        return 1
    return 0


def _cmd_reproduce(args) -> int:
    from heartreg.reproduce import reproduce

    # the output folder by its name: an absolute path (a user's, a site's) has no place on the page (an audit)
    argv = ["heartreg", "reproduce", "-o", Path(args.out_dir).resolve().name, "--size", args.size, "--seed", str(args.seed),
            "--trials", *map(str, args.trials)]
    if args.points is not None:
        argv += ["--points", str(args.points)]
    if args.step != 0.01:
        argv += ["--step", str(args.step)]
    if args.report_only:
        argv += ["--report-only"]
    result = reproduce(
        args.out_dir, size=args.size, seed=args.seed, trials=args.trials, n_points=args.points,
        phase_step=args.step, command=" ".join(argv), rerun=not args.report_only, progress=not args.quiet,
        log=None if args.quiet else (lambda msg: print(msg, file=sys.stderr)),
        workers=args.workers, scheduler=args.scheduler, memory_limit=args.memory_limit,
    )
    print((result.out_dir / "reproduction.md").read_text())
    s = result.summary
    print(f"phi_R* within 0.05 of the truth in {s['phi_r_within']} of {s['n_trials']} trial(s)"
          + (f"; misses: {', '.join(f'trial {k}' for k in s['misses'])}" if s["misses"] else ""))
    print(f"all outputs in {result.out_dir}; open {result.paths['html']} in a browser")
    print("time: " + ", ".join(f"{k} {v:.1f} s" for k, v in result.timings_s.items()))
    return 0


def _cmd_batch(args) -> int:
    from heartreg.batch import run_batch

    log = None if args.quiet else (lambda msg: print(msg, file=sys.stderr))
    try:
        result = run_batch(
            args.cohort, args.out_dir, workers=args.workers, scheduler=args.scheduler, memory_limit=args.memory_limit,
            num_parts=args.num_parts, part_id=args.part_id, progress=not args.quiet, log=log,
        )
    except KeyboardInterrupt as exc:  # not "nothing was written": the finished cases stay, and the summary
        print("heartreg batch: interrupted; the cases finished are kept in the output folder and its summary.csv: "
              "run the same command again to go on", file=sys.stderr)
        return _interrupted_status(type(exc))
    print(f"batch of {len(result.records)} case(s) in {result.out_dir}: {result.count('done')} done, "
          f"{result.count('failed')} failed, {result.count('not run')} not run ({len(result.ran)} run now)")
    for r in result.records:
        if r.status == "failed":
            print(f"  {r.case}: {r.error}")
    print(f"  summary {result.paths['summary']}, page {result.paths['index']}")
    return 1 if result.count("failed") else 0
