"""One executor interface for independent work (starts, CV realizations, ensemble members).

Anything with ``map(fn, items) -> list`` (results in item order) is an
executor. Three are provided, each also with ``start()`` (warm up before the
first map) and ``close()``: in-process serial, a local spawn-safe process
pool (default; workers capped at ``os.cpu_count()``) and a Dask distributed
cluster named by its scheduler address. ``fn`` must be a picklable
module-level function and items picklable values.
"""

from __future__ import annotations

import os
from typing import Callable, Iterable, Protocol, runtime_checkable

from calibration._errors import CalibrationError


@runtime_checkable
class Executor(Protocol):
    """Maps a function over independent items; returns the results in item order.

    ``width`` (optional; 1 when absent) is how many items run at once: a caller that submits in
    rounds (the multi-start's stopping rule) sizes its rounds by it."""

    def map(self, fn: Callable, items: Iterable) -> list: ...


def _progress(iterable, total, label):
    if label is None:
        return iterable
    try:
        from tqdm import tqdm
    except ImportError:  # pragma: no cover - tqdm is a core dependency
        return iterable
    return tqdm(iterable, total=total, desc=label, leave=False)


class SerialExecutor:
    """Runs everything in this process (debugging, tiny problems, nested use inside workers)."""

    def __init__(self, progress: str | None = None):
        self.progress = progress

    @property
    def width(self) -> int:
        """Items run at once: 1."""
        return 1

    def map(self, fn: Callable, items: Iterable) -> list:
        items = list(items)
        return [fn(x) for x in _progress(items, len(items), self.progress)]

    def start(self, modules: tuple = ()) -> None:
        """Nothing to start (same interface as :meth:`ProcessExecutor.start`)."""
        return None

    def close(self) -> None:
        return None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _import_modules(modules: tuple) -> None:
    import importlib

    for name in modules:
        importlib.import_module(name)


class ProcessExecutor:
    """Local process pool (``spawn`` start method, safe with threads and on every OS).

    Parameters
    ----------
    max_workers : int, optional
        Number of worker processes; default and cap is ``os.cpu_count()``.
    progress : str, optional
        Show a progress bar with this label on stderr.
    """

    def __init__(self, max_workers: int | None = None, progress: str | None = None):
        n = os.cpu_count() or 1
        if max_workers is not None and max_workers < 1:
            raise CalibrationError(f"execution.workers must be >= 1, got {max_workers}")
        self.max_workers = min(max_workers or n, n)
        self.progress = progress
        self._pool = None

    def _get_pool(self):
        if self._pool is None:
            import multiprocessing as mp
            from concurrent.futures import ProcessPoolExecutor

            self._pool = ProcessPoolExecutor(self.max_workers, mp_context=mp.get_context("spawn"))
        return self._pool

    def start(self, modules: tuple = ("calibration._fit",)) -> None:
        """Spawn the workers now and import ``modules`` in them, without waiting.

        A spawned worker needs 1-2 s to start Python and import numpy, scipy
        and this package. Started while the main process builds the reduction
        basis (single-threaded Lanczos), that time overlaps with the build
        instead of adding to the first multi-start.
        """
        if self.max_workers == 1:
            return
        pool = self._get_pool()
        for _ in range(self.max_workers):
            pool.submit(_import_modules, tuple(modules))

    @property
    def width(self) -> int:
        """Items run at once: the workers."""
        return self.max_workers

    def map(self, fn: Callable, items: Iterable) -> list:
        """``[fn(x) for x in items]`` in the workers. A list or tuple of one item runs here; any other
        iterable (a generator) is submitted item by item as it yields, so the caller's work producing the
        next item (e.g. the screening's next candidate extension) overlaps with the workers' runs."""
        lazy = not isinstance(items, (list, tuple))
        if self.max_workers == 1 or (not lazy and len(items) <= 1):
            items = list(items)
            return [fn(x) for x in _progress(items, len(items), self.progress)]
        from concurrent.futures import as_completed

        pool = self._get_pool()
        futures = {pool.submit(fn, x): i for i, x in enumerate(items)}
        items = range(len(futures))
        out = [None] * len(items)
        for fut in _progress(as_completed(futures), len(items), self.progress):
            out[futures[fut]] = fut.result()
        return out

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class DaskExecutor:
    """A Dask distributed cluster, by scheduler address (``tcp://host:8786``) or an existing Client.

    Needs the ``dask`` extra (``pip install frfcal[dask]``).
    """

    def __init__(self, address=None, client=None, progress: str | None = None, cluster=None):
        try:
            from distributed import Client
        except ImportError as exc:
            raise CalibrationError(
                "execution.scheduler needs dask.distributed: install the 'dask' extra (pip install frfcal[dask])"
            ) from exc
        if client is None:
            if not address:
                raise CalibrationError("DaskExecutor needs a scheduler address or a Client")
            try:
                client = Client(address, timeout="10s")
            except OSError as exc:
                raise CalibrationError(f"cannot reach Dask scheduler at {address}: {exc}") from exc
            self._own = True
        else:
            self._own = False
        self.client = client
        self.progress = progress
        self._cluster = cluster

    @classmethod
    def local(cls, n_workers: int | None = None, host: str = "127.0.0.1", progress: str | None = None):
        """Start a ``distributed.LocalCluster`` of worker processes on ``host`` (loopback by default) and use it.

        The scheduler, workers and the dashboard listen on ``host`` only; the
        cluster is shut down by :meth:`close`.
        """
        try:
            from distributed import Client, LocalCluster
        except ImportError as exc:
            raise CalibrationError(
                "execution.scheduler = \"local\" needs dask.distributed: install the 'dask' extra "
                "(pip install frfcal[dask])"
            ) from exc
        n = n_workers or os.cpu_count() or 1
        cluster = LocalCluster(host=host, n_workers=n, threads_per_worker=1, processes=True,
                               dashboard_address=f"{host}:0")
        ex = cls(client=Client(cluster), progress=progress, cluster=cluster)
        ex._own = True
        return ex

    @property
    def width(self) -> int:
        """Items run at once: the cluster's worker threads (at least 1)."""
        try:
            return max(sum(self.client.nthreads().values()), 1)
        except (OSError, TimeoutError):  # a scheduler that does not answer: rounds of one
            return 1

    def map(self, fn: Callable, items: Iterable) -> list:
        items = list(items)
        if not items:
            return []
        futures = self.client.map(fn, items, pure=False)
        return self.client.gather(futures)

    def start(self, modules: tuple = ()) -> None:
        """Nothing to start: the cluster's workers are already running."""
        return None

    def close(self) -> None:
        if self._own:
            self.client.close()
            if self._cluster is not None:
                self._cluster.close()
                self._cluster = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def make_executor(scheduler: str | None = None, workers: int | None = None, progress: str | None = None,
                  host: str = "127.0.0.1"):
    """Dask when a scheduler address is given, else a local process pool (serial when workers == 1).

    ``scheduler="local"`` starts a Dask LocalCluster of ``workers`` processes
    listening on ``host`` (loopback unless another interface is named).
    """
    if scheduler == "local":
        return DaskExecutor.local(workers, host=host, progress=progress)
    if scheduler:
        return DaskExecutor(scheduler, progress=progress)
    if workers == 1:
        return SerialExecutor(progress=progress)
    return ProcessExecutor(workers, progress=progress)
