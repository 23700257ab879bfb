"""The base of the frozen option records that the library, the pipeline and the
command share (:class:`modeling.ModelOptions`, :class:`registration.RegistrationOptions`).

Examples
--------
>>> from dataclasses import dataclass
>>> from hrcore.options import OptionsRecord
>>> @dataclass(frozen=True)
... class Knobs(OptionsRecord):
...     step_mm: float = 1.0
...     extra: dict | None = None
...     def __post_init__(self):
...         self._freeze_mapping("extra")
>>> Knobs.of(step_mm=2.0)
Knobs(step_mm=2.0, extra=None)
>>> Knobs.of(Knobs(extra={"a": 1})).extra["a"]
1
"""

from __future__ import annotations

import dataclasses
from types import MappingProxyType

__all__ = ["OptionsRecord"]


class OptionsRecord:
    """Mixin of a frozen options dataclass: copying with overrides, read-only mappings."""

    __slots__ = ()

    @classmethod
    def of(cls, options=None, **overrides):
        """``options`` (default: the defaults) with some fields replaced.

        Parameters
        ----------
        options : cls, optional
            The options to start from; None: ``cls()``.
        **overrides
            Fields to replace (checked again by the class's ``__post_init__``).

        Returns
        -------
        cls
            ``options`` itself when nothing is overridden.

        Raises
        ------
        TypeError
            ``options`` is not a ``cls``.
        """
        base = cls() if options is None else options
        if not isinstance(base, cls):
            raise TypeError(f"options must be a {cls.__name__}, got {type(base).__name__}")
        return dataclasses.replace(base, **overrides) if overrides else base

    def _freeze_mapping(self, name: str) -> None:
        """Replace the mapping field ``name`` (unless None) by a read-only copy (in ``__post_init__``)."""
        value = getattr(self, name)
        if value is not None:
            object.__setattr__(self, name, MappingProxyType(dict(value)))
