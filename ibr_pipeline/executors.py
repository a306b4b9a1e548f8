"""Executors for per-view tasks: in-process, a local process pool, or a Dask cluster.

All three run the same picklable task function (`runner.run_view_task`) on the same arguments and
yield `(index, result, exception)` as tasks finish, so a stage's outputs are identical whichever ran
it; only the coordinating process writes records. They live apart from runner.py, which is about
planning and records.
"""
from __future__ import annotations

import logging
import multiprocessing
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from typing import Callable, Iterator, Sequence

from .errors import InputError
from .threads import limit_threads, worker_threads

log = logging.getLogger("ibr_pipeline.executors")


class Executor:
    name = "executor"
    jobs = 1  # local worker processes a whole-scene stage may start beside it (StageContext.jobs)

    def map_unordered(self, fn: Callable, argsets: Sequence[tuple]) -> Iterator[tuple]:
        raise NotImplementedError

    def results(self, fn: Callable, argsets: Sequence[tuple]) -> Iterator[tuple]:
        """(index, fn(*argsets[index])) as tasks finish; the first failed task's exception is
        raised (whole-scene stages, where one failed piece fails the stage)."""
        for i, res, exc in self.map_unordered(fn, argsets):
            if exc is not None:
                raise exc
            yield i, res

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def block_order(n: int, jobs: int) -> list[int]:
    """Task indices 0..n-1 cut into `jobs` contiguous blocks and dealt one from each block in
    turn (0, b, 2b, 1, b+1, ...): a pool hands tasks out in that order, so each worker mostly gets
    consecutive views, and a stage whose view reads its neighbours (the reflection stage's
    per-worker cache of mirror-world footprints) builds each of them in one worker, not in all."""
    if n <= 0:
        return []
    size = -(-n // max(1, jobs))
    blocks = [list(range(k, min(n, k + size))) for k in range(0, n, size)]
    return [b[j] for j in range(size) for b in blocks if j < len(b)]


class LocalExecutor(Executor):
    """`jobs` worker processes (spawned: safe with open3d/torch threads; each pinned to its share
    of the cores, `limit_threads`); jobs=1 runs in-process."""

    def __init__(self, jobs: int = 1):
        if jobs < 1:
            raise ValueError("jobs must be >= 1")
        self.jobs = jobs
        self.name = "in-process" if jobs == 1 else f"process pool ({jobs} workers)"
        self._pool: ProcessPoolExecutor | None = None

    def map_unordered(self, fn, argsets, in_order: bool = False):
        """`in_order`: hand the tasks out in the given order (a caller that sorted them, largest
        first), not in `block_order`."""
        if self.jobs == 1 or len(argsets) <= 1:
            for i, args in enumerate(argsets):
                try:
                    yield i, fn(*args), None
                except Exception as e:  # reported per task; KeyboardInterrupt still stops the run
                    yield i, None, e
            return
        self._ensure_pool()
        order = range(len(argsets)) if in_order else block_order(len(argsets), self.jobs)
        futures = {self._pool.submit(fn, *argsets[i]): i for i in order}
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

    def submit(self, fn, *args):
        """One task, started now (a Future): a caller can go on producing the next task's inputs
        while workers run this one. jobs=1 runs it here, before returning a finished Future."""
        from concurrent.futures import Future
        if self.jobs == 1:
            fut: Future = Future()
            try:
                fut.set_result(fn(*args))
            except Exception as e:
                fut.set_exception(e)
            return fut
        return self._ensure_pool().submit(fn, *args)

    def _ensure_pool(self) -> ProcessPoolExecutor:
        if self._pool is None:
            self._pool = ProcessPoolExecutor(self.jobs, mp_context=multiprocessing.get_context("spawn"),
                                             initializer=limit_threads,
                                             initargs=(worker_threads(self.jobs),))
        return self._pool

    def close(self):
        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)
            self._pool = None


class ClusterError(InputError):
    """The Dask cluster cannot run the tasks (no worker for `watchdog_s`, the scheduler lost them):
    the user must fix the cluster, not the data. Tasks finished before were yielded (and recorded);
    a rerun continues. One line, exit code 2 (an InputError)."""


class DaskExecutor(Executor):
    """Per-view tasks on a Dask cluster: an existing scheduler address, or a LocalCluster of n workers.

    Workers need `ibr_pipeline` importable and the workspace on a shared file system at the same path.

    Progress watchdog: a scheduler whose workers all went away keeps the tasks queued forever. When
    no worker has been connected and no task has finished for `watchdog_s` seconds,
    `map_unordered` stops with a `ClusterError` naming the scheduler, after yielding every task
    that finished. Workers that are connected but busy with long tasks never trip it.
    """

    poll_s = 1.0   # how often the scheduler is asked for its workers while nothing finishes
    fetch_s = 10.0  # longest wait for a finished task's (small) result to come back

    def __init__(self, scheduler: str | None = None, local_workers: int = 0,
                 watchdog_s: float = 120.0):
        from distributed import Client, LocalCluster

        if not watchdog_s > 0:
            raise ValueError("watchdog_s must be > 0")
        self.watchdog_s = float(watchdog_s)
        self._cluster = None
        if scheduler:
            self.client = Client(scheduler, timeout="30s")
            self.name = f"dask ({scheduler})"
        else:
            self._cluster = LocalCluster(n_workers=max(1, local_workers), threads_per_worker=1,
                                         processes=True, dashboard_address=None)
            self.client = Client(self._cluster)
            self.name = f"dask LocalCluster ({max(1, local_workers)} workers)"
            self.jobs = max(1, local_workers)  # the cluster's workers share this machine
        self.address = getattr(self.client.scheduler, "address", None) or scheduler or "?"

    def _workers(self) -> int | None:
        """Workers connected to the scheduler now; None when the scheduler does not answer."""
        try:
            return len(self.client.nthreads(callback_timeout=max(1.0, min(10.0, self.watchdog_s))))
        except Exception as e:  # OSError, TimeoutError, CommClosedError: unreachable scheduler
            log.debug("dask scheduler %s did not answer (%s)", self.address, e)
            return None

    def _stalled(self, finished: int, total: int, reachable: bool) -> ClusterError:
        what = "no workers" if reachable else "unreachable (no answer)"
        if self._cluster is not None:
            fix = "the LocalCluster's workers died (out of memory?): lower --dask-local and rerun"
        else:
            fix = f"start workers (dask worker {self.address}) and rerun"
        return ClusterError(f"dask scheduler {self.address}: {what} for {self.watchdog_s:g} s; "
                            f"{finished} of {total} views finished and kept; {fix} "
                            f"(--dask-timeout sets how long to wait)")

    def map_unordered(self, fn, argsets):
        import queue

        futures = [self.client.submit(fn, *args, pure=False) for args in argsets]
        index = {f.key: i for i, f in enumerate(futures)}
        done: queue.Queue = queue.Queue()
        for f in futures:
            f.add_done_callback(done.put)  # called in a thread, whatever the outcome
        pending = {f.key for f in futures}
        finished = 0
        poll = min(self.poll_s, self.watchdog_s / 3)
        try:
            # the watchdog clock restarts whenever a task finishes or a worker is seen connected
            last_alive = last_poll = time.monotonic()
            while pending:
                try:
                    fut = done.get(timeout=poll)
                except queue.Empty:
                    fut = None
                if fut is not None and fut.key in pending:
                    if fut.status == "cancelled":  # scheduler restarted or lost the task
                        raise ClusterError(
                            f"dask scheduler {self.address}: a task was cancelled by the cluster "
                            f"(scheduler restarted or lost it); {finished} of {len(futures)} views "
                            f"finished and kept; rerun to continue")
                    item = None
                    if fut.status == "error":
                        item = index[fut.key], None, fut.exception()
                    else:
                        try:
                            item = index[fut.key], fut.result(timeout=self.fetch_s), None
                        except TimeoutError:
                            # finished, but its worker left before the result came back: the
                            # scheduler computes it again; wait for that (the watchdog applies)
                            fut.add_done_callback(done.put)
                    if item is not None:
                        pending.discard(fut.key)
                        finished += 1
                        yield item
                        last_alive = last_poll = time.monotonic()  # consumer time is not the cluster's
                        continue
                now = time.monotonic()
                if now - last_poll < poll:
                    continue
                last_poll = now
                n = self._workers()
                reachable = n is not None
                now = time.monotonic()
                if n:
                    last_alive = now
                elif now - last_alive >= self.watchdog_s:
                    raise self._stalled(finished, len(futures), reachable)
        finally:
            try:
                self.client.cancel([f for f in futures if not f.done()])
            except Exception as e:  # a gone scheduler: nothing left to cancel
                log.debug("could not cancel the remaining dask tasks (%s)", e)

    def close(self):
        self.client.close()
        if self._cluster is not None:
            self._cluster.close()


def make_executor(jobs: int = 1, dask_scheduler: str | None = None, dask_local: int = 0,
                  dask_watchdog_s: float = 120.0) -> Executor:
    """The executor the CLI flags ask for: Dask (`dask_watchdog_s`: stop when no worker has been
    connected and no task finished for that long) or local processes."""
    if dask_scheduler or dask_local:
        return DaskExecutor(dask_scheduler, dask_local, watchdog_s=dask_watchdog_s)
    return LocalExecutor(jobs)
