"""BLAS thread limiting and a small thread pool for the calibration kernels."""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

_POOL: tuple | None = None  # (threads, ThreadPoolExecutor)


_CONTROLLER: tuple | None = None  # (key, threadpoolctl.ThreadpoolController)
#: Modules that load a BLAS of their own (a sparse backend on the system BLAS): the controller is made again
#: when one of them has been imported since it was made.
_BLAS_MODULES = ("sksparse.cholmod", "cholespy", "pypardiso")


def _controller():
    """The process's ``threadpoolctl.ThreadpoolController`` (None without threadpoolctl).

    The libraries are found once per process (finding them takes ~5 ms) and again after a sparse backend
    with its own BLAS was imported.
    """
    global _CONTROLLER
    try:
        from threadpoolctl import ThreadpoolController
    except ImportError:
        return None
    import sys

    key = tuple(m in sys.modules for m in _BLAS_MODULES)
    if _CONTROLLER is None or _CONTROLLER[0] != key:
        _CONTROLLER = (key, ThreadpoolController())
    return _CONTROLLER[1]


def blas_threads(n: int):
    """Context limiting BLAS to ``n`` threads (no-op without threadpoolctl; the limit itself takes
    microseconds).

    Parameters
    ----------
    n : int
        Maximum number of BLAS threads inside the context.
    """
    ctl = _controller()
    if ctl is None:
        import contextlib

        return contextlib.nullcontext()
    return ctl.limit(limits=n, user_api="blas")


def data_threads() -> int:
    """Threads for data-parallel kernels of this process (:func:`thread_map`).

    ``FRFCAL_THREADS`` when set; else 1 in a worker process (a process pool's
    or a Dask worker: the parallelism is the pool's, and more threads would
    oversubscribe the cores), else the cores this process may run on.
    """
    env = os.environ.get("FRFCAL_THREADS")
    if env:
        try:
            return max(1, int(env))
        except ValueError:
            raise ValueError(f"FRFCAL_THREADS must be a whole number, got {env!r}") from None
    import multiprocessing

    if multiprocessing.parent_process() is not None:
        return 1
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


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
