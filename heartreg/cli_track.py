"""``heartreg track``'s command: the checks of its flags, the stream's source, the summary.

The maths and the log are :mod:`heartreg.track`'s; OpenIGTLink is :mod:`heartreg.igtl`'s.
"""

from __future__ import annotations

import sys

from heartreg.cli_commands import _interrupted_status
from hrcore.errors import UsageError


def _cmd_track(args) -> int:
    from registration.session import read_session

    from heartreg.igtl import igtl_client_chunks
    from heartreg.track import TrackError, load_tracker, run_track, session_chunks

    if args.speed is not None and not args.speed > 0:
        raise UsageError(f"--speed must be positive (1 = real time), got {args.speed}")
    if args.igtl_rate < 0:
        raise UsageError(f"--igtl-rate must be 0 (all samples) or a positive rate, got {args.igtl_rate}")
    if args.igtl_in is not None and args.replay is not None:
        raise UsageError("--igtl-in and --replay are two sources of the stream: give one")
    if not args.idle_timeout > 0:
        raise UsageError(f"--idle-timeout must be positive (s), got {args.idle_timeout}")
    from hrcore.output import check_output_path

    # the log never lies inside an input (it replaced registration.json), nor replaces a file without --overwrite
    check_output_path(args.log, inputs=(args.model_dir, args.registration_dir, args.session_dir, args.replay),
                      what="--log", overwrite=args.overwrite, folder=False)
    tracker, model, _ = load_tracker(args.model_dir, args.registration_dir, args.session_dir)
    trust = tracker.trust
    if trust.level.value != "ok":  # once, before the stream: every place on the map rests on it (the log says so)
        worst = max(trust.reasons, key=lambda r: r.level.rank)
        print(f"warning: registration {args.registration_dir} is trusted '{trust.summary()}': {worst.message}; "
              "every place on the map rests on it: check it before navigating on it (the log's registration_trust "
              "says so)", file=sys.stderr, flush=True)
    skipped: dict[str, int] = {}
    problems: dict[str, int] = {}  # malformed messages dropped, connections lost (counted by the client)
    if args.igtl_in is not None:
        host, _, port = args.igtl_in.rpartition(":")
        if not port.isdigit() or not 0 < int(port) <= 65535:
            raise UsageError(f"--igtl-in must be HOST:PORT with a port 1..65535, got {args.igtl_in!r}")
        chunks = igtl_client_chunks(host or "127.0.0.1", int(port), idle_timeout_s=args.idle_timeout,
                                    skipped=skipped, problems=problems)
        speed = None  # a live stream paces itself
    else:
        replay = read_session(args.replay if args.replay is not None else args.session_dir)
        if replay.sample_rate_hz != tracker.rate_hz:  # the causal filters follow the stream's own rate
            tracker = tracker.at_rate(replay.sample_rate_hz)
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
            # also with -q (no progress bar): with --igtl-port 0 the line is the only way to learn the port
            listening=lambda port: print(f"OpenIGTLink server on port {port}", flush=True),
        )
    finally:
        if bar is not None:
            bar.close()
    _print_track_summary(summary, args.log)
    for why, n in skipped.items():
        print(f"  skipped           {n} sample(s) from --igtl-in: {why}")
    for why, n in problems.items():
        print(f"  --igtl-in         {n} time(s): {why}")
    if summary.interrupted:
        return _interrupted_status(summary.interrupted_by)
    if summary.n_placed == 0:  # a run that placed nothing is no success, though its log is kept (a record)
        raise TrackError(_nothing_placed(summary, args, skipped))
    return 0


def _nothing_placed(s, args, skipped: dict) -> str:
    """Why a run placed no sample on the map, in one line."""
    source = f"--igtl-in {args.igtl_in}" if args.igtl_in is not None else "the replay"
    if s.n_samples == 0:
        why = (f"no pose arrived from {source} before it went quiet for --idle-timeout {args.idle_timeout:g} s"
               if args.igtl_in else f"{source} held no sample")
        if skipped:
            why += f"; {sum(skipped.values())} sample(s) were skipped, see above"
    elif s.n_invalid_pose == s.n_samples:
        why = (f"all {s.n_samples} poses from {source} were invalid (no rigid transform); check the tracker's "
               "RobotToTracker and ProbeToTracker transforms")
    else:
        counts = ", ".join(f"{v} {k}" for k, v in sorted(s.qualities.items(), key=lambda kv: -kv[1]))
        why = f"none of the {s.n_samples} samples could be placed (quality: {counts})"
        if s.qualities.get("no_phase"):
            why += "; the phases need an R-peak and a start of expiration: stream at least about 10 s"
    return f"nothing was placed on the map: {why}; the log {args.log} was written"


def _print_track_summary(summary, csv_path, *, file=None) -> None:
    """``heartreg track``'s summary lines (a :class:`heartreg.track_log.TrackSummary`; ``file``: stdout)."""
    file = sys.stdout if file is None else file  # the stdout of the call, not of the import
    s = summary
    rate = s.n_samples / s.wall_s if s.wall_s > 0 else float("nan")
    print(f"tracked {s.n_samples} samples ({s.n_placed} placed on the map) in {s.wall_s:.2f} s "
          f"({rate:.0f} samples/s){' - interrupted' if s.interrupted else ''}", file=file)
    print(f"  log               {csv_path}", file=file)
    if s.n_invalid_pose:
        print(f"  invalid poses     {s.n_invalid_pose} sample(s): a pose not a rigid transform (NaN or inf, rotation "
              "not orthonormal, det not +1, last row not 0 0 0 1), logged as quality 'tracker', not placed", file=file)
    if s.n_sent == 0 and s.models_sent == 0:
        print("  OpenIGTLink       nothing sent (no --igtl-port, or no client connected)", file=file)
    else:
        print(f"  OpenIGTLink       {s.n_sent} samples sent, {s.n_dropped} held back by the rate limit, "
              f"model sent {s.models_sent} time(s)", file=file)
    print(f"  R-peak latency    mean {s.r_peak_latency_ms[0]:.0f} ms, max {s.r_peak_latency_ms[1]:.0f} ms", file=file)
