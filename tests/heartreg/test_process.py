"""The command's process: numpy's arrays are not advised to the kernel as huge pages (heartreg.cli)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

PROBE = """
import heartreg.cli, numpy, os
try:
    multiarray = numpy._core.multiarray
except AttributeError:  # numpy 1.26
    multiarray = numpy.core.multiarray
print(os.environ['NUMPY_MADVISE_HUGEPAGE'], multiarray._set_madvise_hugepage(True))
"""


@pytest.mark.parametrize("given, expected", [(None, "0 False"), ("1", "1 True")])
def test_the_command_asks_numpy_for_no_huge_pages_unless_the_user_did(given, expected):
    env = {k: v for k, v in os.environ.items() if k != "NUMPY_MADVISE_HUGEPAGE"}
    if given is not None:
        env["NUMPY_MADVISE_HUGEPAGE"] = given
    out = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == expected.split()
