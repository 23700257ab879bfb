"""Issue 15: kill -9 at any moment of ``model``, ``register`` or ``pipeline``
leaves the previous output or the complete new one, and the next run cleans up.

Each command runs for real, as a subprocess on the small sample case, with
``--overwrite`` onto an earlier run's folder.  The test watches the command's
staging folder and stops the process (SIGSTOP) at each of several moments of
its write: what the output path holds while the process is stopped is exactly
what a kill -9 at that moment would leave (a killed process runs no more code).
At the last moment the process is killed (SIGKILL).  A rerun must then remove
the killed run's staging and write the complete output in one step.  The kill
points are found by watching the file system, not by sleeping, so they fall
inside the write however loaded the machine is.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from heartreg.cli import main
from tests.heartreg.small_case import digest, small_case

ROOT = Path(__file__).resolve().parents[2]
#: longest a command may take to reach the next kill point on a loaded machine, s.
WAIT_S = 300


@pytest.fixture(scope="module")
def case(sample_case, tmp_path_factory):
    """The sample CT, a model meshed from the phantom's analytic heart and a
    session of 8 points (a registration in seconds)."""
    src, truth = sample_case
    root = tmp_path_factory.mktemp("kill")
    model, session = small_case(src, truth, root, grid=60, points=8)
    return {"ct": src / "ct", "model": model, "session": session}


def _argv(command: str, case, out: Path) -> list[str]:
    fast = ["-q", "--overwrite"]
    return {
        "model": ["model", str(case["ct"]), "-o", str(out), "--faces", "2000", "--fiducials", "0", *fast],
        "register": ["register", str(case["model"]), str(case["session"]), "-o", str(out), "--step", "0.5",
                     "--no-view", *fast],
        "pipeline": ["pipeline", str(case["ct"]), str(case["session"]), "-o", str(out), "--step", "0.5",
                     "--faces", "2000", "--no-view", *fast],
    }[command]


_S = ".out.heartreg-*.tmp"  # the staging folder beside OUT
#: the moments to kill at, in the order the command reaches them: a glob (in OUT's
#: parent) that starts to match there.  The last one is followed by seconds of work.
KILL_POINTS = {
    "model": [_S, f".{_S}.heartreg-*.tmp/heart.ply",  # the mesh written (write_model's own staging)
              f"{_S}/model.json"],  # the model written, the picture being drawn
    "register": [_S, f"{_S}/registration.json", f"{_S}/fig2_rms.png", f"{_S}/fig7_distances.png"],
    "pipeline": [f"{_S}/phases/phases.json", f"{_S}/.model.heartreg-*.tmp/heart.ply", f"{_S}/model/model.json",
                 f"{_S}/registration/registration.json", f"{_S}/registration/fig2_rms.png"],
}

#: an earlier run's output: a marker in each part (its content does not matter to the
#: contract, but none of its names is a kill point; for the pipeline only its
#: parts, so that the whole folder is swapped in one step), and the file that makes
#: a folder an earlier output --overwrite may replace.
EARLIER = {
    "model": ["model.json", "earlier_marker"],
    "register": ["registration.json", "earlier_marker"],
    "pipeline": ["phases/phases.json", "model/model.json", "registration/registration.json"],
}


def _wait_for(proc, parent: Path, points: list[str]) -> int | None:
    """Poll until one of ``points`` matches; its index (the latest matching), or
    None if the command ended first."""
    deadline = time.monotonic() + WAIT_S
    while proc.poll() is None and time.monotonic() < deadline:
        for k in range(len(points) - 1, -1, -1):
            if next(parent.glob(points[k]), None) is not None:
                return k
        time.sleep(0.002)
    return None


@pytest.mark.parametrize("command", ["model", "register", "pipeline"])
def test_kill_9_at_several_moments_leaves_the_earlier_or_the_complete_output(case, tmp_path, command):
    parent = tmp_path / "runs"
    out = parent / "out"
    for name in EARLIER[command]:
        (out / name).parent.mkdir(parents=True, exist_ok=True)
        (out / name).write_text("an earlier run")
    earlier = digest(out)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    env.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkOSOpenGLRenderWindow")
    proc = subprocess.Popen([sys.executable, "-m", "heartreg", *_argv(command, case, out)], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    points = KILL_POINTS[command]
    seen = []  # (kill point, what OUT held there)
    try:
        k = 0
        while k < len(points):
            reached = _wait_for(proc, parent, points[k:])
            if reached is None:
                break
            k += reached  # a point passed between two polls is left out
            proc.send_signal(signal.SIGSTOP)
            seen.append((points[k], digest(out)))
            proc.send_signal(signal.SIGKILL if k == len(points) - 1 else signal.SIGCONT)
            k += 1
    finally:
        if proc.poll() is None and not (seen and seen[-1][0] == points[-1]):
            proc.kill()
        _, err = proc.communicate(timeout=WAIT_S)
    assert proc.returncode == -signal.SIGKILL and seen and seen[-1][0] == points[-1], \
        f"{command} ended before its last kill point: {err}"
    assert len(seen) >= 2, [entry for entry, _ in seen]  # several moments, not one
    killed_at = digest(out)
    stale = [p.name for p in parent.iterdir() if p.name != "out"]

    assert main(_argv(command, case, out)) == 0  # the rerun: cleans up, writes the whole output
    complete = digest(out)
    assert [p.name for p in parent.iterdir()] == ["out"]  # the killed run's staging removed
    assert not any("earlier_marker" in name for name in complete)  # replaced whole, nothing mixed in
    assert seen[0][1] == earlier  # the first kill point is well before the end of the write
    for entry, state in seen + [("after the kill", killed_at)]:
        # the earlier output untouched or, had the commit come first, the complete new one
        assert state == earlier or set(state) == set(complete), (command, entry, sorted(state))
    if killed_at == earlier:
        assert stale, "a killed run that wrote nothing visible left its staging folder for the rerun"
