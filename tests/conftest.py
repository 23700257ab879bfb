"""Phantom cases shared by the whole suite (written once per test run).

The phantom (heartreg.phantom) is the independent ground truth: every stage is
tested against the values in its truth.json. Under pytest-xdist (``make test``)
the workers share one copy of each case: the first to need it writes it, the
others wait for it (a file lock beside their temporary folders).
"""

from __future__ import annotations

import fcntl
import json
import os
from pathlib import Path

import pytest
from hypothesis import settings

from heartreg.phantom import make_phantom

# The same examples on every run (CI included): a property test that fails, fails
# again with the same example, and the suite does not turn red by chance.
settings.register_profile("heartreg", derandomize=True, print_blob=True)
settings.load_profile("heartreg")

#: Seed of the shared sample case; its CT has no ectopic hit (phases 0.68-0.75).
SAMPLE_SEED = 0


def shared_folder(tmp_path_factory, name: str, make, done: str) -> Path:
    """A folder made by ``make(folder)`` once per test run, whichever worker asks first.

    ``done`` is the file (relative to the folder) whose presence says the folder is
    complete: ``make`` must write it last.  Tests read the folder, never write into it.
    """
    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # the run's temporary folder, above every worker's own
    out = root / f"shared-{name}"
    with open(root / f"shared-{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
        if not (out / done).is_file():
            make(out)
    return out


def shared_phantom(tmp_path_factory, name: str, **options) -> tuple[Path, dict]:
    """``make_phantom(folder, **options)`` once per test run: the folder and its truth."""
    # make_phantom moves the case in whole, truth.json included
    out = shared_folder(tmp_path_factory, name, lambda out: make_phantom(out, overwrite=True, **options),
                        "truth.json")
    return out, load_truth(out)


@pytest.fixture(scope="session")
def sample_case(tmp_path_factory):
    """A sample-size phantom (trial 1 settings): CT, qrs.csv, session, truth."""
    return shared_phantom(tmp_path_factory, "sample_case", preset="wood2018-trial1", size="sample",
                          seed=SAMPLE_SEED, n_points=30)


@pytest.fixture(scope="session")
def full_case(tmp_path_factory):
    """A full-size phantom CT (512 x 512 x 288, 0.49 mm pixels, 0.625 mm slices)."""
    return shared_phantom(tmp_path_factory, "full_case", preset="wood2018-trial3", size="full", seed=1,
                          session=False)


@pytest.fixture(scope="session")
def sample_outputs(sample_case, tmp_path_factory):
    """``heartreg phases`` and ``heartreg model`` on the sample CT with their default
    options, once per run: the folder holding ``phases/`` and ``model/``."""
    from heartreg.cli import main

    case_dir, _ = sample_case

    def make(out: Path) -> None:
        for command in ("phases", "model"):
            if not (out / command).exists():  # staged: a folder there is complete
                assert main([command, str(case_dir / "ct"), "-o", str(out / command), "-q"]) == 0
        (out / "done").write_text("")

    return shared_folder(tmp_path_factory, "sample_outputs", make, "done")


def load_truth(case_dir):
    return json.loads((case_dir / "truth.json").read_text())
