"""The bottom layer of heartreg: what every package shares.

``hrcore`` imports nothing from ``imaging``, ``modeling``, ``registration`` or
``heartreg``; they all import from it. It holds the error family
(:class:`HeartregError`, :mod:`hrcore.errors`), the output contract
(:func:`staged_output`, :mod:`hrcore.output`: stage, one rename, nothing left
behind, never into an input), the 4x4 geometry (:mod:`hrcore.geometry`) and the
base of the option records (:mod:`hrcore.options`).
"""

from hrcore.errors import HeartregError
from hrcore.output import staged_output

__all__ = ["HeartregError", "staged_output"]
