"""Bench: ``heartreg batch`` throughput with 1 and 2 local workers, and each worker's peak memory.

    python bench/bench_batch.py [--repeats N] [--cases 8] [--size sample|full]

The same cases (the bundled sample CT, or the full-size bench phantom, each
case ``heartreg phases`` + ``heartreg model`` with its own ``--faces``) run
through the batch's own machinery (:func:`heartreg.batch.open_client`,
:func:`heartreg.batch.run_tasks` with :func:`heartreg.batch.run_case`) on a
fresh local cluster of 1, then 2 worker processes (one thread each), into a
fresh output folder each run.  Timed: from the first case submitted to the
last record back (cases per minute); the cluster's start and the workers'
start-up (imports and the offscreen-OpenGL probe, done once by a warm-up call on every worker) are not, and are given
in the notes.  Peak memory: each worker process's own peak RSS
(``getrusage(RUSAGE_SELF).ru_maxrss``, asked of every worker after the run);
the table gives the largest.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import common


def _warm_up() -> float:
    """A worker's start-up (on a worker): import what a case needs (the modules the stages import
    on first use too) and probe offscreen OpenGL.

    The probe (a child process drawing one picture, ~3 s of CPU) runs once per
    worker process, whatever the number of cases; left in the timing, it
    falls on the first case, beside the other worker's work.  Returns the seconds.
    """
    t = time.perf_counter()
    import heartreg.cli  # noqa: F401
    import imaging.phase  # noqa: F401 - imaging's names load on first use
    import imaging.series  # noqa: F401
    import modeling  # noqa: F401
    import registration  # noqa: F401
    import fast_simplification  # noqa: F401 - what the model stage imports on first use
    import matplotlib.figure  # noqa: F401
    import pymeshlab
    import pyvista  # noqa: F401
    import skimage.measure  # noqa: F401
    from modeling.render import offscreen_available

    pymeshlab.MeshSet()  # loads its plugins (~0.7 s), once per process
    offscreen_available()
    return time.perf_counter() - t


def _peak_rss_mb() -> float:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _cohort(study: Path, n: int, folder: Path) -> Path:
    path = folder / "cohort.csv"
    lines = ["case,study,options"] + [f"c{i:02d},{study},--faces {20000 - 500 * i}" for i in range(n)]
    path.write_text("\n".join(lines) + "\n")
    return path


def _one_run(cohort: Path, workers: int) -> dict:
    from heartreg.batch import open_client, read_cohort, run_case, run_tasks

    cases = read_cohort(cohort)
    with common.scratch_dir("batch-") as out:
        t = time.perf_counter()
        with open_client(workers=workers) as client:
            t_start = time.perf_counter() - t
            imports = client.run(_warm_up)
            t = time.perf_counter()
            records = [r for _, r in run_tasks(client, run_case, cases, names=[c.name for c in cases],
                                               args=(str(out),), progress=False)]
            elapsed = time.perf_counter() - t
            peaks = client.run(_peak_rss_mb)
    failed = [r for r in records if getattr(r, "status", "failed") != "done"]
    if failed:
        raise common.BenchError(f"{len(failed)} case(s) failed: {failed[0]}")
    return {"time_s": elapsed, "start_s": t_start, "imports_s": max(imports.values()),
            "peak_mb": sorted(peaks.values())}


def main(argv=None) -> int:
    p = common.bench_argparser(__doc__.splitlines()[0])
    p.add_argument("--cases", type=int, default=8, help="cases per run (default 8)")
    p.add_argument("--size", default="sample", choices=("sample", "full"), help="sample CT or full-size CT")
    args = p.parse_args(argv)
    if args.size == "full":
        study = common.ensure_phantom_case("full_ct") / "ct"
    else:
        study = common.REPO_DIR / "sample_dicom" / "ct"
    rows, rates = [], {}
    with common.scratch_dir("batch-cohort-") as folder:
        cohort = _cohort(study, args.cases, folder)
        runs = {1: [], 2: []}
        for _ in range(args.repeats):
            for workers in (1, 2):  # interleaved: the machine's load falls on both alike
                runs[workers].append(_one_run(cohort, workers))
        for workers, done in runs.items():
            times = [r["time_s"] for r in done]
            timing = common.Runs(times_s=times, peak_mb=[max(r["peak_mb"]) for r in done],
                                 info={"runs": done})
            rates[workers] = 60 * args.cases / timing.median_s
            notes = (f"{rates[workers]:.1f} cases/min; per-worker peak "
                     f"{', '.join(f'{m:.0f}' for m in done[-1]['peak_mb'])} MB; cluster start "
                     f"{done[-1]['start_s']:.1f} s and worker start-up (imports, offscreen probe) {done[-1]['imports_s']:.1f} s not timed")
            if workers == 2:
                notes += f"; scaling {rates[2] / rates[1]:.2f}x over 1 worker"
            rows.append(common.Row(
                step=f"batch, {args.cases} {args.size} cases (phases + model), {workers} worker(s)",
                ours=timing, notes=notes,
                command=f"heartreg batch COHORT -o OUT --workers {workers}"))
    common.write_results("bench_batch", rows, command=" ".join(["python", *sys.argv]), repeats=args.repeats)
    return 0


if __name__ == "__main__":
    sys.exit(main())
