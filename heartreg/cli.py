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
    print(f"  truth            {out / 'truth.json'}")
    return 0


def _series_arg(value: str):
    """``--series``: an index from ``--list-series`` or a SeriesInstanceUID."""
    return int(value) if value.isdigit() else value


def _open_study(args):
    """Load the study's volume and compute its phase report (shared by commands)."""
    from imaging import compute_phase_report, load_study, read_ecg_waveform, read_qrs_file
    from imaging.waveform import WaveformError

    volume = load_study(args.study_dir, series=args.series, progress=not args.quiet)
    qrs = read_qrs_file(args.qrs) if args.qrs else None
    records = []
    for path in volume.waveform_files:
        try:
            records.append(read_ecg_waveform(path))
        except WaveformError as exc:
            print(f"note: {exc}", file=sys.stderr)
    report = compute_phase_report(
        volume, qrs_s=qrs, qrs_label=f"R-peak file {Path(args.qrs).name}" if args.qrs else "",
        ecg_records=records,
    )
    return volume, report


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

    if args.list_series:
        return _print_series(args.study_dir)
    if args.out_dir is None:
        raise ValueError("give an output folder with -o OUT_DIR (or --list-series)")
    volume, report = _open_study(args)
    extra = {
        "series_instance_uid": volume.series.series_instance_uid,
        "series_description": volume.series.description,
        "volume_notes": list(volume.notes),
    }
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
    p.add_argument("--overwrite", action="store_true", help="replace existing phantom outputs")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_phantom)

    p = sub.add_parser("phases", help="cardiac phase of every CT slice (paper Fig. 4)")
    _add_study_options(p)
    p.add_argument("-o", "--out-dir", type=Path, default=None, help="folder for phases.csv/json/png")
    p.set_defaults(func=_cmd_phases)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command line; return the exit status."""
    parser = _build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help(sys.stderr)
        return EXIT_USAGE
    try:
        return args.func(args)
    except (ValueError, OSError) as exc:
        if args.debug:
            raise
        print(f"heartreg {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("heartreg: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
