"""One executor for independent units of work: in-process, local processes, or a Dask cluster.

Stages hand their independent units (SIFT and pair matching, oblique sub-block adjustments, dense pairs,
buildings, atlases) to :meth:`Executor.map`; the run's configuration decides where they run. Functions and
arguments must be picklable (module-level functions) for the ``processes`` and ``dask`` modes.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Sequence
from typing import Any

from ..errors import ConfigError

MODES = ("inline", "processes", "dask")


class Executor:
    """Maps a function over items.

    Parameters
    ----------
    mode : ``inline`` (this process, in order), ``processes`` (a local process pool) or ``dask``
    workers : process count for ``processes``, worker count for a Dask ``LocalCluster``
    address : scheduler address (``tcp://host:8786``) for ``dask``; without it a LocalCluster is started
    """

    def __init__(self, mode: str = "inline", workers: int = 2, address: str | None = None) -> None:
        if mode not in MODES:
            raise ConfigError(f"unknown executor mode '{mode}' (use one of {', '.join(MODES)})")
        self.mode = mode
        self.workers = max(1, int(workers))
        self.address = address
        self._pool = None
        self._client = None
        self._cluster = None

    @property
    def threads_per_worker(self) -> int:
        """BLAS/OpenMP threads of each local worker process: the cores of this process divided among the workers."""
        return max(1, len(os.sched_getaffinity(0)) // self.workers)

    def map(self, fn: Callable[..., Any], items: Sequence[Any] | Iterable[Any],
            on_done: Callable[[int, int], None] | None = None) -> list[Any]:
        """``[fn(item) for item in items]``, possibly in parallel; results keep the order of ``items``.

        ``on_done(done, total)`` is called in this process as units finish (progress and cancellation: the
        callback may raise :class:`~..errors.Cancelled`, which cancels the remaining units).
        """
        items = list(items)
        total = len(items)
        if self.mode == "inline" or total <= 1 and self.mode != "dask":
            out = []
            for i, it in enumerate(items):
                out.append(fn(it))
                if on_done is not None:
                    on_done(i + 1, total)
            return out
        if self.mode == "processes":
            return self._map_processes(fn, items, on_done)
        return self._map_dask(fn, items, on_done)

    def _map_processes(self, fn, items, on_done):
        import concurrent.futures as cf
        import multiprocessing as mp

        if self._pool is None:
            self._pool = cf.ProcessPoolExecutor(max_workers=self.workers, mp_context=mp.get_context("spawn"),
                                                initializer=limit_threads, initargs=(self.threads_per_worker,))
        futures = {self._pool.submit(fn, it): i for i, it in enumerate(items)}
        out: list[Any] = [None] * len(items)
        done = 0
        try:
            for fut in cf.as_completed(futures):
                out[futures[fut]] = fut.result()
                done += 1
                if on_done is not None:
                    on_done(done, len(items))
        except BaseException:
            for fut in futures:
                fut.cancel()
            raise
        return out

    def _map_dask(self, fn, items, on_done):
        from distributed import Client, LocalCluster, as_completed

        if self._client is None:
            if self.address:
                self._client = Client(self.address)
            else:
                self._cluster = LocalCluster(n_workers=self.workers, threads_per_worker=1, processes=True,
                                             dashboard_address=None)
                self._client = Client(self._cluster)
        futures = self._client.map(fn, items, pure=False)
        index = {f.key: i for i, f in enumerate(futures)}
        out: list[Any] = [None] * len(items)
        done = 0
        try:
            for fut in as_completed(futures):
                out[index[fut.key]] = fut.result()
                done += 1
                if on_done is not None:
                    on_done(done, len(items))
        except BaseException:
            self._client.cancel(futures)
            raise
        return out

    def close(self) -> None:
        """Shut down the pool or the Dask client (and its LocalCluster, if this executor started one)."""
        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)
            self._pool = None
        if self._client is not None:
            self._client.close()
            self._client = None
        if self._cluster is not None:
            self._cluster.close()
            self._cluster = None

    def __enter__(self) -> Executor:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def limit_threads(threads: int) -> None:
    """Initializer of the local worker processes: ``threads`` threads for the BLAS and OpenMP pools, those loaded
    already (threadpoolctl) and those loaded later (environment). Each worker would otherwise start a BLAS thread
    per core, and the workers' threads would spin against each other: on 2 cores the least-squares matching of the
    demo block took 59 s in two workers with OpenBLAS' default, 37 s with one thread each."""
    from threadpoolctl import threadpool_limits

    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = str(threads)
    threadpool_limits(threads)
