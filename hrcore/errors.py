"""One error family for the whole project.

Every domain error of heartreg derives from :class:`HeartregError`, and also
from the built-in it has always been (``ValueError`` for bad values,
``RuntimeError`` for a missing capability), so callers that caught the built-in
keep working. A caller catches ``HeartregError`` to handle the library's own
refusals without catching programming errors. :func:`refusal_line` is the one
line a command prints for a refusal or an OS error (:func:`os_error_message`).

Examples
--------
>>> from hrcore import HeartregError
>>> class SeriesError(HeartregError, ValueError):
...     pass
>>> issubclass(SeriesError, ValueError)
True
"""

from __future__ import annotations

import errno


class HeartregError(Exception):
    """Base of every error heartreg raises on bad input or an impossible request.

    The message is one line that names the file or argument at fault and says
    what to do.
    """


class UsageError(HeartregError, ValueError):
    """A bad argument or option value: the message names the keyword argument
    (and the command-line flag, where there is one) and the values it takes."""


def read_json_object(path, *, keys=(), what: str = "file", error: type = HeartregError, fix: str = "") -> dict:
    """The JSON object in ``path``, with ``keys`` present; else ``error`` with one line naming the file.

    ``what`` names the file's kind in the message (``"phantom truth"``) and
    ``fix`` says what to do (``"write the case again with heartreg phantom"``).
    """
    import json
    from pathlib import Path

    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else type(exc).__name__
        raise error(f"{path} is not a readable {what} ({reason}){'; ' + fix if fix else ''}") from None
    missing = [k for k in keys if not isinstance(doc, dict) or k not in doc]
    if not isinstance(doc, dict) or missing:
        held = f"lacks {', '.join(map(repr, missing))}" if isinstance(doc, dict) else "is no JSON object"
        raise error(f"{path} {held}: not a {what}{'; ' + fix if fix else ''}")
    return doc


# ------------------------------------------------------------------ OS errors as one line
def root_os_error(exc: BaseException) -> BaseException:
    """The OS error behind ``exc`` (``exc`` when none): a library may re-raise one errno-less, its traceback in
    the message (pydicom's writer: "With tag (7FE0,0010) got exception: [Errno 28] ...")."""
    seen = exc
    while seen is not None and not (isinstance(seen, OSError) and seen.errno is not None):
        seen = seen.__cause__ or seen.__context__
    return exc if seen is None else seen


def os_error_message(exc: OSError, *, what: str = "") -> str:
    """One line for an OS error: the file, the reason in words, what to do."""
    exc = root_os_error(exc)
    name = exc.filename or what or "a file"
    reason = exc.strerror or str(exc) or type(exc).__name__
    hint = {
        errno.ENOSPC: "free disk space or choose an output on another disk",
        errno.EDQUOT: "free space within your quota or choose another disk",
        errno.EACCES: "check the permissions or choose another path",
        errno.EPERM: "check the permissions or choose another path",
        errno.EROFS: "choose an output on a writable disk",
        errno.ENOENT: "check the path",
    }.get(exc.errno, "check the path and rerun")
    return f"{name}: {reason}; {hint}"


def refusal_line(exc: BaseException) -> str | None:
    """The one line a command prints for a refusal (a :class:`HeartregError` or an
    OS error, translated); None for anything else, which is a bug.

    The study's DICOM UIDs in it are their pseudonyms (:func:`hrcore.redact.pseudonymize_uids`):
    the line is printed, and ``heartreg batch`` writes it into its records."""
    from hrcore.redact import pseudonymize_uids

    if isinstance(exc, OSError) and getattr(root_os_error(exc), "strerror", None):
        return pseudonymize_uids(os_error_message(exc))
    if isinstance(exc, (HeartregError, OSError)):
        return pseudonymize_uids(" ".join(str(exc).split())) or type(exc).__name__
    return None
