"""The ``heartreg`` command line.

One function per subcommand (:mod:`heartreg.cli_commands`, ``track``'s in
:mod:`heartreg.cli_track`): parse (:mod:`heartreg.cli_parser`), call the
library, write files.  Logs and progress go to stderr, summaries to stdout.
The project's errors are caught here and printed as one line on stderr with a
non-zero exit status (``--debug`` shows the traceback instead).
"""

from __future__ import annotations

import argparse
import os
import sys

# Before numpy is imported (it reads this once): no transparent huge pages asked for numpy's arrays.  numpy
# advises them for every array of 4 MB or more; where the kernel then defragments memory on the page fault
# (/sys/kernel/mm/transparent_hugepage/defrag 'madvise', a common default) a process that has just read a
# CT's files stalls on its first touch of each new volume-sized array, and the segmentation makes dozens:
# the full-size model's mask stage took 3.0-3.6 s with them, 1.9-2.2 s without (bench/README.md).  A value
# the user set is kept; the Dask workers of `batch` inherit it.
os.environ.setdefault("NUMPY_MADVISE_HUGEPAGE", "0")

from heartreg import __version__  # noqa: E402 (after the environment above)
from heartreg.cli_parser import _build_parser  # noqa: E402
from hrcore.errors import HeartregError, UsageError  # noqa: E402

__all__ = ["CommandLineError", "command_parser", "main"]

EXIT_USAGE = 2
EXIT_BUG = 70  # EX_SOFTWARE
EXIT_PIPE = 141  # 128 + SIGPIPE: the reader of the output left, as `yes | head` ends `yes`


class CommandLineError(UsageError):
    """A command line that does not parse (``heartreg batch`` checks its cases' lines with it)."""


def command_parser() -> argparse.ArgumentParser:
    """The parser ``main`` uses, raising :class:`CommandLineError` instead of exiting.

    ``heartreg batch`` parses and runs each case's single commands with it, so
    a case runs exactly the code of the command typed by hand.
    """
    parser = _build_parser()

    def fail(message):
        raise CommandLineError(message)

    for p in _all_parsers(parser):
        p.error = fail
    return parser


def _all_parsers(parser) -> list:
    """The parser and its subcommands' parsers."""
    parsers = [parser]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            parsers.extend(action.choices.values())
    return parsers


def _usage_error_in_one_line(parser) -> None:
    """A command line that does not parse: one line naming the argument, status 2."""

    def error(message):
        sys.stderr.write(f"{parser.prog}: error: {message} (see {parser.prog} --help)\n")
        sys.exit(EXIT_USAGE)

    parser.error = error


def _one_line_warning(message, category, filename, lineno, line=None) -> str:
    """``warning: MESSAGE``, on a line of its own: after a progress bar's text when a bar is drawn (it ran on
    from it, 'model:   0%| ... mask]warning: ...', an audit; the bar is drawn again below it)."""
    from hrcore.redact import pseudonymize_uids

    bars = getattr(getattr(sys.modules.get("tqdm"), "tqdm", None), "_instances", ())
    return ("\n" if bars else "") + f"warning: {pseudonymize_uids(str(message))}\n"  # no study's UID printed


class Terminated(KeyboardInterrupt):
    """SIGTERM, turned into an exception so that every staging folder is removed."""


def _on_sigterm(signum, frame):
    raise Terminated


def _interruption(exc: BaseException) -> KeyboardInterrupt | None:
    """The KeyboardInterrupt (or :class:`Terminated`) behind ``exc``, if any: a signal that arrives while
    an extension module initialises comes back as that import's error ("initialization failed")."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


def _reader_gone() -> bool:
    """Whether standard output is a pipe whose reader has left (``heartreg ... | head``);
    if so, further output goes to the null device (no second error at exit)."""
    import os
    import select

    try:
        fd = sys.stdout.fileno()
        poll = select.poll()
        poll.register(fd, 0)  # a pipe without reader reports an error to its writer
        gone = any(events & select.POLLERR for _, events in poll.poll(0))
    except (AttributeError, OSError, ValueError):  # no poll (Windows), no file descriptor
        return False
    if gone:
        null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(null, fd)
        os.close(null)
    return gone


def main(argv: list[str] | None = None) -> int:
    """Run the command line; return the exit status.

    Refusals of bad input (:class:`HeartregError`) and OS errors are one line on
    stderr and status 1; any other exception is a bug: its traceback and status
    70.  Output piped into a reader that leaves early (``| head``) ends the
    command quietly with 141, as other programs.  SIGINT (Ctrl-C) gives 130 and
    SIGTERM 143, after every staged output has been removed, also while the
    command line is still being read (its imports).
    """
    try:
        return _main(argv)
    except Terminated:
        print("heartreg: terminated (SIGTERM); nothing was written", file=sys.stderr)
        return 143
    except KeyboardInterrupt:
        print("heartreg: interrupted; nothing was written", file=sys.stderr)
        return 130


def run() -> None:
    """The ``heartreg`` program (console script, ``python -m heartreg``): :func:`main`, then exit.

    After an interruption the process ends at once with 130 or 143, its outputs
    already cleaned up: CPython marks a KeyboardInterrupt raised inside code that
    an extension runs through ``PyRun_String`` as unhandled even when
    :func:`main` catches it, and would then end the process by SIGINT (-2)
    instead of the status (1 in 45 interrupts during ``register``'s write).
    """
    import os
    import signal

    for stream in (sys.stdout, sys.stderr):  # a path the terminal cannot encode is escaped, not a crash after the work
        if hasattr(stream, "reconfigure"):
            stream.reconfigure(errors="backslashreplace")
    status = main()
    for sig in (signal.SIGINT, signal.SIGTERM):  # done, outputs whole: a signal now would only change the status
        signal.signal(sig, signal.SIG_IGN)
    if status in (130, 143):
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(status)
    sys.exit(status)


def _main(argv: list[str] | None) -> int:
    import signal
    import threading

    in_main = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _on_sigterm) if in_main else None  # before the parser's imports (~1 s)
    try:
        return _parse_and_run(argv, in_main)
    finally:
        if in_main:
            signal.signal(signal.SIGTERM, previous)


def _parse_and_run(argv: list[str] | None, in_main: bool) -> int:
    import warnings

    parser = _build_parser()
    for p in _all_parsers(parser):
        _usage_error_in_one_line(p)
    args, extra = parser.parse_known_args(argv)
    if extra:  # named by the command they were given to, not by 'heartreg' (an audit)
        where = f"heartreg {args.command}" if args.command else "heartreg"
        sys.stderr.write(f"{where}: error: unrecognized arguments: {' '.join(extra)} (see {where} --help)\n")
        sys.exit(EXIT_USAGE)
    if args.command is None:
        parser.print_help(sys.stderr)
        return EXIT_USAGE
    format_warning = warnings.formatwarning
    warnings.formatwarning = _one_line_warning
    from hrcore.output import defer_interrupt, raise_deferred_interrupt, refusal_line, take_deferred_interrupt

    unraisable = sys.unraisablehook

    def keep_interrupts(args):  # a signal that lands in a garbage collector's callback is not lost
        if isinstance(args.exc_value, KeyboardInterrupt):
            defer_interrupt(args.exc_value)
        else:
            unraisable(args)

    if in_main:
        defer_interrupt(None)
        sys.unraisablehook = keep_interrupts
    try:
        try:
            status = args.func(args)
            raise_deferred_interrupt()
            return status
        except Exception as exc:
            interrupt = _interruption(exc) or (take_deferred_interrupt() if in_main else None)
            if interrupt is not None:  # to main's handler: 130 or 143, no traceback
                raise interrupt from None
            raise
    except (HeartregError, OSError) as exc:
        if args.debug:
            raise
        if isinstance(exc, BrokenPipeError) and _reader_gone():
            return EXIT_PIPE  # quietly, as other programs: the outputs are complete, only the summary is lost
        print(f"heartreg {args.command}: error: {refusal_line(exc)}", file=sys.stderr)
        return 1
    except MemoryError as exc:
        if args.debug:
            raise
        print(f"heartreg {args.command}: error: out of memory ({' '.join(str(exc).split()) or 'no detail'}); "
              "nothing was written; free memory or ask for less (a coarser --step, fewer --faces)", file=sys.stderr)
        return 1
    except Exception:  # not a refusal of bad input: a bug, shown in full
        import traceback

        traceback.print_exc()
        print(f"heartreg {args.command}: internal error (a bug in heartreg {__version__}); please report it "
              "with the traceback above and the command line", file=sys.stderr)
        return EXIT_BUG
    finally:
        warnings.formatwarning = format_warning
        if in_main:
            sys.unraisablehook = unraisable
            defer_interrupt(None)  # nothing kept past this command


if __name__ == "__main__":  # pragma: no cover
    run()
