"""Sums whose result does not depend on how many threads BLAS runs.

OpenBLAS splits a long product such as ``A.T @ B`` (3000 x 59 by 3000 x 6)
over its threads along the summed axis and adds the partial sums at the end,
so the last bits of the result depend on the thread count: a Dask batch
worker (one BLAS thread) and the single command (one per core) would write
different bytes.  :func:`gram` sums on one BLAS thread, in an order fixed by
the shapes alone; :func:`one_blas_thread` runs any block (a LAPACK solver,
say) on one BLAS thread, as a batch worker does.
"""

from __future__ import annotations

import contextlib
import functools

import numpy as np

__all__ = ["gram", "one_blas_thread"]


def gram(a, b) -> np.ndarray:
    """``a.T @ b`` on one BLAS thread: the same bits whatever the thread count.

    Parameters
    ----------
    a : (n, k) float
    b : (n, m) float

    Returns
    -------
    (k, m) float64

    Examples
    --------
    >>> import numpy as np
    >>> a = np.arange(6.0).reshape(3, 2)
    >>> gram(a, a).tolist()
    [[20.0, 26.0], [26.0, 35.0]]
    """
    # one thread sums in one order (numpy's own einsum loops would too, but ~6x slower)
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    with one_blas_thread():
        return a.T @ b


@functools.lru_cache(maxsize=1)
def _controller():
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController()


@contextlib.contextmanager
def one_blas_thread():
    """Run the block with BLAS (and LAPACK) on one thread, then restore the count.

    Examples
    --------
    >>> import numpy as np
    >>> with one_blas_thread():
    ...     x = np.linalg.lstsq(np.eye(3), np.ones(3), rcond=None)[0]
    >>> x.tolist()
    [1.0, 1.0, 1.0]
    """
    with _controller().limit(limits=1, user_api="blas"):
        yield
