"""BLAS thread limiting (``femodel._blas``) and a small thread pool for the calibration kernels."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

from femodel._blas import blas_threads, data_threads

_POOL: tuple | None = None  # (threads, ThreadPoolExecutor)


def thread_map(fn, items, threads: int | None = None) -> list:
    """``[fn(x) for x in items]`` on :func:`data_threads` threads, BLAS limited to one thread each.

    For kernels whose work is NumPy/LAPACK calls on independent pieces (they
    release the GIL): the pieces of one evaluation run side by side on the
    cores instead of one BLAS call at a time.
    """
    global _POOL
    items = list(items)
    n = min(data_threads() if threads is None else threads, len(items))
    if n <= 1:
        return [fn(x) for x in items]
    if _POOL is None or _POOL[0] != n:
        if _POOL is not None:
            _POOL[1].shutdown(wait=False)
        _POOL = (n, ThreadPoolExecutor(max_workers=n, thread_name_prefix="frfcal-data"))
    with blas_threads(1):
        return list(_POOL[1].map(fn, items))
