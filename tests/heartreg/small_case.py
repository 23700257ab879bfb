"""A quick model and a short session cut from the shared sample phantom.

The model is meshed straight from the phantom's analytic heart (no segmentation)
and the session keeps only its first points, so a registration on them takes
seconds: for tests of contracts and readers, not of accuracy.  :func:`digest`
fingerprints a folder (inputs must not change; outputs are the old or the new);
:func:`time_box` turns a hang into a failure.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import shutil
import signal
from pathlib import Path

from heartreg.phantom import config as phantom_config
from heartreg.phantom import layout
from modeling import make_heart_model, write_model
from modeling.surface import Mesh


def small_case(src: Path, truth: dict, root: Path, *, grid: int, points: int) -> tuple[Path, Path]:
    """Write ``root/model`` (a ``grid`` x ``grid`` mesh of the true heart) and
    ``root/session`` (the sample session's first ``points`` records); return both."""
    from tests.registration.conftest import heart_grid_mesh

    heart = layout.make_heart(phantom_config.PRESETS["wood2018-trial1"])
    vertices, faces = heart_grid_mesh(heart, truth["cardiac_phase"], truth["respiration_phase"], n_u=grid, n_v=grid)
    built = make_heart_model(
        Mesh(vertices, faces), cardiac_phase=truth["cardiac_phase"], cardiac_phase_source="truth",
        fiducials_patient_mm=truth["fiducials_patient_mm"],
    )
    write_model(built, root / "model")
    return root / "model", first_points(src / "session", root / "session", points)


def first_points(src: Path, dst: Path, n: int) -> Path:
    """A copy of session ``src`` with its first ``n`` point records only (and their files)."""
    meta = json.loads((src / "session.json").read_text())
    meta["points"] = meta["points"][:n]
    (dst / "points").mkdir(parents=True)
    for entry in meta["points"]:
        shutil.copyfile(src / entry["file"], dst / entry["file"])
    shutil.copyfile(src / meta["fiducials_file"], dst / meta["fiducials_file"])
    if meta.get("fiducial_trace_file"):  # session format 2
        shutil.copyfile(src / meta["fiducial_trace_file"], dst / meta["fiducial_trace_file"])
    (dst / "session.json").write_text(json.dumps(meta, indent=2) + "\n")
    return dst


def digest(root: Path) -> dict:
    """Every file under ``root`` (relative path) with the SHA-1 of its bytes."""
    return {
        str(p.relative_to(root)): hashlib.sha1(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*")) if p.is_file()
    }


class Hang(Exception):
    """Code under a :func:`time_box` ran past its time."""


@contextlib.contextmanager
def time_box(seconds: float):
    """Raise :class:`Hang` in the main thread if the block runs longer than ``seconds``."""

    def alarm(signum, frame):
        raise Hang(f"still running after {seconds} s")

    previous = signal.signal(signal.SIGALRM, alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
