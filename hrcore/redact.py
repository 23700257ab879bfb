"""Notes without the names of a study's files, for what is written to disk.

Exported files are often named after the patient (``SMITH_JOHN.CT.0005.dcm``):
the readers' messages name the file they mean, which helps on the terminal, but
an output file names an input by its kind (README, *Reliability*).  What
:func:`file_namer` returns replaces every name (and path relative to the
study) of a file under the study in a text by ``a file``; names without a
letter or shorter than 3 characters (``1``, ``42``) cannot name anyone and are
left alone, so that numbers in the text stay.

DICOM UIDs of the study (Study, Series, SOP Instance, Frame of Reference) identify
it as well: DICOM PS3.15's Basic Application Level Confidentiality Profile
replaces them ("U" action) by UIDs that are internally consistent.  What an
output writes or a summary prints is :func:`pseudonym_uid` of the UID:
``2.25.`` followed by the first 128 bits of the SHA-256 of the UID's text, as
a decimal integer (a UUID-derived UID, PS3.5 B.2).  The same UID gives the same
pseudonym in every output (a model and a phase report of one series name the
same one), and a user who holds the study can confirm that an output belongs
to it by hashing the study's UID, while the output does not carry it.
:func:`pseudonymize_uids` does the same for the UIDs inside a text (a note).
"""

from __future__ import annotations

import hashlib
import os
import re
from collections.abc import Callable
from pathlib import Path

__all__ = ["file_namer", "pseudonym_uid", "pseudonymize_uids", "PSEUDONYM_IN_TEXT", "UID_IN_TEXT"]

#: Most files looked at below a study (a study of 10 000 slices stays well below).
MAX_FILES = 100_000
#: A DICOM UID inside a text: dotted digits, at least five components (a version "1.2.3" is none).
UID_IN_TEXT = re.compile(r"(?<![\w.])\d+(?:\.\d+){4,}(?![\w.])")
#: A pseudonym inside a text (:func:`pseudonym_uid`: ``2.25.`` and a decimal integer), which UID_IN_TEXT's
#: five components do not match.
PSEUDONYM_IN_TEXT = re.compile(r"(?<![\w.])2\.25\.\d+(?![\w.])")
#: The root of the UIDs the DICOM standard defines (SOP classes, transfer syntaxes): they name no study.
STANDARD_ROOT = "1.2.840.10008."


def pseudonym_uid(uid: str) -> str:
    """The UID written in place of ``uid``: ``2.25.`` and the first 128 bits of its SHA-256 ('' stays '').

    ``uid`` is hashed as its text without the space or NUL that pads a DICOM value.

    >>> pseudonym_uid("1.2.3.4.5") == pseudonym_uid("1.2.3.4.5 ") != pseudonym_uid("1.2.3.4.6")
    True
    >>> pseudonym_uid("")
    ''
    """
    uid = uid.strip(" \0")
    if not uid:
        return ""
    return "2.25." + str(int(hashlib.sha256(uid.encode()).hexdigest()[:32], 16))


def pseudonymize_uids(text: str) -> str:
    """``text`` with every DICOM UID in it replaced by its :func:`pseudonym_uid`, but the standard's own."""
    return UID_IN_TEXT.sub(lambda m: m[0] if m[0].startswith(STANDARD_ROOT) else pseudonym_uid(m[0]), text)


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
