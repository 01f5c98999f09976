"""BLAS thread limits for the process (threadpoolctl), shared by every layer above femodel."""

from __future__ import annotations

import contextlib
import os
import sys

_CONTROLLER: tuple | None = None  # (key, threadpoolctl.ThreadpoolController)
#: Modules that load a BLAS of their own (a sparse backend on the system BLAS): the controller is made again
#: when one of them has been imported since it was made.
BLAS_MODULES = ("sksparse.cholmod", "femodel._cholmod", "cholespy", "pypardiso")


def controller():
    """The process's ``threadpoolctl.ThreadpoolController`` (None without threadpoolctl).

    The libraries are found once per process (finding them takes ~5 ms) and again after a sparse backend
    with its own BLAS was imported.
    """
    global _CONTROLLER
    try:
        from threadpoolctl import ThreadpoolController
    except ImportError:
        return None
    key = tuple(m in sys.modules for m in BLAS_MODULES)
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
    ctl = controller()
    if ctl is None:
        return contextlib.nullcontext()
    return ctl.limit(limits=n, user_api="blas")


def data_threads() -> int:
    """Threads for data-parallel kernels of this process (``calibration._threads.thread_map``, the split
    solves of ``femodel._cholmod``).

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
