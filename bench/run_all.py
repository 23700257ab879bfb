"""Run every ``bench/bench_*.py`` and write ``bench/out/results.md``.

    python bench/run_all.py [--repeats N] [--only NAME ...]      (``make bench``)

The benches are discovered by file name (``bench_*.py`` beside this file, in
name order) and run one after another, never two at once: the machine is
shared.  Each writes ``bench/out/<name>.json``; this script gathers them into
one Markdown table (step, ours (s), reference (s), ratio, peak memory (MB),
notes) with the machine it ran on, prints it and writes ``bench/out/results.md``
and ``bench/out/results.json``.  A bench that fails is reported in the table and
makes the exit status non-zero; the others still run.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import common  # noqa: E402


def discover() -> list[Path]:
    return sorted(common.BENCH_DIR.glob("bench_*.py"))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeats", type=int, default=common.DEFAULT_REPEATS,
                   help=f"runs per step, 1..{common.MAX_REPEATS}")
    p.add_argument("--only", nargs="+", default=None, metavar="NAME",
                   help="run only these benches (e.g. imaging phantom)")
    args = p.parse_args(argv)

    common.ensure_requirements()
    common.OUT_DIR.mkdir(parents=True, exist_ok=True)
    benches = discover()
    if args.only:
        wanted = {n.removeprefix("bench_").removesuffix(".py") for n in args.only}
        benches = [b for b in benches if b.stem.removeprefix("bench_") in wanted]
    rows, failures, elapsed = [], [], {}
    for script in benches:
        print(f"== {script.name}", file=sys.stderr, flush=True)
        result = common.OUT_DIR / f"{script.stem}.json"
        result.unlink(missing_ok=True)
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, str(script), "--repeats", str(args.repeats)],
                              cwd=common.REPO_DIR, stdout=subprocess.DEVNULL)
        elapsed[script.stem] = time.perf_counter() - t0
        if result.exists():
            rows.extend(json.loads(result.read_text())["rows"])
        if proc.returncode != 0 or not result.exists():
            failures.append(script.name)
            rows.append({"step": f"{script.name} FAILED (exit {proc.returncode})", "ours": None,
                         "reference": None, "ratio": None, "notes": "see its stderr above"})

    info = common.machine_info()
    command = " ".join(["python", "bench/run_all.py", *(argv if argv is not None else sys.argv[1:])])
    table = common.markdown_table(rows)
    text = "\n".join([
        "# heartreg benchmarks",
        "",
        f"Command: `{command}` (from the repository root; `make bench` runs `bench/run_all.py`).",
        f"Machine: {common.machine_line(info)}.",
        f"Runs per step: {args.repeats}; times are the median (min in brackets), memory the largest "
        "peak RSS over the runs in MiB (ours / reference), each run in a fresh process.",
        "",
        table,
        "",
        "Bench wall time: " + ", ".join(f"{k} {v:.0f} s" for k, v in elapsed.items()),
        "",
    ])
    (common.OUT_DIR / "results.md").write_text(text)
    (common.OUT_DIR / "results.json").write_text(json.dumps(
        {"command": command, "repeats": args.repeats, "machine": info, "rows": rows}, indent=1) + "\n")
    print(text)
    if failures:
        print(f"failed: {', '.join(failures)}", file=sys.stderr)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
