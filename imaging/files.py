"""Atomic output files: write under a temporary name, then rename.

Every stage writes its outputs through these so that a failure never leaves a
half-finished file behind.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

__all__ = ["atomic_path", "gzip_damage", "is_analyze_header", "write_text_atomic", "umask_mode"]


def umask_mode(*, directory: bool = False) -> int:
    """The permission bits a new file (or folder) gets under the current umask.

    Temporary files and folders are created private (0600 / 0700); outputs are
    given these bits before they are renamed into place.
    """
    mask = os.umask(0)
    os.umask(mask)
    return (0o777 if directory else 0o666) & ~mask


@contextlib.contextmanager
def atomic_path(path):
    """Yield a temporary path beside ``path``; rename it to ``path`` on success.

    The caller writes the temporary file (e.g. with matplotlib's ``savefig`` or a
    mesh writer); on an exception it is removed and ``path`` is left untouched.
    An OS error that names no file (a writer's full disk) is raised naming ``path``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}-", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
        os.chmod(tmp, umask_mode())
        os.replace(tmp, path)
    except OSError as exc:
        if exc.filename is None and exc.errno is not None:  # e.g. a full disk inside a writer: name the file
            raise OSError(exc.errno, exc.strerror or os.strerror(exc.errno), str(path)) from exc
        raise
    finally:
        if tmp.exists():
            tmp.unlink()


def write_text_atomic(path, text: str) -> None:
    """Write ``text`` to ``path`` atomically (UTF-8)."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


def gzip_damage(path) -> str | None:
    """Why a gzip-compressed (``.gz``) file is damaged (its CRC or length check fails, it ends early), or None
    (also for a file of another kind).

    nibabel (and SimpleITK) hand on what a damaged ``.nii.gz`` decompresses to without checking its
    CRC: 64 zeroed bytes inside a heart mask made it a third smaller, silently.  Python's gzip
    reader checks the whole stream (about 1 s per 100 MB).
    """
    import gzip
    import zlib

    if not str(path).lower().endswith(".gz"):
        return None
    try:
        with gzip.open(path, "rb") as f:
            while f.read(1 << 22):
                pass
    except (gzip.BadGzipFile, EOFError, zlib.error) as exc:
        return str(exc) or type(exc).__name__
    return None


def is_analyze_header(head: bytes) -> bool:
    """Whether ``head`` (a file's first bytes) opens an Analyze 7.5 / NIfTI-1 header: its size, 348, in the
    first four bytes, in either byte order."""
    return len(head) >= 348 and 348 in (int.from_bytes(head[:4], "little"), int.from_bytes(head[:4], "big"))
