"""Arrays in JSON files: nested lists of numbers, exact, non-finite values as ``null``.

Python writes a float as its shortest exact ``repr``, so an array written by
:func:`json_floats` and read back by :func:`float_array` is bit for bit the
array that was written (NaN and infinities, which JSON cannot hold, come back
as NaN).

Examples
--------
>>> import json, numpy as np
>>> a = np.array([[0.1, np.nan], [1e-300, 2.0]])
>>> text = json.dumps(json_floats(a))
>>> text
'[[0.1, null], [1e-300, 2.0]]'
>>> b = float_array(json.loads(text))
>>> bool(np.array_equal(a, b, equal_nan=True)), b.flags.writeable
(True, False)
"""

from __future__ import annotations

import numpy as np

from hrcore.geometry import frozen

__all__ = ["json_floats", "float_array", "int_array", "bool_array"]


def json_floats(a) -> list:
    """Nested lists of Python floats, non-finite entries as ``None``."""
    a = np.asarray(a, dtype=float)
    out = a.astype(object)
    out[~np.isfinite(a)] = None
    return out.tolist()


def float_array(values, shape=None) -> np.ndarray:
    """A read-only float64 array from nested lists (``None`` as NaN).

    Parameters
    ----------
    values : nested lists of numbers or None
    shape : tuple of int, optional
        The shape it must have (``-1`` for any length).

    Raises
    ------
    ValueError
        Ragged lists, non-numbers, or another shape.
    """
    a = np.array(values, dtype=float)
    _check_shape(a, shape)
    return frozen(a)


def int_array(values, shape=None) -> np.ndarray:
    """A read-only int64 array from nested lists of integers."""
    a = np.array(values, dtype=np.int64)
    _check_shape(a, shape)
    return frozen(a)


def bool_array(values, shape=None) -> np.ndarray:
    """A read-only bool array from nested lists of booleans."""
    if not all(isinstance(v, bool) for v in np.ravel(np.array(values, dtype=object))):
        raise ValueError("expected booleans")
    a = np.array(values, dtype=bool)
    _check_shape(a, shape)
    return frozen(a)


def _check_shape(a: np.ndarray, shape) -> None:
    if shape is None:
        return
    if a.ndim != len(shape) or any(s not in (-1, n) for s, n in zip(shape, a.shape)):
        raise ValueError(f"expected shape {tuple(shape)}, got {a.shape}")
