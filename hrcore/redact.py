"""Notes without the names of a study's files, for what is written to disk.

Exported files are often named after the patient (``SMITH_JOHN.CT.0005.dcm``):
the readers' messages name the file they mean, which helps on the terminal, but
an output file names an input by its kind (README, *Reliability*).  What
:func:`file_namer` returns replaces every name (and path relative to the
study) of a file under the study in a text by ``a file``; names without a
letter or shorter than 3 characters (``1``, ``42``) cannot name anyone and are
left alone, so that numbers in the text stay.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable
from pathlib import Path

__all__ = ["file_namer"]

#: Most files looked at below a study (a study of 10 000 slices stays well below).
MAX_FILES = 100_000


def file_namer(study, *, placeholder: str = "a file") -> Callable[[str], str]:
    """A function that replaces the names of the files under ``study`` (a folder, or one file) in a text."""
    study = Path(study)
    names: set[str] = set()
    if study.is_file():
        names.add(study.name)
    elif study.is_dir():
        for n, path in enumerate(p for p in study.rglob("*") if not p.is_dir()):
            if n >= MAX_FILES:
                break
            rel = path.relative_to(study).as_posix()
            names.update((rel, path.name, rel.replace("/", os.sep)))
    names = {s for s in names if len(s) >= 3 and re.search(r"[^\W\d_]", s)}
    if not names:
        return lambda text: text
    # a whole name: not inside a longer word or path (the characters around are no name's)
    pattern = re.compile(r"(?<![\w.\-])(?:" + "|".join(map(re.escape, sorted(names, key=len, reverse=True)))
                         + r")(?![\w\-]|\.\w)")
    return lambda text: pattern.sub(placeholder, text)
