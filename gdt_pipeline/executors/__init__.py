"""The built-in tile executors, registered through the ``gdt_executors`` hook like a third party's:

- ``serial``: every tile in this process, one after the other (any registry, no pickling);
- ``processes``: a local pool of worker processes (``concurrent.futures``, started fresh: no forked OpenMP state);
- ``dask``: a dask.distributed cluster, a ``LocalCluster`` by default or a running scheduler at ``--address``.

Tasks are handed out as workers free up, at most twice as many in flight as workers, so the tiles cut but not yet
run never pile up in memory.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from typing import Any

from ..plugins import ExecutorOptions, ExecutorSpec, hookimpl

IN_FLIGHT_PER_WORKER = 2


def _workers(options: ExecutorOptions) -> int:
    return options.workers or os.cpu_count() or 1


class SerialExecutor:
    """Tiles one after the other in this process."""

    dashboard: str | None = None

    def map(self, fn: Callable[[Any], Any], tasks: Iterable[Any], done: Callable[[int, Any], None] | None = None
            ) -> list[Any]:
        """``fn(task)`` for each task in turn."""
        out = []
        for i, task in enumerate(tasks):
            out.append(fn(task))
            if done is not None:
                done(i, out[-1])
        return out


def _bounded(submit: Callable[[Any], Any], wait_some: Callable[[set], set], tasks: Iterable[Any], limit: int,
             done: Callable[[int, Any], None] | None) -> list[Any]:
    """Submit tasks keeping at most ``limit`` in flight; results in task order."""
    futures: dict[Any, int] = {}
    results: dict[int, Any] = {}
    pending: set = set()
    for i, task in enumerate(tasks):
        while len(pending) >= limit:
            pending = _collect(wait_some(pending), pending, futures, results, done)
        fut = submit(task)
        futures[fut] = i
        pending.add(fut)
    while pending:
        pending = _collect(wait_some(pending), pending, futures, results, done)
    return [results[i] for i in range(len(results))]


def _collect(finished: set, pending: set, futures: dict[Any, int], results: dict[int, Any],
             done: Callable[[int, Any], None] | None) -> set:
    for fut in finished:
        results[futures[fut]] = fut.result()  # a worker's exception surfaces here, with its own message
        if done is not None:
            done(futures[fut], results[futures[fut]])
    return pending - finished


class PoolExecutor:
    """Tiles on a local pool of worker processes."""

    dashboard: str | None = None

    def __init__(self, pool: ProcessPoolExecutor, workers: int) -> None:
        self.pool, self.workers = pool, workers

    def map(self, fn: Callable[[Any], Any], tasks: Iterable[Any], done: Callable[[int, Any], None] | None = None
            ) -> list[Any]:
        """``fn(task)`` on the pool's workers."""
        def wait_some(pending: set[Future]) -> set[Future]:
            return wait(pending, return_when=FIRST_COMPLETED).done

        return _bounded(lambda t: self.pool.submit(fn, t), wait_some, tasks, IN_FLIGHT_PER_WORKER * self.workers,
                        done)


class DaskExecutor:
    """Tiles on a dask.distributed cluster."""

    def __init__(self, client: Any, workers: int) -> None:
        self.client, self.workers = client, workers
        self.dashboard = getattr(client, "dashboard_link", None)

    def map(self, fn: Callable[[Any], Any], tasks: Iterable[Any], done: Callable[[int, Any], None] | None = None
            ) -> list[Any]:
        """``fn(task)`` on the cluster's workers; each task is scattered first (large arrays, not graph payload)."""
        from distributed import wait as dask_wait

        def submit(task: Any) -> Any:
            data = self.client.scatter(task, direct=True)
            return self.client.submit(fn, data, pure=False)

        def wait_some(pending: set) -> set:
            return set(dask_wait(list(pending), return_when="FIRST_COMPLETED").done)

        return _bounded(submit, wait_some, tasks, IN_FLIGHT_PER_WORKER * self.workers, done)


@contextlib.contextmanager
def open_serial(options: ExecutorOptions) -> Iterator[SerialExecutor]:
    """The in-process executor."""
    yield SerialExecutor()


@contextlib.contextmanager
def open_processes(options: ExecutorOptions) -> Iterator[PoolExecutor]:
    """A local pool of ``workers`` fresh processes, shut down on exit."""
    workers = _workers(options)
    with ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        yield PoolExecutor(pool, workers)


@contextlib.contextmanager
def open_dask(options: ExecutorOptions) -> Iterator[DaskExecutor]:
    """A client of the scheduler at ``address``, or of a LocalCluster of ``workers`` single-threaded processes."""
    try:
        from distributed import Client, LocalCluster
    except ImportError as exc:  # dask is a dependency; this guards a broken install
        raise RuntimeError("the dask executor needs dask.distributed: pip install 'dask[distributed]'") from exc
    if options.address:
        with Client(options.address) as client:
            yield DaskExecutor(client, max(1, len(client.scheduler_info().get("workers", {}))))
        return
    workers = _workers(options)
    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0",
                      memory_limit=0) as cluster, Client(cluster) as client:
        yield DaskExecutor(client, workers)


@hookimpl
def gdt_executors() -> list[ExecutorSpec]:
    """The built-in tile executors."""
    return [
        ExecutorSpec(name="serial", version="1.0.0", open=open_serial, in_process=True,
                     description="Every tile in this process, one after the other."),
        ExecutorSpec(name="processes", version="1.0.0", open=open_processes,
                     description="A local pool of worker processes (--workers, default one per core)."),
        ExecutorSpec(name="dask", version="1.0.0", open=open_dask,
                     description="A dask.distributed cluster: a LocalCluster, or --address tcp://host:port."),
    ]
