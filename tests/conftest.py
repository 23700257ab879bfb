"""Phantom cases shared by the whole suite (written once per test run).

The phantom (heartreg.phantom) is the independent ground truth: every stage is
tested against the values in its truth.json. Under pytest-xdist (``make test``)
the workers share one copy of each case: the first to need it writes it, the
others wait for it (a file lock beside their temporary folders).

``make test`` gives each worker a whole test file at a time (``--dist loadfile``),
in collection order; the costliest files are collected first (``COSTLIEST_FIRST``)
so that none of them starts last and holds the run while the other worker idles.

Under xdist one worker runs per core, so each worker (and every command a test
starts) computes on one BLAS thread: two OpenBLAS threads per worker on a
machine already busy with the other workers spin against each other (measured:
a registration's motion-model fits took 4-6 times longer).  The library's
results do not depend on the thread count (``hrcore.blas``, tested on one and
two threads by ``tests/hrcore/test_blas.py``).
"""

from __future__ import annotations

import fcntl
import json
import os
from pathlib import Path

if os.environ.get("PYTEST_XDIST_WORKER"):
    for _name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(_name, "1")  # before numpy loads its BLAS; inherited by the commands tests run

import pytest
from hypothesis import settings

from heartreg.phantom import make_phantom

if os.environ.get("PYTEST_XDIST_WORKER"):
    from threadpoolctl import threadpool_limits

    # in case numpy's BLAS was loaded before this file (by a plugin): one thread from here on
    _ONE_BLAS_THREAD = threadpool_limits(limits=1, user_api="blas")

# The same examples on every run (CI included): a property test that fails, fails
# again with the same example, and the suite does not turn red by chance.
settings.register_profile("heartreg", derandomize=True, print_blob=True)
settings.load_profile("heartreg")

#: Test files that cost the most CPU, the costliest first: user + sys of the test
#: process and its children, measured one file after another on a loaded machine
#: (December 2026, the shared cases below built once; seconds).  A file that takes more than
#: ~10 s belongs here.  The rest follow in pytest's own order.
COSTLIEST_FIRST = (
    "tests/heartreg/test_batch.py",  # 76 + its killed cluster: two Dask clusters (2 + 1 workers), 7 sample-case runs
    "tests/heartreg/test_reproduce.py",  # 90: two trials, phantom to figures, on a one-worker local Dask cluster
    "tests/heartreg/test_demo.py",  # 83: the demo (100 points) and two pipeline commands
    "tests/modeling/test_build.py",  # 71: writes the full-size case and models it
    "tests/heartreg/test_kill.py",  # 64: three commands as subprocesses, run again in-process
    "tests/registration/test_pipeline.py",  # 30
    "tests/heartreg/test_reliability.py",  # 28
    "tests/heartreg/test_phantom_anatomy.py",  # 25
    "tests/heartreg/test_no_patient_data.py",  # 24
    "tests/heartreg/test_temporal_eval.py",  # 23
    "tests/modeling/test_realct.py",  # 23
    "tests/modeling/test_surface.py",  # 19
    "tests/heartreg/test_track.py",  # 18
    "tests/registration/test_slicer.py",  # 16
    "tests/heartreg/test_phantom_cli.py",  # 14
    "tests/modeling/test_frame.py",  # 12
    "tests/heartreg/test_readme_api.py",  # 12
    "tests/heartreg/test_phantom_ct.py",  # 11 (reads the full-size case: after test_build)
    "tests/imaging/test_phase.py",  # 10 (reads the full-size case: after test_build)
)


def pytest_configure(config):
    # xdist would hand out the files with the most tests first (its "loadscope
    # reorder"); COSTLIEST_FIRST is the better order
    if hasattr(config.option, "loadscopereorder"):
        config.option.loadscopereorder = False


def pytest_collection_modifyitems(session, config, items):
    """The files of ``COSTLIEST_FIRST`` first, in its order; tests keep their order within a file."""
    rank = {name: k for k, name in enumerate(COSTLIEST_FIRST)}
    root = Path(__file__).resolve().parents[1]

    def key(item):
        try:
            return rank.get(Path(item.path).resolve().relative_to(root).as_posix(), len(rank))
        except ValueError:  # a file outside the repository (pytest given a path elsewhere)
            return len(rank)

    items.sort(key=key)


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
