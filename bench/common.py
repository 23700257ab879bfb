"""Shared helpers of the benches: timing, peak memory, results as JSON and Markdown.

Every measured run happens in a **fresh child process**, so its peak memory is
its own: the parent waits for the child with :func:`os.wait4`, whose rusage is
that one child's (with its own waited-for children), i.e. what
``resource.getrusage(RUSAGE_CHILDREN).ru_maxrss`` reports in a parent that has
no other children.  ``ru_maxrss`` is in KiB on Linux.

Two kinds of measured step:

- :func:`run_command`: a command line (e.g. ``heartreg phantom ...``).  The wall
  time is taken in the parent around the whole child, interpreter start-up and
  imports included: what a user waits for.
- :func:`run_step`: a Python function ``module:function`` run by
  ``bench/_worker.py`` in a child.  The worker imports the listed modules first,
  then times only the call (or the function reports its own ``time_s``), so
  import time is not counted; the peak memory is the child's whole peak,
  libraries included, and the worker also reports the resident size just before
  the call (``baseline_mb``).

Results: :func:`write_results` writes ``bench/out/<bench>.json``;
:func:`markdown_table` renders rows as the README's table.  Nothing here is a
test: benches measure, they never assert speed.
"""

from __future__ import annotations

import contextlib
import json
import os
import platform
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

BENCH_DIR = Path(__file__).resolve().parent
REPO_DIR = BENCH_DIR.parent
OUT_DIR = BENCH_DIR / "out"
DATA_DIR = OUT_DIR / "data"
REQUIREMENTS = BENCH_DIR / "requirements.txt"
WORKER = BENCH_DIR / "_worker.py"
DEFAULT_REPEATS = 3
MAX_REPEATS = 3  # the machine is shared: never more than this
TABLE_COLUMNS = ("step", "ours (s)", "reference (s)", "ratio", "peak memory (MB)", "notes")

__all__ = [
    "BENCH_DIR",
    "DATA_DIR",
    "OUT_DIR",
    "REPO_DIR",
    "BenchError",
    "Row",
    "Runs",
    "bench_argparser",
    "ensure_phantom_case",
    "ensure_requirements",
    "machine_info",
    "markdown_table",
    "run_command",
    "run_step",
    "run_steps_interleaved",
    "time_callable",
    "warm_page_cache",
    "write_results",
]


class BenchError(RuntimeError):
    """A measured step failed (the message holds the command and its stderr tail)."""


# ---------------------------------------------------------------- requirements


def _requirement_names(path: Path = REQUIREMENTS) -> list[str]:
    names = []
    for line in path.read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if not line or line.startswith("-"):
            continue
        m = re.match(r"[A-Za-z0-9][A-Za-z0-9._-]*", line)
        if m:
            names.append(m.group(0))
    return names


def ensure_requirements(path: Path = REQUIREMENTS) -> list[str]:
    """Install ``bench/requirements.txt`` into this interpreter's environment when
    any of its distributions is missing; return the names that were missing.

    They are bench-only reference tools, never heartreg dependencies.
    """
    from importlib import metadata

    missing = []
    for name in _requirement_names(path):
        try:
            metadata.distribution(name)
        except metadata.PackageNotFoundError:
            missing.append(name)
    if missing:
        print(f"bench: installing bench requirements ({', '.join(missing)}) from {path}", file=sys.stderr)
        subprocess.run([sys.executable, "-m", "pip", "install", "-q", "-r", str(path)], check=True)
    return missing


# ---------------------------------------------------------------- measuring


@dataclass
class Runs:
    """Repeated runs of one step: wall times in s and peak RSS per run in MB."""

    times_s: list[float]
    peak_mb: list[float] = field(default_factory=list)
    info: dict = field(default_factory=dict)  # what the last run's step reported

    @property
    def median_s(self) -> float:
        return statistics.median(self.times_s)

    @property
    def min_s(self) -> float:
        return min(self.times_s)

    @property
    def peak_max_mb(self) -> float | None:
        return max(self.peak_mb) if self.peak_mb else None

    def to_dict(self) -> dict:
        return {
            "times_s": self.times_s,
            "median_s": self.median_s,
            "min_s": self.min_s,
            "peak_mb": self.peak_mb,
            "peak_max_mb": self.peak_max_mb,
            "info": self.info,
        }


def _check_repeats(repeats: int) -> int:
    repeats = int(repeats)
    if not 1 <= repeats <= MAX_REPEATS:
        raise ValueError(f"repeats must be 1..{MAX_REPEATS} on this shared machine, got {repeats}")
    return repeats


def _wait_child(argv, *, env=None, cwd=None, stdout_path=None) -> tuple[float, float, int, str]:
    """Run ``argv`` in a child; return (wall s, peak RSS MB, exit status, stderr tail)."""
    with tempfile.TemporaryFile() as err, (
        open(stdout_path, "wb") if stdout_path else open(os.devnull, "wb")
    ) as out:
        t0 = time.perf_counter()
        proc = subprocess.Popen([str(a) for a in argv], stdout=out, stderr=err, env=env, cwd=cwd)
        _, status, rusage = os.wait4(proc.pid, 0)
        wall_s = time.perf_counter() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)
        err.seek(0)
        tail = err.read()[-4000:].decode("utf-8", "replace")
    return wall_s, rusage.ru_maxrss / 1024.0, proc.returncode, tail


def run_command(argv, *, repeats: int = DEFAULT_REPEATS, before=None, after=None, cwd=None) -> Runs:
    """Run a command line ``repeats`` times, each in a fresh child.

    Parameters
    ----------
    argv : sequence of str or Path
    before, after : callable, optional
        Called (untimed) before and after each run, e.g. to empty an output folder.

    Returns
    -------
    Runs
        Wall time of each whole child (start-up included) and its peak RSS.
    """
    repeats = _check_repeats(repeats)
    runs = Runs(times_s=[])
    for _ in range(repeats):
        if before:
            before()
        wall_s, peak_mb, code, tail = _wait_child(argv, cwd=cwd)
        if after:
            after()
        if code != 0:
            raise BenchError(f"command failed ({code}): {' '.join(map(str, argv))}\n{tail}")
        runs.times_s.append(wall_s)
        runs.peak_mb.append(peak_mb)
    return runs


def run_step(
    target: str,
    kwargs: dict | None = None,
    *,
    repeats: int = DEFAULT_REPEATS,
    imports: tuple[str, ...] = (),
    before=None,
    after=None,
) -> Runs:
    """Run the Python function ``target`` (``"module:function"``) ``repeats`` times,
    each in a fresh child (``bench/_worker.py``).

    The worker imports ``imports`` and the target's module (untimed), records the
    resident size, then times ``function(**kwargs)``.  The function returns a
    JSON-able dict; a ``time_s`` key in it replaces the worker's timing (for steps
    that need untimed set-up inside the child).  Modules are searched in
    ``bench/`` first.

    Returns
    -------
    Runs
        Times of the call only, the child's peak RSS, and the last run's dict
        (plus ``baseline_mb``) in ``info``.
    """
    repeats = _check_repeats(repeats)
    runs = Runs(times_s=[])
    payload = json.dumps(kwargs or {})
    for _ in range(repeats):
        if before:
            before()
        with tempfile.TemporaryDirectory(prefix="bench-") as tmp:
            result_path = Path(tmp) / "result.json"
            argv = [sys.executable, WORKER, target, payload, result_path]
            for mod in imports:
                argv += ["--import", mod]
            _, peak_mb, code, tail = _wait_child(argv, cwd=REPO_DIR)
            if code != 0 or not result_path.exists():
                raise BenchError(f"step {target} failed ({code}) with {payload}\n{tail}")
            result = json.loads(result_path.read_text())
        if after:
            after()
        runs.times_s.append(float(result.pop("time_s")))
        runs.peak_mb.append(peak_mb)
        runs.info = result
    return runs


def run_steps_interleaved(specs: dict, *, repeats: int = DEFAULT_REPEATS) -> dict:
    """Run several :func:`run_step` steps round-robin (a, b, a, b, ...) so that a
    drift of the shared machine's load or page cache hits them alike.

    Parameters
    ----------
    specs : dict
        name -> dict of :func:`run_step` arguments (``target``, ``kwargs``, ``imports``).

    Returns
    -------
    dict
        name -> Runs.
    """
    repeats = _check_repeats(repeats)
    out = {name: Runs(times_s=[]) for name in specs}
    for _ in range(repeats):
        for name, spec in specs.items():
            one = run_step(spec["target"], spec.get("kwargs"), repeats=1, imports=tuple(spec.get("imports", ())))
            out[name].times_s += one.times_s
            out[name].peak_mb += one.peak_mb
            out[name].info = one.info
    return out


def warm_page_cache(folder: Path) -> int:
    """Read every file under ``folder`` once (untimed) so that every timed reader
    starts from the same warm page cache; return the bytes read."""
    total = 0
    for path in sorted(Path(folder).rglob("*")):
        if path.is_file():
            with open(path, "rb") as f:
                while chunk := f.read(1 << 20):
                    total += len(chunk)
    return total


def time_callable(fn, *args, repeats: int = DEFAULT_REPEATS, **kwargs) -> Runs:
    """Time ``fn(*args, **kwargs)`` in this process (no memory figure: use
    :func:`run_step` when the peak memory matters)."""
    repeats = _check_repeats(repeats)
    runs = Runs(times_s=[])
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn(*args, **kwargs)
        runs.times_s.append(time.perf_counter() - t0)
    return runs


# ---------------------------------------------------------------- data


def ensure_phantom_case(name: str, *, size: str = "full", preset: str = "wood2018-trial3", seed: int = 1,
                        session: bool = False) -> Path:
    """A phantom case under ``bench/out/data/<name>``, generated once by the
    ``heartreg`` CLI (untimed) and reused when present.  Returns its folder
    (the CT study is its ``ct/`` subfolder)."""
    out = DATA_DIR / name
    if (out / "truth.json").exists() and (out / "ct").is_dir() and (not session or (out / "session").is_dir()):
        return out
    if out.exists():
        shutil.rmtree(out)
    DATA_DIR.mkdir(parents=True, exist_ok=True)
    argv = [*heartreg_cli(), "phantom", out, "--size", size, "--preset", preset, "--seed", str(seed), "-q"]
    if not session:
        argv.append("--no-session")
    print(f"bench: generating {out} (once): {' '.join(map(str, argv[1:]))}", file=sys.stderr)
    _, _, code, tail = _wait_child(argv)
    if code != 0:
        raise BenchError(f"could not generate {out}\n{tail}")
    return out


def heartreg_cli() -> list[str]:
    """The ``heartreg`` console script of this interpreter's environment."""
    script = Path(sys.executable).parent / "heartreg"
    return [str(script)] if script.exists() else [sys.executable, "-m", "heartreg"]


@contextlib.contextmanager
def scratch_dir(prefix: str):
    """A temporary folder inside ``bench/out/`` (same disk as the data), removed after."""
    OUT_DIR.mkdir(parents=True, exist_ok=True)
    path = Path(tempfile.mkdtemp(prefix=prefix, dir=OUT_DIR))
    try:
        yield path
    finally:
        shutil.rmtree(path, ignore_errors=True)


# ---------------------------------------------------------------- reporting


@dataclass
class Row:
    """One line of the results table."""

    step: str
    ours: Runs
    reference: Runs | None = None
    reference_name: str = ""
    notes: str = ""
    command: str = ""

    @property
    def ratio(self) -> float | None:
        return self.ours.median_s / self.reference.median_s if self.reference else None

    def to_dict(self) -> dict:
        return {
            "step": self.step,
            "command": self.command,
            "notes": self.notes,
            "ours": self.ours.to_dict(),
            "reference_name": self.reference_name,
            "reference": self.reference.to_dict() if self.reference else None,
            "ratio": self.ratio,
        }


def _fmt_time(d: dict | None) -> str:
    if not d:
        return "–"
    return f"{d['median_s']:.3g} (min {d['min_s']:.3g})" if len(d["times_s"]) > 1 else f"{d['median_s']:.3g}"


def _fmt_mb(d: dict | None) -> str:
    return "–" if not d or d.get("peak_max_mb") is None else f"{d['peak_max_mb']:.0f}"


def markdown_table(rows) -> str:
    """Rows (``Row`` or their ``to_dict()``) as a Markdown table with
    :data:`TABLE_COLUMNS`.  Times are the median over the runs (min in brackets);
    memory is the largest peak RSS over the runs (ours / reference)."""
    lines = ["| " + " | ".join(TABLE_COLUMNS) + " |", "|" + "---|" * len(TABLE_COLUMNS)]
    for row in rows:
        d = row.to_dict() if isinstance(row, Row) else row
        ref = d.get("reference")
        ref_cell = _fmt_time(ref) + (f" ({d['reference_name']})" if ref and d.get("reference_name") else "")
        mem = _fmt_mb(d.get("ours")) + (f" / {_fmt_mb(ref)}" if ref else "")
        ratio = "–" if d.get("ratio") is None else f"{d['ratio']:.2f}"
        cells = [d["step"], _fmt_time(d.get("ours")), ref_cell, ratio, mem, d.get("notes", "")]
        lines.append("| " + " | ".join(str(c).replace("|", "\\|") for c in cells) + " |")
    return "\n".join(lines)


def _read(path: str) -> str:
    try:
        return Path(path).read_text()
    except OSError:
        return ""


def machine_info() -> dict:
    """nproc, CPU model, RAM, Python and key library versions, and the commit."""
    cpu = re.search(r"^model name\s*:\s*(.+)$", _read("/proc/cpuinfo"), re.M)
    mem = re.search(r"^MemTotal:\s*(\d+)\s*kB", _read("/proc/meminfo"), re.M)
    from importlib import metadata

    versions = {}
    for dist in ("heartreg", "numpy", "scipy", "pydicom", "SimpleITK", "open3d", "dicom2stl"):
        with contextlib.suppress(metadata.PackageNotFoundError):
            versions[dist] = metadata.version(dist)
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO_DIR,
                                capture_output=True, text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain"], cwd=REPO_DIR,
                               capture_output=True, text=True).stdout.strip()
        commit += " (+ uncommitted changes)" if dirty else ""
    except (OSError, subprocess.CalledProcessError):
        commit = "unknown"
    return {
        "nproc": os.cpu_count(),
        "cpu_model": cpu.group(1).strip() if cpu else platform.processor() or "unknown",
        "ram_gib": round(int(mem.group(1)) / 1024**2, 1) if mem else None,
        "python": platform.python_version(),
        "platform": platform.platform(),
        "versions": versions,
        "commit": commit,
        "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
    }


def machine_line(info: dict) -> str:
    v = ", ".join(f"{k} {val}" for k, val in info["versions"].items())
    return (f"{info['nproc']} cores ({info['cpu_model']}), {info['ram_gib']} GiB RAM, "
            f"Python {info['python']}; {v}; commit {info['commit']}; {info['date']}")


def write_results(bench: str, rows, *, command: str, repeats: int) -> Path:
    """Write ``bench/out/<bench>.json`` (rows, machine, command) and print the table."""
    OUT_DIR.mkdir(parents=True, exist_ok=True)
    path = OUT_DIR / f"{bench}.json"
    doc = {
        "bench": bench,
        "command": command,
        "repeats": repeats,
        "machine": machine_info(),
        "rows": [r.to_dict() for r in rows],
    }
    path.write_text(json.dumps(doc, indent=1) + "\n")
    print(markdown_table(rows))
    print(f"\n{path}", file=sys.stderr)
    return path


def bench_argparser(description: str):
    import argparse

    p = argparse.ArgumentParser(description=description)
    p.add_argument("--repeats", type=int, default=DEFAULT_REPEATS,
                   help=f"runs per step, 1..{MAX_REPEATS} (median and min reported)")
    return p


def command_line() -> str:
    """How this bench script was invoked, relative to the repository."""
    script = Path(sys.argv[0]).resolve()
    with contextlib.suppress(ValueError):
        script = script.relative_to(REPO_DIR)
    return " ".join(["python", str(script), *sys.argv[1:]])
