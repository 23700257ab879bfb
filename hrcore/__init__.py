"""The bottom layer of heartreg: what every package shares.

``hrcore`` imports nothing from ``imaging``, ``modeling``, ``registration`` or
``heartreg``; they all import from it. It holds the error family
(:class:`HeartregError`) and the output contract (:mod:`hrcore.output`: stage,
one rename, nothing left behind, never into an input).
"""

from hrcore.errors import HeartregError, UsageError
from hrcore.output import OutputError, check_output_path, staged_output

__all__ = ["HeartregError", "OutputError", "UsageError", "check_output_path", "staged_output"]
