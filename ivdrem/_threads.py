"""One BLAS thread while ivdrem steps a loop.

The engine calls LAPACK on small matrices many times per step (the SVD of Ψ in the mixing
(17), the max-hold's eigensolver): BLAS threads only add synchronisation there.  Measured on
this project's 2-core machine under load, numba's SVD of a 43 x 43 Ψ (the Panda's size):
9 ms with OpenBLAS's default 2 threads, 0.7 ms with one.  The limit holds only inside the
``with`` block, so a user's own numpy keeps its threads outside ivdrem's runs.
"""
from __future__ import annotations

from contextlib import contextmanager

__all__ = ["one_blas_thread"]


@contextmanager
def one_blas_thread():
    """Limit every loaded BLAS library (OpenBLAS, MKL, BLIS) to one thread inside the block."""
    from threadpoolctl import threadpool_limits
    with threadpool_limits(limits=1, user_api="blas"):
        yield
