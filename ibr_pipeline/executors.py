"""Executors for per-view tasks: in-process, a local process pool, or a Dask cluster.

All three run the same picklable task function (`runner.run_view_task`) on the same arguments and
yield `(index, result, exception)` as tasks finish, so a stage's outputs are identical whichever ran
it; only the coordinating process writes records. They live apart from runner.py, which is about
planning and records.
"""
from __future__ import annotations

import logging
import multiprocessing
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from typing import Callable, Iterator, Sequence

log = logging.getLogger("ibr_pipeline.executors")


class Executor:
    name = "executor"

    def map_unordered(self, fn: Callable, argsets: Sequence[tuple]) -> Iterator[tuple]:
        raise NotImplementedError

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class LocalExecutor(Executor):
    """`jobs` worker processes (spawned: safe with open3d/torch threads); jobs=1 runs in-process."""

    def __init__(self, jobs: int = 1):
        if jobs < 1:
            raise ValueError("jobs must be >= 1")
        self.jobs = jobs
        self.name = "in-process" if jobs == 1 else f"process pool ({jobs} workers)"
        self._pool: ProcessPoolExecutor | None = None

    def map_unordered(self, fn, argsets):
        if self.jobs == 1 or len(argsets) <= 1:
            for i, args in enumerate(argsets):
                try:
                    yield i, fn(*args), None
                except Exception as e:  # reported per task; KeyboardInterrupt still stops the run
                    yield i, None, e
            return
        if self._pool is None:
            self._pool = ProcessPoolExecutor(self.jobs, mp_context=multiprocessing.get_context("spawn"))
        futures = {self._pool.submit(fn, *args): i for i, args in enumerate(argsets)}
        try:
            for fut in as_completed(futures):
                exc = fut.exception()
                yield futures[fut], (None if exc else fut.result()), exc
        except BrokenProcessPool as e:  # a worker died (segfault, OOM kill): remaining tasks fail
            for fut, i in futures.items():
                if not fut.done():
                    yield i, None, e
            self._pool = None
        finally:
            for fut in futures:
                fut.cancel()

    def close(self):
        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)
            self._pool = None


class DaskExecutor(Executor):
    """Per-view tasks on a Dask cluster: an existing scheduler address, or a LocalCluster of n workers.

    Workers need `ibr_pipeline` importable and the workspace on a shared file system at the same path.
    """

    def __init__(self, scheduler: str | None = None, local_workers: int = 0):
        from distributed import Client, LocalCluster

        self._cluster = None
        if scheduler:
            self.client = Client(scheduler, timeout="30s")
            self.name = f"dask ({scheduler})"
        else:
            self._cluster = LocalCluster(n_workers=max(1, local_workers), threads_per_worker=1,
                                         processes=True, dashboard_address=None)
            self.client = Client(self._cluster)
            self.name = f"dask LocalCluster ({max(1, local_workers)} workers)"

    def map_unordered(self, fn, argsets):
        from distributed import as_completed as dask_as_completed

        futures = [self.client.submit(fn, *args, pure=False) for args in argsets]
        index = {f.key: i for i, f in enumerate(futures)}
        try:
            for fut in dask_as_completed(futures):
                if fut.status == "error":
                    yield index[fut.key], None, fut.exception()
                else:
                    yield index[fut.key], fut.result(), None
        finally:
            self.client.cancel([f for f in futures if not f.done()])

    def close(self):
        self.client.close()
        if self._cluster is not None:
            self._cluster.close()


def make_executor(jobs: int = 1, dask_scheduler: str | None = None, dask_local: int = 0) -> Executor:
    if dask_scheduler or dask_local:
        return DaskExecutor(dask_scheduler, dask_local)
    return LocalExecutor(jobs)
