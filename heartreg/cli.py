"""The ``heartreg`` command line.

One function per subcommand: parse, call the library, write files.  Logs and
progress go to stderr, summaries to stdout.  The project's errors are caught
here and printed as one line on stderr with a non-zero exit status
(``--debug`` shows the traceback instead).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from heartreg import __version__

__all__ = ["main"]

EXIT_USAGE = 2


def _cmd_phantom(args) -> int:
    from heartreg.phantom.generate import make_phantom

    if args.navigation and args.no_session:
        raise ValueError("--navigation needs the session: drop --no-session")
    overrides = {}
    if args.points is not None:
        overrides["n_points"] = args.points
    truth = make_phantom(
        args.out_dir,
        preset=args.preset,
        size=args.size,
        seed=args.seed,
        session=not args.no_session,
        progress=not args.quiet,
        overwrite=args.overwrite,
        **overrides,
    )
    out = Path(args.out_dir)
    print(f"phantom {truth['preset']} ({truth['size']}, seed {truth['seed']}) written to {out}")
    print(f"  CT slices        {len(truth['slice_cardiac_phase'])} in {out / 'ct'}")
    print(f"  image phase      phi_C* = {truth['cardiac_phase']:.4f}, phi_R* = {truth['respiration_phase']:.2f}")
    if "session" in truth:
        print(f"  session points   {len(truth['session']['points'])} in {out / 'session'}")
    if args.navigation:
        from heartreg.phantom.navigation import write_navigation

        nav = write_navigation(out)
        print(f"  navigation       {nav.time_s.size} samples in {out / 'navigation'}, truth {out / 'navigation_truth.csv'}")
    print(f"  truth            {out / 'truth.json'}")
    return 0


def _series_arg(value: str):
    """``--series``: an index from ``--list-series`` or a SeriesInstanceUID."""
    return int(value) if value.isdigit() else value


def _open_study(args):
    """Load the study's volume and compute its phase report (shared by commands)."""
    from heartreg.pipeline import open_study

    return open_study(
        args.study_dir, series=args.series, qrs=args.qrs, progress=not args.quiet,
        warn=lambda msg: print(msg, file=sys.stderr),
    )


def _print_series(study_dir) -> int:
    from imaging import list_series

    for s in list_series(study_dir):
        print(
            f"[{s.index}] {s.uid}  {s.modality:<3} {s.n_slices:>4} images  "
            f"{s.orientation:<8} {s.description!r}  {s.kind}{(' - ' + s.reason) if s.reason else ''}"
        )
    return 0


def _cmd_phases(args) -> int:
    from imaging import write_phase_report

    from heartreg.pipeline import check_out_dir, phase_report_extra

    if args.list_series:
        return _print_series(args.study_dir)
    if args.out_dir is None:
        raise ValueError("give an output folder with -o OUT_DIR (or --list-series)")
    check_out_dir(args.out_dir)
    volume, report = _open_study(args)
    extra = phase_report_extra(volume, args.study_dir)
    paths = write_phase_report(report, args.out_dir, extra=extra)
    lo, hi = 0.6, 0.8
    print(f"{report.n_slices} slices of series {volume.series.series_instance_uid}")
    print(f"  R-peak source     {report.source}")
    print(f"  clock             {report.clock}")
    print(f"  volume phase      {report.volume_cardiac_phase:.4f} (mean), {report.circular_mean_phase:.4f} (circular mean)")
    print(f"  slice phases      {report.phases.min():.3f} .. {report.phases.max():.3f}, "
          f"{100 * report.fraction_in_window:.0f} % inside {lo}-{hi}, {len(report.jumps)} jump(s)")
    print(f"  written           {', '.join(str(p) for p in paths.values())}")
    return 0


def _cmd_model(args) -> int:
    from modeling import build_heart_model, offscreen_available, render_model_png, write_model

    if args.list_series:
        return _print_series(args.study_dir)
    from heartreg.pipeline import check_out_dir

    if args.label is not None and args.mask is None:
        raise ValueError("--label chooses a label of --mask; give the label map with --mask FILE")
    check_out_dir(args.out_dir, what="model folder", must_be_empty=not args.overwrite)
    volume, report = _open_study(args)
    from tqdm import tqdm

    # the stages of build_heart_model (mask, mesh, fiducials, frame), then the write
    bar = tqdm(total=5, desc="model", disable=args.quiet, file=sys.stderr, leave=False)

    def stage(name: str) -> None:  # a stage starts: the one before it is done
        bar.update(0 if name == "mask" else 1)
        bar.set_postfix_str(name)

    build = build_heart_model(
        volume,
        cardiac_phase=report.volume_cardiac_phase,
        cardiac_phase_source=report.source,
        mask_path=args.mask,
        label=args.label,
        target_faces=args.faces,
        expected_fiducials=None if args.fiducials == 0 else args.fiducials,
        fiducial_floor_hu=args.fiducial_floor_hu,
        trim_vessels=not args.keep_vessels,
        progress=stage,
    )
    stage("write")
    out = write_model(build.model, args.out_dir, overwrite=args.overwrite)
    bar.update(1)
    bar.close()
    model = build.model
    picture = "skipped (no offscreen OpenGL: install libosmesa6 or libegl1)"
    if offscreen_available():
        picture = str(render_model_png(model, out / "model.png"))
    e = model.frame.euler_xyz_deg
    print(f"heart model of series {volume.series.series_instance_uid} written to {out}")
    print(f"  mask              {build.mask_source}")
    print(f"  mesh              {model.mesh.faces.shape[0]} faces, watertight, heart frame (mm)")
    print(f"  image phase       phi_C* = {model.cardiac_phase:.4f} ({report.source})")
    print(f"  heart frame       Euler XYZ = ({e[0]:.1f}, {e[1]:.1f}, {e[2]:.1f}) deg, "
          f"{model.frame.iterations} iterations, last change {model.frame.axis_change_deg:.3f} deg")
    print(f"  fiducials         {len(model.fiducials_patient_mm)}")
    print("  time              " + ", ".join(f"{k} {v:.2f} s" for k, v in build.timings_s.items()))
    print(f"  picture           {picture}")
    return 0


def _cmd_register(args) -> int:
    from modeling.model import read_model
    from registration.pipeline import register_session
    from registration.report import write_registration
    from registration.session import read_session

    from heartreg.pipeline import check_out_dir

    out = check_out_dir(args.out_dir, must_be_empty=not args.overwrite)
    model = read_model(args.model_dir)
    session = read_session(args.session_dir)
    for stale in [*out.glob("fig*.png"), *out.glob("*sweep.csv"), out / "registration.json"]:
        stale.unlink(missing_ok=True)  # --overwrite: no file of an earlier run stays beside the new ones
    harmonics = tuple(args.harmonics) if args.harmonics else (5, 4, 2, 1)
    result = register_session(
        model, session, harmonics=harmonics, phase_step=args.step, progress=not args.quiet,
    )
    paths = write_registration(result, args.out_dir, model=model, view=not args.no_view)
    T = result.T_heart_from_probe
    e = result.euler_xyz_deg
    print(f"registration of {result.n_points} point(s) to a {result.n_faces}-face model, written to {args.out_dir}")
    print(f"  phases            phi_C* = {result.phase_c:.4f} ({result.phase_c_source}), "
          f"phi_R* = {result.phase_r:.2f} (eq. 10)")
    print(f"  T_heart_from_probe translation ({T[0, 3]:.2f}, {T[1, 3]:.2f}, {T[2, 3]:.2f}) mm, "
          f"Euler XYZ ({e[0]:.2f}, {e[1]:.2f}, {e[2]:.2f}) deg")
    print(f"  from T0           {result.translation_distance_mm:.2f} mm, {result.rotation_distance_deg:.2f} deg")
    print(f"  errors            RMS {result.rms_mm:.3f} mm, FRE {result.fre_mm:.2f} mm, "
          f"static delta mean {result.delta_static_mean_mm:.2f} mm")
    print(f"  exclusions        {len(result.exclusions)}"
          + "".join(f"\n    point {i}: {why}" for i, why in result.exclusions))
    for note in list(result.notes) + list(paths["notes"]):
        print(f"  note              {note}")
    print("  time              " + ", ".join(f"{k} {v:.2f} s" for k, v in result.timings_s.items()))
    return 0


def _cmd_track(args) -> int:
    from registration.session import read_session

    from heartreg.igtl import igtl_client_chunks
    from heartreg.track import load_tracker, print_summary, run_track, session_chunks

    if args.speed is not None and not args.speed > 0:
        raise ValueError(f"--speed must be positive (1 = real time), got {args.speed}")
    tracker, model, _ = load_tracker(args.model_dir, args.registration_dir, args.session_dir)
    if args.igtl_in is not None:
        host, _, port = args.igtl_in.rpartition(":")
        if not port.isdigit():
            raise ValueError(f"--igtl-in must be HOST:PORT, got {args.igtl_in!r}")
        chunks = igtl_client_chunks(host or "127.0.0.1", int(port), idle_timeout_s=args.idle_timeout)
        speed = None  # a live stream paces itself
    else:
        replay = read_session(args.replay if args.replay is not None else args.session_dir)
        chunks = session_chunks(replay, chunk=1 if args.speed is not None else 2000)
        speed = args.speed
    bar = None
    if not args.quiet:
        from tqdm import tqdm

        bar = tqdm(desc="track", unit="sample", leave=False)
    try:
        summary = run_track(
            tracker, chunks, args.log, model=model, speed=speed, igtl_port=args.igtl_port,
            igtl_rate_hz=args.igtl_rate if args.igtl_rate > 0 else None, wait_client_s=args.wait_client,
            progress=None if bar is None else (lambda rows: bar.update(len(rows.time_s))),
        )
    finally:
        if bar is not None:
            bar.close()
    print_summary(summary, args.log)
    return 130 if summary.interrupted else 0


def _cmd_pipeline(args) -> int:
    from heartreg.pipeline import run_pipeline

    run = run_pipeline(
        args.study_dir, args.session_dir, args.out_dir, series=args.series, qrs=args.qrs, mask=args.mask,
        label=args.label, faces=args.faces, fiducials=args.fiducials, phase_step=args.step,
        overwrite=args.overwrite, progress=not args.quiet,
    )
    reg = run.registration
    print(f"pipeline written to {run.out_dir}")
    print(f"  phi_C* = {run.phase_report.volume_cardiac_phase:.4f} ({run.phase_report.source})")
    print(f"  phi_R* = {reg.phase_r:.2f}, RMS {reg.rms_mm:.2f} mm, FRE {reg.fre_mm:.2f} mm, "
          f"mean delta vs static {reg.static.mean_delta_mm:.2f} mm")
    print(f"  report {run.paths['report']}")
    return 0


def _cmd_demo(args) -> int:
    from heartreg.demo import format_table, run_demo

    run, rows = run_demo(args.out_dir, sample_dir=args.sample, progress=not args.quiet)
    print(format_table(rows))
    missed = [r[0] for r in rows if r[5] is False]
    print(f"\nall outputs in {run.out_dir}; open {run.paths['report']} in a browser")
    print("stage times: " + ", ".join(f"{k} {v:.1f} s" for k, v in run.timings_s.items()))
    if missed:
        print("outside tolerance: " + "; ".join(missed))
    return 0


def _cmd_reproduce(args) -> int:
    from heartreg.reproduce import reproduce

    argv = ["heartreg", "reproduce", "-o", str(args.out_dir), "--size", args.size, "--seed", str(args.seed),
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
    )
    print((result.out_dir / "reproduction.md").read_text())
    s = result.summary
    print(f"phi_R* within 0.05 of the truth in {s['phi_r_within']} of {s['n_trials']} trial(s)"
          + (f"; misses: {', '.join(f'trial {k}' for k in s['misses'])}" if s["misses"] else ""))
    print(f"all outputs in {result.out_dir}; open {result.paths['html']} in a browser")
    print("time: " + ", ".join(f"{k} {v:.1f} s" for k, v in result.timings_s.items()))
    return 0


def _add_study_options(p) -> None:
    p.add_argument("study_dir", type=Path, help="folder holding the DICOM study (searched recursively)")
    p.add_argument("--qrs", type=Path, default=None,
                   help="R-peak times, CSV with column time_s (seconds after midnight, AcquisitionTime clock)")
    p.add_argument("--series", type=_series_arg, default=None,
                   help="series to use: index from --list-series or SeriesInstanceUID (default: automatic)")
    p.add_argument("--list-series", action="store_true", help="list the series found and exit")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")


def _build_parser() -> argparse.ArgumentParser:
    from heartreg.phantom.config import PRESETS, SIZES

    parser = argparse.ArgumentParser(
        prog="heartreg",
        description="Beating-heart registration for organ-mounted robots (Wood et al. 2018).",
    )
    parser.add_argument("--version", action="version", version=f"heartreg {__version__}")
    parser.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    p = sub.add_parser("phantom", help="write a synthetic beating-heart case (CT, session, truth)")
    p.add_argument("out_dir", type=Path, help="output folder")
    p.add_argument("--preset", default="default", choices=sorted(PRESETS), help="phantom settings")
    p.add_argument("--size", default="sample", choices=sorted(SIZES), help="CT grid size")
    p.add_argument("--seed", type=int, default=0, help="random seed (same seed, same bytes)")
    p.add_argument("--points", type=int, default=None, help="number of robot attachment points")
    p.add_argument("--no-session", action="store_true", help="write the CT study only")
    p.add_argument("--navigation", action="store_true",
                   help="also a 60 s navigation session (the robot crawling) and its truth, for heartreg track")
    p.add_argument("--overwrite", action="store_true", help="replace existing phantom outputs")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_phantom)

    p = sub.add_parser("phases", help="cardiac phase of every CT slice (paper Fig. 4)")
    _add_study_options(p)
    p.add_argument("-o", "--out-dir", type=Path, default=None, help="folder for phases.csv/json/png")
    p.set_defaults(func=_cmd_phases)

    p = sub.add_parser("model", help="CT study -> heart model in the heart-centric frame")
    _add_study_options(p)
    p.add_argument("-o", "--out-dir", type=Path, required=True, help="model folder to write")
    p.add_argument("--mask", type=Path, default=None,
                   help="external label map (NIfTI, NRRD or DICOM SEG) instead of the automatic segmentation")
    p.add_argument("--label", type=int, default=None, help="heart label in --mask")
    p.add_argument("--faces", type=int, default=20000, help="faces of the decimated mesh")
    p.add_argument("--fiducials", type=int, default=9, help="skin fiducials expected (0: none)")
    p.add_argument("--fiducial-floor-hu", type=float, default=None, help="HU above which fiducial excess density counts")
    p.add_argument("--keep-vessels", action="store_true",
                   help="keep the great-vessel stubs (do not trim them off the base)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing model folder")
    p.set_defaults(func=_cmd_model)

    p = sub.add_parser("pipeline", help="study + session -> phases, model, registration, report.html")
    _add_study_options(p)
    p.add_argument("session_dir", type=Path, help="intra-operative session folder (docs/formats.md)")
    p.add_argument("-o", "--out-dir", type=Path, required=True, help="output folder")
    p.add_argument("--mask", type=Path, default=None, help="external label map instead of the segmentation")
    p.add_argument("--label", type=int, default=None, help="heart label in --mask")
    p.add_argument("--faces", type=int, default=20000, help="faces of the decimated mesh")
    p.add_argument("--fiducials", type=int, default=9, help="skin fiducials expected")
    p.add_argument("--step", type=float, default=0.01, help="respiration phase step of the sweep")
    p.add_argument("--overwrite", action="store_true", help="replace an existing model folder")
    p.set_defaults(func=_cmd_pipeline)

    p = sub.add_parser("demo", help="the whole chain on the bundled sample, recovered vs truth")
    p.add_argument("-o", "--out-dir", type=Path, default=Path("demo_out"), help="output folder (default demo_out)")
    p.add_argument("--sample", type=Path, default=None, help="phantom case to use instead of sample_dicom/")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=_cmd_demo)

    p = sub.add_parser("register", help="register a session to a heart model in space and phase")
    p.add_argument("model_dir", type=Path, help="heart model folder (heartreg model)")
    p.add_argument("session_dir", type=Path, help="session folder (heartreg-session)")
    p.add_argument("-o", "--out-dir", type=Path, required=True, help="folder for registration.json, CSVs, PNGs")
    p.add_argument("--step", type=float, default=0.01, help="phase step of the sweeps (default 0.01)")
    p.add_argument("--harmonics", type=int, nargs=4, metavar=("HC", "HR", "HMC", "HMR"), default=None,
                   help="Fourier harmonics of the motion models (default 5 4 2 1)")
    p.add_argument("--no-view", action="store_true", help="skip the 3-D view (fig8_view.png)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.add_argument("--overwrite", action="store_true", help="replace the files of an earlier registration in OUT_DIR")
    p.set_defaults(func=_cmd_register)

    p = sub.add_parser("track", help="the robot on the map, live: causal phases, CSV log, OpenIGTLink to Slicer")
    p.add_argument("model_dir", type=Path, help="heart model folder (heartreg model)")
    p.add_argument("registration_dir", type=Path, help="registration folder (heartreg register)")
    p.add_argument("session_dir", type=Path,
                   help="the session the registration was made from (its records give the motion models)")
    p.add_argument("--replay", type=Path, default=None,
                   help="session folder to replay as the pose stream (default SESSION_DIR)")
    p.add_argument("--igtl-in", default=None, metavar="HOST:PORT",
                   help="take the stream from an OpenIGTLink server instead (docs/formats.md)")
    p.add_argument("--idle-timeout", type=float, default=5.0, help="--igtl-in: end after this many idle seconds")
    p.add_argument("--speed", type=float, default=None,
                   help="replay pacing: 1 = real time, 2 = twice as fast (default: as fast as possible)")
    p.add_argument("--log", type=Path, required=True, help="CSV log to write (one row per sample)")
    p.add_argument("--igtl-port", type=int, default=None,
                   help="serve OpenIGTLink to Slicer on this port (18944 is Slicer's default; 0: any free)")
    p.add_argument("--igtl-rate", type=float, default=100.0,
                   help="most samples per second sent over OpenIGTLink (0: all)")
    p.add_argument("--wait-client", type=float, default=0.0,
                   help="seconds to wait for an OpenIGTLink client before the stream starts")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_track)

    p = sub.add_parser("reproduce", help="the paper's experiment on the six phantom presets, beside its numbers")
    p.add_argument("-o", "--out-dir", type=Path, required=True, help="output folder (phantom cases reused)")
    p.add_argument("--size", default="full", choices=sorted(SIZES), help="phantom CT grid (default full)")
    p.add_argument("--seed", type=int, default=0, help="phantom seed of every trial")
    p.add_argument("--trials", type=int, nargs="+", default=[1, 2, 3, 4, 5, 6], metavar="N",
                   help="trials of Table 1 to run (default all six)")
    p.add_argument("--points", type=int, default=None, help="attachment points per session instead of Table 1's")
    p.add_argument("--step", type=float, default=0.01, help="phase step of the sweeps (default 0.01)")
    p.add_argument("--report-only", action="store_true",
                   help="re-draw the tables, figures and page from an earlier run in OUT_DIR; run nothing")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=_cmd_reproduce)
    return parser


def _one_line_warning(message, category, filename, lineno, line=None) -> str:
    return f"warning: {message}\n"


def main(argv: list[str] | None = None) -> int:
    """Run the command line; return the exit status."""
    import warnings

    parser = _build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help(sys.stderr)
        return EXIT_USAGE
    format_warning = warnings.formatwarning
    warnings.formatwarning = _one_line_warning
    try:
        return args.func(args)
    except (ValueError, OSError, RuntimeError) as exc:
        if args.debug:
            raise
        print(f"heartreg {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("heartreg: interrupted", file=sys.stderr)
        return 130
    finally:
        warnings.formatwarning = format_warning


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
