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
