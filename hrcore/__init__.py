"""The bottom layer of heartreg: what every package shares.

``hrcore`` imports nothing from ``imaging``, ``modeling``, ``registration`` or
``heartreg``; they all import from it. It holds the error family
(:class:`HeartregError`).
"""

from hrcore.errors import HeartregError

__all__ = ["HeartregError"]
