"""The synthetic phantom: full-size CT, the session alone, and the sample case.

Steps, each run in a fresh child process (see ``common.py``), into a fresh
folder under ``bench/out/`` that is removed after the run:

- full CT: ``heartreg phantom OUT --size full --preset wood2018-trial3 --seed 1
  --no-session -q`` (512 x 512 x 288 DICOM slices + ECG waveform), timed as a
  whole command (interpreter start-up included).
- session alone: ``heartreg.phantom.write_session(OUT, make_config('default'),
  seed=1)``, i.e. 100 points x 30 s x 100 Hz; imports untimed.
- sample case: ``heartreg phantom OUT --seed 1 -q`` (default preset, sample-size
  CT 128 x 128 x 72 and the session: what ``heartreg demo`` starts from).
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import common  # noqa: E402


def session(out_dir: str, preset: str, n_points: int, duration_s: float, seed: int) -> dict:
    """Step run in a child: write the session alone."""
    from heartreg.phantom import make_config, write_session

    truth = write_session(Path(out_dir), make_config(preset), seed=seed, n_points=n_points,
                          duration_s=duration_s)
    return {"n_points": len(truth.points)}


def _tree_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


class _Fresh:
    """A fresh output folder per run; records what the run wrote, then removes it."""

    def __init__(self, root: Path):
        self.out = root / "case"
        self.bytes = 0
        self.files = 0

    def before(self):
        if self.out.exists():
            shutil.rmtree(self.out)

    def after(self):
        if self.out.exists():
            self.bytes = _tree_bytes(self.out)
            self.files = sum(1 for p in self.out.rglob("*") if p.is_file())
            shutil.rmtree(self.out)

    def written(self) -> str:
        return f"writes {self.files} files, {self.bytes / 2**20:.1f} MiB"


def main(argv=None) -> int:
    args = common.bench_argparser(__doc__.splitlines()[0]).parse_args(argv)
    common.ensure_requirements()
    n = args.repeats
    cli = common.heartreg_cli()
    rows = []
    with common.scratch_dir("phantom-") as root:
        fresh = _Fresh(root)
        full = [*cli, "phantom", fresh.out, "--size", "full", "--preset", "wood2018-trial3",
                "--seed", "1", "--no-session", "-q"]
        runs = common.run_command(full, repeats=n, before=fresh.before, after=fresh.after)
        rows.append(common.Row(
            step="phantom full CT (512x512x288 + ECG DICOM)", ours=runs,
            notes=f"whole CLI process; {fresh.written()}",
            command="heartreg phantom OUT --size full --preset wood2018-trial3 --seed 1 --no-session -q",
        ))

        kwargs = {"out_dir": str(fresh.out), "preset": "default", "n_points": 100, "duration_s": 30.0, "seed": 1}
        runs = common.run_step("bench_phantom:session", kwargs, repeats=n, imports=("numpy", "heartreg.phantom"),
                               before=fresh.before, after=fresh.after)
        rows.append(common.Row(
            step="phantom session alone (100 points x 30 s x 100 Hz)", ours=runs,
            notes=f"write_session in a child, imports untimed; {fresh.written()}",
            command="heartreg.phantom.write_session(OUT, make_config('default'), seed=1, n_points=100, duration_s=30)",
        ))

        sample = [*cli, "phantom", fresh.out, "--seed", "1", "-q"]
        runs = common.run_command(sample, repeats=n, before=fresh.before, after=fresh.after)
        rows.append(common.Row(
            step="phantom sample case (128x128x72 CT + session)", ours=runs,
            notes=f"whole CLI process; {fresh.written()}",
            command="heartreg phantom OUT --seed 1 -q",
        ))
    common.write_results("bench_phantom", rows, command=common.command_line(), repeats=n)
    return 0


if __name__ == "__main__":
    sys.exit(main())
