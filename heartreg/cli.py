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
