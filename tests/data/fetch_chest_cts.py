"""Fetch two more real chest CTs for the tests: pyradiomics' ``lung1`` and ``lung2``.

They ship only in the source distribution of pyradiomics 3.0.1 on PyPI (its
``data/`` folder, BSD-3-Clause; the package itself is not installed, its build
needs a compiler).  Both are full-field chest CTs without contrast, 5 mm slices,
stored as NRRD:

- ``lung1_image.nrrd``: 512 x 512 x 48, 0.57 mm pixels, from the neck to the
  heart's lower part (the scan ends inside the heart);
- ``lung2_image.nrrd``: 512 x 512 x 61, 0.63 mm pixels, the whole chest and the
  liver below it.

Run by ``make test`` before pytest (``python tests/data/fetch_chest_cts.py``);
the files go to ``.cache/chest_cts/`` in the checkout.  The archive's SHA-256
is PyPI's own, checked before anything is kept; the members are written to a
staging name and renamed.  Offline, it says so in one line and the tests that
need the files skip.
"""

from __future__ import annotations

import hashlib
import json
import sys
import tarfile
import tempfile
import urllib.request
from pathlib import Path

CACHE = Path(__file__).resolve().parents[2] / ".cache" / "chest_cts"
MEMBERS = ("lung1_image.nrrd", "lung2_image.nrrd")
PROJECT = "https://pypi.org/pypi/pyradiomics/json"
VERSION = "3.0.1"
TIMEOUT_S = 60


def paths() -> dict[str, Path]:
    """Where each CT is (or will be) kept, by file name."""
    return {name: CACHE / name for name in MEMBERS}


def fetch() -> None:
    if all(p.is_file() for p in paths().values()):
        return
    with urllib.request.urlopen(PROJECT, timeout=TIMEOUT_S) as reply:
        files = json.load(reply)["releases"][VERSION]
    sdist = next(f for f in files if f["packagetype"] == "sdist")
    CACHE.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=CACHE) as tmp:
        archive = Path(tmp) / sdist["filename"]
        digest = hashlib.sha256()
        with urllib.request.urlopen(sdist["url"], timeout=TIMEOUT_S) as reply, archive.open("wb") as out:
            while chunk := reply.read(1 << 20):
                digest.update(chunk)
                out.write(chunk)
        if digest.hexdigest() != sdist["digests"]["sha256"]:
            raise OSError(f"{sdist['filename']}: SHA-256 differs from PyPI's")
        with tarfile.open(archive) as tar:
            for name in MEMBERS:
                member = next(m for m in tar.getmembers() if m.name.endswith("/data/" + name))
                staged = Path(tmp) / name
                with tar.extractfile(member) as src, staged.open("wb") as out:
                    out.write(src.read())
                staged.replace(CACHE / name)


if __name__ == "__main__":
    try:
        fetch()
    except Exception as exc:  # offline or PyPI changed: the tests that need the files skip
        print(f"note: pyradiomics' chest CTs not fetched into {CACHE} ({exc}); their tests will skip", file=sys.stderr)
