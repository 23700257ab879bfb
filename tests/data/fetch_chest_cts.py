"""Fetch two more real chest CTs for the tests: pyradiomics' ``lung1`` and ``lung2``.

They ship only in the source distribution of pyradiomics 3.0.1 on PyPI (its
``data/`` folder, BSD-3-Clause; the package itself is not installed, its build
needs a compiler).  Both are full-field chest CTs without contrast, 5 mm slices,
stored as NRRD:

- ``lung1_image.nrrd``: 512 x 512 x 48, 0.57 mm pixels, from the neck to the
  heart's lower wall;
- ``lung2_image.nrrd``: 512 x 512 x 61, 0.63 mm pixels, the whole chest and the
  liver below it.

Run by ``make test`` before pytest (``python tests/data/fetch_chest_cts.py``);
the files go to ``.cache/chest_cts/`` in the checkout.  The archive and both
files are checked against pinned SHA-256 digests: a cached file that does not
match (a truncated earlier run) is fetched again, and a file is renamed into
place only once its digest matches.  Offline, the script says so in one line,
removes a cached file that does not match, and the tests that need the files
skip.
"""

from __future__ import annotations

import hashlib
import sys
import tarfile
import tempfile
import urllib.request
from pathlib import Path

CACHE = Path(__file__).resolve().parents[2] / ".cache" / "chest_cts"
SDIST = ("https://files.pythonhosted.org/packages/1b/35/c7f7fb7affd302fd8107dcee6b6e7aaf3708b75ad69d5f9a3dfcadb73eaa/"
         "pyradiomics-3.0.1.tar.gz")
SDIST_SHA256 = "47c57f441d6cb7973fa3b2ea48d3948df78e3348e1c69e1e2ff19001601fc2f5"
#: File name -> SHA-256 of the file as the archive holds it.
MEMBERS = {
    "lung1_image.nrrd": "379fa48bf34cfa961e6f5ec19c0c38757a30b9aa884212ef28dc29b5061c64ed",
    "lung2_image.nrrd": "aa2b94eec79127ed786798ac8dc3c013010e1692d5787bebfae1a1e9685a4651",
}
TIMEOUT_S = 60


def paths() -> dict[str, Path]:
    """Where each CT is (or will be) kept, by file name."""
    return {name: CACHE / name for name in MEMBERS}


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as f:
        while chunk := f.read(1 << 20):
            digest.update(chunk)
    return digest.hexdigest()


def _missing() -> list[str]:
    return [name for name, path in paths().items() if not path.is_file() or _sha256(path) != MEMBERS[name]]


def fetch() -> None:
    missing = _missing()
    if not missing:
        return
    CACHE.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=CACHE) as tmp:
        archive = Path(tmp) / "sdist.tar.gz"
        with urllib.request.urlopen(SDIST, timeout=TIMEOUT_S) as reply, archive.open("wb") as out:
            while chunk := reply.read(1 << 20):
                out.write(chunk)
        if _sha256(archive) != SDIST_SHA256:
            raise OSError("the pyradiomics 3.0.1 archive's SHA-256 differs from the pinned one")
        with tarfile.open(archive) as tar:
            members = {Path(m.name).name: m for m in tar.getmembers() if "/data/" in m.name}
            for name in missing:
                if name not in members:
                    raise OSError(f"{name} is not in the archive's data/ folder")
                staged = Path(tmp) / name
                with tar.extractfile(members[name]) as src, staged.open("wb") as out:
                    while chunk := src.read(1 << 20):
                        out.write(chunk)
                if _sha256(staged) != MEMBERS[name]:
                    raise OSError(f"{name}'s SHA-256 differs from the pinned one")
                staged.replace(CACHE / name)


if __name__ == "__main__":
    try:
        fetch()
    except Exception as exc:  # offline, or the archive changed: the tests that need the files skip
        for name in _missing():  # a damaged file is no file: its tests skip instead of failing on it
            paths()[name].unlink(missing_ok=True)
        print(f"note: pyradiomics' chest CTs not fetched into {CACHE} ({exc}); their tests will skip", file=sys.stderr)
