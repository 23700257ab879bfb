"""A package's public names imported on first use (PEP 562).

A package ``__init__`` that imports all its modules makes ``import pkg.small``
pay for every one of them: the command line's parser reads the phantom's
presets (``heartreg.phantom.config``) and would otherwise import the whole
phantom (scipy.stats, pydicom, ~1 s) for ``heartreg model``.
"""

from __future__ import annotations

import importlib
import sys

__all__ = ["lazy_exports"]


def lazy_exports(package: str, modules: dict[str, tuple[str, ...]]):
    """``__getattr__`` and ``__dir__`` for ``package`` whose names live in ``modules``.

    Parameters
    ----------
    package : str
        The package's ``__name__``.
    modules : dict of str to tuple of str
        Submodule (dotted, absolute) -> the public names it defines.

    Returns
    -------
    getattr, dir : callables
        Assign them to the package's ``__getattr__`` and ``__dir__``; a name is
        imported from its module on first access and kept in the package.

    Examples
    --------
    >>> get, _ = lazy_exports("json", {"json.decoder": ("JSONDecodeError",)})
    >>> get("JSONDecodeError").__name__
    'JSONDecodeError'
    """
    where = {name: module for module, names in modules.items() for name in names}

    def __getattr__(name: str):
        module = where.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(module), name)
        setattr(sys.modules[package], name, value)
        return value

    def __dir__():
        return sorted(set(vars(sys.modules[package])) | set(where))

    return __getattr__, __dir__
