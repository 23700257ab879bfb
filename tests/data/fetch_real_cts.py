"""Fetch more real CTs for the tests from source archives on PyPI.

Each archive ships test data that its wheel leaves out; neither package is
installed (pyradiomics' build needs a compiler, TotalSegmentator pulls in
PyTorch), only the files below are taken:

- pyradiomics 3.0.1 (BSD-3-Clause), ``data/``: two full-field chest CTs without
  contrast, 5 mm slices, NRRD:

  - ``lung1_image.nrrd``: 512 x 512 x 48, 0.57 mm pixels, from the neck to the
    heart's lower wall;
  - ``lung2_image.nrrd``: 512 x 512 x 61, 0.63 mm pixels, the whole chest and
    the liver below it;

- TotalSegmentator 2.18.0 (Apache-2.0), ``tests/reference_files/``:

  - ``ts_aorta/``: an aortic CTA of the whole chest (early arterial phase,
    233 x 167 x 191 voxels, 1.5 mm, NIfTI in LPS) with TotalSegmentator's
    own masks of its aorta, aortic annulus and sinotubular junction: the
    aortic valve's level on a real heart;
  - ``ts_dicom/``: a real DICOM series as an anonymiser left it (20 slices of
    a PET/CT's abdomen, 512 x 512, 2 mm, JPEG 2000, SOPInstanceUID and
    SeriesInstanceUID blanked) and ``ts_dicom_seg.nii.gz``, a segmentation on
    its grid written by another reader (its affine, for the geometry);
  - ``ts_pulmonary/``: TotalSegmentator's pulmonary valve annulus and
    sinotubular junction on ``shared/realct`` (its ``pulmonary_report``,
    made from the same CT): the pulmonary valve's level on a real heart;
  - ``ts_mr.nii.gz``: a small MR volume, what a user may pass by mistake.

Run by ``make test`` before pytest (``python tests/data/fetch_real_cts.py``);
the files go to ``.cache/real_cts/`` in the checkout.  The archives and every
file are checked against pinned SHA-256 digests (a folder's digest runs over its top-level
files' names and digests): a cached entry that does not match (a truncated
earlier run) is fetched again, and an entry is renamed into place only once its
digest matches.  Offline, the script says so in one line per archive, removes a cached
entry that does not match, and the tests that need it skip.
"""

from __future__ import annotations

import hashlib
import shutil
import sys
import tarfile
import tempfile
import urllib.request
from dataclasses import dataclass
from pathlib import Path

CACHE = Path(__file__).resolve().parents[2] / ".cache" / "real_cts"
TIMEOUT_S = 60
_FILES = "https://files.pythonhosted.org/packages/"


@dataclass(frozen=True)
class Source:
    """A source archive on PyPI and what to take from it."""

    url: str
    sha256: str
    #: local name -> (member path inside the archive's top folder, SHA-256 of
    #: the file, or of the folder: see :func:`digest`)
    entries: dict[str, tuple[str, str]]


SOURCES = (
    Source(
        _FILES + "1b/35/c7f7fb7affd302fd8107dcee6b6e7aaf3708b75ad69d5f9a3dfcadb73eaa/pyradiomics-3.0.1.tar.gz",
        "47c57f441d6cb7973fa3b2ea48d3948df78e3348e1c69e1e2ff19001601fc2f5",
        {
            "lung1_image.nrrd": ("data/lung1_image.nrrd",
                                 "379fa48bf34cfa961e6f5ec19c0c38757a30b9aa884212ef28dc29b5061c64ed"),
            "lung2_image.nrrd": ("data/lung2_image.nrrd",
                                 "aa2b94eec79127ed786798ac8dc3c013010e1692d5787bebfae1a1e9685a4651"),
        },
    ),
    Source(
        _FILES + "c3/53/7d654d2ec3fcb801ae54d318b0ffc18021aed528bf4e4df0753caf0c8a73/totalsegmentator-2.18.0.tar.gz",
        "5d4223ef93973bc36d710869d11e7742ead2c154c72f7f9edcaaadd5b6c4bd03",
        {
            "ts_aorta/ct.nii.gz": ("tests/reference_files/aorta_report/example_ct.nii.gz",
                                   "372d98723e3283a8d4a0ae2f0ef1e581c0ad17b673b30b2e8d3e215180cc2a12"),
            "ts_aorta/aorta.nii.gz": ("tests/reference_files/aorta_report/test_result/models/aorta.nii.gz",
                                      "7fa1b813c63abcbe455b62a510c5e7a00fe0998f30541d5a8af46b20a88dd7f7"),
            "ts_aorta/annulus.nii.gz": (
                "tests/reference_files/aorta_report/test_result/models/annulus_proper.nii.gz",
                "ff547ae351a1d449a4cc727d9ba8ce8acbcc99748d52a18ed1236cc7338696de"),
            "ts_aorta/sinotubular_junction.nii.gz": (
                "tests/reference_files/aorta_report/test_result/models/sinotubular_junction.nii.gz",
                "b915dcb78345a52f254218fad6be76c6dd744a6bea01eb7aef7169ad32a2bc43"),
            "ts_dicom": ("tests/reference_files/example_ct_dicom",
                         "62e48a2b3768c089f34567514bbd04f11457459e59d8a3cd9155b14fe71c826b"),
            "ts_dicom_seg.nii.gz": ("tests/reference_files/example_seg_dicom.nii.gz",
                                    "98af7f6536c316ff9084054f20956cd3e28af376b81d582d269fbea2744878fc"),
            "ts_pulmonary/annulus.nii.gz": ("tests/reference_files/pulmonary_report/models/pul_annulus.nii.gz",
                                            "2f180c0b2967dc9baabfa3fa29723fa5c354ba67388e7c98815829e8841368ac"),
            "ts_pulmonary/sinotubular_junction.nii.gz": (
                "tests/reference_files/pulmonary_report/models/pul_sinotubular_junction.nii.gz",
                "d7c5c438e59830e7cfca7b2cd61415dd52012969e46ec992609a2d7d20235fe3"),
            "ts_mr.nii.gz": ("tests/reference_files/example_mr_sm.nii.gz",
                             "209b46efaff595dd54a9332872e17a722b62654bbb68dbd89acd5090701bbd4f"),
        },
    ),
)


def paths() -> dict[str, Path]:
    """Where each entry is (or will be) kept, by local name."""
    return {name: CACHE / name for source in SOURCES for name in source.entries}


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        while chunk := f.read(1 << 20):
            h.update(chunk)
    return h.hexdigest()


def digest(path: Path) -> str:
    """SHA-256 of a file; of a folder, over its files' sorted names and digests."""
    if path.is_file():
        return _sha256(path)
    h = hashlib.sha256()
    for f in sorted(p for p in path.iterdir() if p.is_file()):
        h.update(f.name.encode() + b"\0" + _sha256(f).encode() + b"\n")
    return h.hexdigest()


def _missing(source: Source) -> list[str]:
    return [name for name, (_, sha) in source.entries.items()
            if not (CACHE / name).exists() or digest(CACHE / name) != sha]


def _fetch(source: Source) -> None:
    missing = _missing(source)
    if not missing:
        return
    CACHE.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=CACHE) as tmp:
        archive = Path(tmp) / "sdist.tar.gz"
        with urllib.request.urlopen(source.url, timeout=TIMEOUT_S) as reply, archive.open("wb") as out:
            shutil.copyfileobj(reply, out, 1 << 20)
        if _sha256(archive) != source.sha256:
            raise OSError(f"{source.url.rsplit('/', 1)[-1]}'s SHA-256 differs from the pinned one")
        with tarfile.open(archive) as tar:
            members = [m for m in tar.getmembers() if m.isfile()]
            for name in missing:
                inner, sha = source.entries[name]
                # the member's path below the archive's top folder (name-version/)
                picked = [(m, m.name.split("/", 1)[1]) for m in members if "/" in m.name
                          and (m.name.split("/", 1)[1] == inner or m.name.split("/", 1)[1].startswith(inner + "/"))]
                if not picked:
                    raise OSError(f"{inner} is not in {source.url.rsplit('/', 1)[-1]}")
                staged = Path(tmp) / "staged" / name
                for member, rel in picked:
                    target = staged if rel == inner else staged / Path(rel).relative_to(inner)
                    target.parent.mkdir(parents=True, exist_ok=True)
                    with tar.extractfile(member) as src, target.open("wb") as out:
                        shutil.copyfileobj(src, out, 1 << 20)
                if digest(staged) != sha:
                    raise OSError(f"{inner}'s SHA-256 differs from the pinned one")
                final = CACHE / name
                final.parent.mkdir(parents=True, exist_ok=True)
                if final.is_dir():
                    shutil.rmtree(final)
                staged.replace(final)


def _remove_damaged(source: Source) -> None:
    """A damaged entry is no entry: its tests skip instead of failing on it."""
    for name in _missing(source):
        path = CACHE / name
        shutil.rmtree(path) if path.is_dir() else path.unlink(missing_ok=True)


def fetch() -> None:
    for source in SOURCES:
        try:
            _fetch(source)
        except Exception as exc:  # offline, or the archive changed: the tests that need it skip
            _remove_damaged(source)
            name = source.url.rsplit("/", 1)[-1]
            print(f"note: real CTs from {name} not fetched into {CACHE} ({exc}); their tests will skip",
                  file=sys.stderr)


if __name__ == "__main__":
    fetch()
