"""BLAS thread limiting for the calibration kernels."""

from __future__ import annotations


def blas_threads(n: int):
    """Context limiting BLAS to ``n`` threads (no-op without threadpoolctl).

    Parameters
    ----------
    n : int
        Maximum number of BLAS threads inside the context.
    """
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        import contextlib

        return contextlib.nullcontext()
    return threadpool_limits(limits=n, user_api="blas")
