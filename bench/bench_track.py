"""``heartreg track``: time per update at 100 Hz input, and the replay at full speed.

Inputs (built once, untimed, into ``bench/out/data/track_sample``): the sample
phantom case of the tests (``heartreg phantom --preset wood2018-trial1 --seed 0
--points 30``), its model (``heartreg model``), its registration (``heartreg
register --no-view``) and a 60 s navigation session
(:func:`heartreg.phantom.navigation.write_navigation`: 6000 samples at 100 Hz).

Steps, each in a fresh child (``common.run_step``; loading the model and
re-fitting the motion models is untimed):

- update at 100 Hz input: every sample of the navigation session given to
  ``Tracker.process`` on its own (a chunk of one, as a live 100 Hz stream
  delivers it): causal phases, localisation, nearest surface point.  The
  row's time is the mean per update; the notes give p50 and p99 of the wall
  time and of the thread's CPU time, and the load average (the machine is
  shared by several jobs: wall-time tails there are other jobs' time slices).
  Target (issue 13): p99 <= 1 ms.
- replay at full speed: ``run_track`` over the session replayed three times
  (18 000 samples, chunks of 2000), CSV log written, no OpenIGTLink client.
  The row's time is the whole replay; the notes give samples/s.  Target:
  >= 10 000 samples/s.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import common  # noqa: E402

ME = "bench_track"
CASE = common.DATA_DIR / "track_sample"


def ensure_inputs() -> Path:
    """Phantom case, model, registration and navigation session (once, untimed)."""
    case = CASE
    if (case / "navigation_truth.csv").exists() and (case / "registration" / "registration.json").exists():
        return case
    import shutil
    import subprocess

    if case.exists():
        shutil.rmtree(case)
    cli = common.heartreg_cli()
    steps = [
        [*cli, "phantom", case, "--preset", "wood2018-trial1", "--seed", "0", "--points", "30", "-q"],
        [*cli, "model", case / "ct", "-o", case / "model"],
        [*cli, "register", case / "model", case / "session", "-o", case / "registration", "--no-view", "-q"],
    ]
    for argv in steps:
        print("bench: " + " ".join(map(str, argv[1:])), file=sys.stderr)
        subprocess.run([str(a) for a in argv], check=True, cwd=common.REPO_DIR, stdout=subprocess.DEVNULL)
    from heartreg.phantom.navigation import write_navigation

    write_navigation(case)
    return case


def _load(case: str):
    from heartreg.track import load_tracker
    from registration.session import read_session

    tracker, model, _ = load_tracker(Path(case) / "model", Path(case) / "registration", Path(case) / "session")
    return tracker, model, read_session(Path(case) / "navigation")


def updates(case: str) -> dict:
    """Step: every sample on its own through ``Tracker.process``."""
    import numpy as np

    from heartreg.track import session_chunks

    tracker, _, nav = _load(case)
    chunks = list(session_chunks(nav, chunk=1))
    wall, cpu = [], []
    for c in chunks:
        t0, c0 = time.perf_counter(), time.thread_time()
        tracker.process(c)
        cpu.append(time.thread_time() - c0)
        wall.append(time.perf_counter() - t0)
    wall, cpu = np.array(wall) * 1e3, np.array(cpu) * 1e3
    return {
        "time_s": float(wall.mean() / 1e3),
        "n": len(chunks),
        "wall_ms": [float(wall.mean()), float(np.percentile(wall, 50)), float(np.percentile(wall, 99))],
        "cpu_ms": [float(cpu.mean()), float(np.percentile(cpu, 50)), float(np.percentile(cpu, 99))],
        "load": os.getloadavg()[0],
    }


def replay(case: str, passes: int = 3) -> dict:
    """Step: the navigation session replayed ``passes`` times at full speed."""
    import dataclasses
    import tempfile

    from heartreg.track import run_track, session_chunks

    tracker, model, nav = _load(case)

    def chunks():
        for k in range(passes):
            for c in session_chunks(nav, chunk=2000):
                yield dataclasses.replace(c, time_s=c.time_s + k * 100.0)

    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        summary = run_track(tracker, chunks(), Path(tmp) / "log.csv", model=model)
        dt = time.perf_counter() - t0
    return {"time_s": dt, "n": summary.n_samples, "rate": summary.n_samples / dt, "load": os.getloadavg()[0]}


def main(argv=None) -> int:
    args = common.bench_argparser(__doc__.splitlines()[0]).parse_args(argv)
    case = ensure_inputs()
    rows = []
    up = common.run_step(f"{ME}:updates", {"case": str(case)}, repeats=args.repeats)
    i = up.info
    rows.append(common.Row(
        "track: one update at 100 Hz input (causal phases + map position + nearest surface point)", up,
        notes=(f"{i['n']} updates; wall mean/p50/p99 {i['wall_ms'][0]:.3f}/{i['wall_ms'][1]:.3f}/"
               f"{i['wall_ms'][2]:.3f} ms, CPU {i['cpu_ms'][0]:.3f}/{i['cpu_ms'][1]:.3f}/{i['cpu_ms'][2]:.3f} ms; "
               f"load average {i['load']:.1f} on {os.cpu_count()} cores; target p99 <= 1 ms"),
    ))
    rp = common.run_step(f"{ME}:replay", {"case": str(case)}, repeats=args.repeats)
    rows.append(common.Row(
        "track: replay at full speed, CSV log (18 000 samples)", rp,
        notes=f"{rp.info['rate']:.0f} samples/s (last run); load average {rp.info['load']:.1f}; target >= 10 000",
    ))
    common.write_results(ME, rows, command=common.command_line(), repeats=args.repeats)
    return 0


if __name__ == "__main__":
    sys.exit(main())
