"""Folders an output makes above itself, and takes away again when it writes nothing.

A command asked to write ``a/b/out`` where ``a/b`` does not exist makes ``a``
and ``a/b``; when it then fails it removes them (and only them: a folder
another process made meanwhile, or one that holds another's file, stays).
:func:`hrcore.output.staged_output` and ``heartreg track``'s log use them.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

__all__ = ["make_folders", "remove_folders"]


def make_folders(folder) -> list[Path]:
    """Make ``folder`` and the folders above it that are missing; the ones this call made, deepest first.

    One another process makes meanwhile is not in the list (not ours to remove); when a folder cannot be
    made, those made before it are removed and the error raised.
    """
    missing = []
    probe = Path(folder)
    while not probe.exists():
        missing.append(probe)
        probe = probe.parent
    made: list[Path] = []
    try:
        for d in reversed(missing):
            try:
                os.mkdir(d)
            except FileExistsError:  # another process (a parallel trial) made it first
                continue
            made.insert(0, d)
    except OSError:
        remove_folders(made)
        raise
    return made


def remove_folders(made) -> None:
    """Remove the folders of :func:`make_folders` (deepest first); one that is not empty stays."""
    for d in made:
        with contextlib.suppress(OSError):
            os.rmdir(d)
