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
        if int(workers) < 1:
            raise ConfigError(f"the executor needs at least one worker, got {workers}")
        self.mode = mode
        self.workers = int(workers)
        self.address = address
        self._pool = None
        self._client = None
        self._cluster = None

    @property
    def threads_per_worker(self) -> int:
        """BLAS/OpenMP threads of each local worker process: the cores of this process divided among the workers."""
        return max(1, len(os.sched_getaffinity(0)) // self.workers)

    def map(self, fn: Callable[..., Any], items: Sequence[Any] | Iterable[Any],
            on_done: Callable[[int, int], None] | None = None, total: int | None = None) -> list[Any]:
        """``[fn(item) for item in items]``, possibly in parallel; results keep the order of ``items``.

        ``on_done(done, total)`` is called in this process as units finish (progress and cancellation: the
        callback may raise :class:`~..errors.Cancelled`, which cancels the remaining units). A lazy iterable
        (a generator) is drawn one item at a time and each unit is sent to the workers as soon as it is drawn, so
        that the workers start on the first units while the later ones are still being made; ``total`` is then
        its length for ``on_done`` (else counted as drawn).
        """
        if isinstance(items, Sequence):
            total = len(items)
            if self.mode == "processes" and total <= 1:
                return self._map_inline(fn, items, on_done, total)
        if self.mode == "inline":
            return self._map_inline(fn, items, on_done, total)
        if self.mode == "processes":
            return self._map_processes(fn, items, on_done, total)
        return self._map_dask(fn, items, on_done, total)

    @staticmethod
    def _map_inline(fn, items, on_done, total):
        out = []
        for it in items:
            out.append(fn(it))
            if on_done is not None:
                on_done(len(out), total or len(out))
        return out

    def _map_processes(self, fn, items, on_done, total):
        import concurrent.futures as cf
        import multiprocessing as mp

        if self._pool is None:
            self._pool = cf.ProcessPoolExecutor(max_workers=self.workers, mp_context=mp.get_context("spawn"),
                                                initializer=limit_threads, initargs=(self.threads_per_worker,))
        return _gather(lambda it: self._pool.submit(fn, it), items, cf.wait, cf.FIRST_COMPLETED,
                       lambda futs: [f.cancel() for f in futs], on_done, total)

    def _map_dask(self, fn, items, on_done, total):
        from distributed import Client, LocalCluster, wait

        if self._client is None:
            if self.address:
                self._client = Client(self.address)
            else:
                self._cluster = LocalCluster(n_workers=self.workers, threads_per_worker=1, processes=True,
                                             dashboard_address=None)
                self._client = Client(self._cluster)
        client = self._client
        return _gather(lambda it: client.submit(fn, it, pure=False), items, wait, "FIRST_COMPLETED",
                       client.cancel, on_done, total)

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


def _gather(submit: Callable[[Any], Any], items: Iterable[Any], wait: Callable, first_completed: Any,
            cancel: Callable[[list], Any], on_done: Callable[[int, int], None] | None, total: int | None) -> list[Any]:
    """The results of ``submit(item)`` (a future of ``concurrent.futures`` or of Dask, ``wait(futures, timeout,
    first_completed)`` as theirs) for each item, in order; items are submitted as they are drawn, finished units
    are reported while later items are drawn. On an error (or a cancellation from ``on_done``) the units not
    finished are cancelled."""
    futures: list = []
    out: dict[int, Any] = {}
    pending: set = set()
    index: dict = {}

    def collect(done: set) -> None:
        for fut in done:
            out[index[fut]] = fut.result()
            pending.discard(fut)
            if on_done is not None:
                on_done(len(out), total or len(futures))

    try:
        for it in items:
            fut = submit(it)
            index[fut] = len(futures)
            futures.append(fut)
            pending.add(fut)
            collect({f for f in pending if f.done()})
        while pending:
            collect(set(wait(list(pending), None, first_completed).done))
    except BaseException:
        cancel([f for f in futures if not f.done()])
        raise
    return [out[i] for i in range(len(futures))]


def limit_threads(threads: int) -> None:
    """Initializer of the local worker processes: ``threads`` threads for the BLAS and OpenMP pools, those loaded
    already (threadpoolctl) and those loaded later (environment). Each worker would otherwise start a BLAS thread
    per core, and the workers' threads would spin against each other: on 2 cores the least-squares matching of the
    demo block took 59 s in two workers with OpenBLAS' default, 37 s with one thread each."""
    from threadpoolctl import threadpool_limits

    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = str(threads)
    threadpool_limits(threads)
