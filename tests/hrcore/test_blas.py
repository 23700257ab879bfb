"""hrcore.blas: sums that give the same bits on one BLAS thread as on two
(a Dask batch worker runs one; the single command one per core)."""

import numpy as np
from threadpoolctl import threadpool_limits

from hrcore.blas import gram, one_blas_thread


def _on_threads(n_threads, fn):
    with threadpool_limits(n_threads, user_api="blas"):
        return fn()


def test_gram_is_a_transposed_product_with_the_same_bits_on_any_thread_count():
    rng = np.random.default_rng(3)
    a, b = rng.normal(size=(4000, 59)), rng.normal(size=(4000, 6))
    np.testing.assert_allclose(gram(a, b), a.T @ b, rtol=1e-12, atol=1e-10)
    assert np.array_equal(_on_threads(1, lambda: gram(a, b)), _on_threads(2, lambda: gram(a, b)))


def test_one_blas_thread_restores_the_thread_count():
    from threadpoolctl import threadpool_info

    before = [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]
    with one_blas_thread():
        assert all(p["num_threads"] == 1 for p in threadpool_info() if p["user_api"] == "blas")
    assert [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"] == before
