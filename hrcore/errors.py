"""One error family for the whole project.

Every domain error of heartreg derives from :class:`HeartregError`, and also
from the built-in it has always been (``ValueError`` for bad values,
``RuntimeError`` for a missing capability), so callers that caught the built-in
keep working. A caller catches ``HeartregError`` to handle the library's own
refusals without catching programming errors.

Examples
--------
>>> from hrcore import HeartregError
>>> class SeriesError(HeartregError, ValueError):
...     pass
>>> issubclass(SeriesError, ValueError)
True
"""

from __future__ import annotations


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
