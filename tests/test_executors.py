"""The same per-view tasks give byte-identical outputs in-process, on a process pool and on Dask."""
import os

import pytest
from toy_stages import STAGES, make_toy_workspace

from ibr_pipeline.executors import DaskExecutor, LocalExecutor
from ibr_pipeline.pipeline import load_configs, run
from ibr_pipeline.workspace import Workspace


def _outputs(ws_root):
    return {p.relative_to(ws_root).as_posix(): p.read_bytes() for p in ws_root.glob("views/*/out.txt")}


def _run_with(tmp_path, name, executor, overrides=None):
    ws_root = make_toy_workspace(tmp_path / name, n_views=8)
    ws = Workspace(ws_root)
    results = run(STAGES, ws, load_configs(STAGES, ws, overrides or {}), STAGES[:2],
                  executor=executor, progress=False)
    return ws_root, results


def test_local_pool_and_dask_match_in_process(tmp_path):
    ref_root, _ = _run_with(tmp_path, "serial", LocalExecutor(1))
    reference = _outputs(ref_root)
    assert len(reference) == 8
    with LocalExecutor(2) as pool:
        pool_root, res = _run_with(tmp_path, "pool", pool)
    assert res[1].views_run == 8 and _outputs(pool_root) == reference
    with DaskExecutor(local_workers=2) as dask:
        dask_root, res = _run_with(tmp_path, "dask", dask)
    assert res[1].views_run == 8 and _outputs(dask_root) == reference


@pytest.mark.parametrize("kind", ["pool", "dask"])
def test_failures_are_reported_per_view_on_every_executor(tmp_path, kind):
    executor = LocalExecutor(2) if kind == "pool" else DaskExecutor(local_workers=2)
    with executor:
        ws_root, res = _run_with(tmp_path, kind, executor, {"upper": {"fail_on": "v03"}})
    assert res[1].result == "failed" and res[1].views_run == 7
    assert res[1].failures == [("v03", "ValueError: toy failure for v03")]
    assert len(_outputs(ws_root)) == 7


# --- the Dask progress watchdog ---------------------------------------------------------------
def _nap(i, seconds):
    """A task for the watchdog tests (module level: workers import it by reference)."""
    import time
    time.sleep(seconds)
    return i


def _cluster(n_workers, threads=1):
    from distributed import LocalCluster
    return LocalCluster(n_workers=n_workers, threads_per_worker=threads, processes=False,
                        dashboard_address=None)


def test_dask_watchdog_stops_when_every_worker_left_and_yields_finished_first():
    import time

    from ibr_pipeline.errors import InputError
    from ibr_pipeline.executors import ClusterError

    got, t_gone = [], None
    with _cluster(1) as cluster, DaskExecutor(cluster.scheduler_address, watchdog_s=3) as ex:
        with pytest.raises(ClusterError) as err:
            for i, out, exc in ex.map_unordered(_nap, [(k, 0.2) for k in range(12)]):
                assert exc is None and out == i
                got.append(i)
                if len(got) == 3:
                    cluster.scale(0)   # every worker leaves; the scheduler stays up
                    t_gone = time.monotonic()
        waited = time.monotonic() - t_gone
    assert isinstance(err.value, InputError)   # the CLI prints it as one line, exit 2
    assert 3 <= len(got) < 12
    msg = str(err.value)
    assert cluster.scheduler_address in msg and "no workers for 3 s" in msg
    assert f"{len(got)} of 12 views finished and kept" in msg
    assert f"dask worker {cluster.scheduler_address}" in msg
    assert 3.0 <= waited < 12.0, waited


def test_dask_watchdog_with_no_worker_from_the_start():
    import time

    from ibr_pipeline.executors import ClusterError, make_executor

    with _cluster(0) as cluster:
        t0 = time.monotonic()
        with make_executor(dask_scheduler=cluster.scheduler_address, dask_watchdog_s=2) as ex:
            assert ex.watchdog_s == 2
            with pytest.raises(ClusterError, match="0 of 3 views"):
                list(ex.map_unordered(_nap, [(k, 0.0) for k in range(3)]))
        assert time.monotonic() - t0 < 10


def test_dask_watchdog_never_trips_on_busy_workers():
    """Tasks longer than the watchdog are fine while their workers stay connected."""
    with _cluster(1, threads=2) as cluster, DaskExecutor(cluster.scheduler_address,
                                                         watchdog_s=0.6) as ex:
        got = sorted(out for _, out, _ in ex.map_unordered(_nap, [(k, 2.0) for k in range(2)]))
    assert got == [0, 1]


def test_runner_keeps_views_finished_before_the_workers_left(tmp_path):
    """Through the runner: the views finished before the cluster lost its workers are recorded, the
    run stops with ClusterError, and a rerun does only the rest."""
    import threading
    import time

    from ibr_pipeline.executors import ClusterError

    ws_root = make_toy_workspace(tmp_path / "ws", n_views=10)
    state = ws_root / ".ibr" / "state" / "upper"
    ws = Workspace(ws_root)
    configs = load_configs(STAGES, ws, {"upper": {"sleep": "0.3"}})
    with _cluster(1) as cluster, DaskExecutor(cluster.scheduler_address, watchdog_s=2) as ex:
        def drop_workers():
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline and len(list(state.glob("*.json"))) < 2:
                time.sleep(0.02)
            cluster.scale(0)
        watcher = threading.Thread(target=drop_workers, daemon=True)
        watcher.start()
        with pytest.raises(ClusterError, match="views finished and kept"):
            run(STAGES, ws, configs, STAGES[:2], executor=ex, progress=False)
        watcher.join()
    done = {p.stem for p in state.glob("*.json")}
    assert 2 <= len(done) < 10
    ran_before = (ws_root / "ranlog.txt").read_text().split()
    results = run(STAGES, ws, configs, STAGES[:2], executor=LocalExecutor(1), progress=False)
    assert results[1].views_run == 10 - len(done)
    ran_after = (ws_root / "ranlog.txt").read_text().split()[len(ran_before):]
    assert not set(ran_after) & done, "views recorded before the error were redone"
    assert len(_outputs(ws_root)) == 10


def _pool_threads():
    import os

    from threadpoolctl import threadpool_info
    blas = [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]
    return os.environ.get("OPENBLAS_NUM_THREADS"), blas


def test_pool_workers_are_pinned_to_their_share_of_the_cores():
    """Each worker of a local pool gets cores // jobs BLAS threads (numpy's OpenBLAS included),
    so two workers on two cores do not spin against each other (issue #28)."""
    import numpy  # noqa: F401  (loads OpenBLAS, as every worker does)

    from ibr_pipeline.executors import worker_threads
    n = worker_threads(2)
    with LocalExecutor(2) as ex:
        got = [r for _, r, e in ex.map_unordered(_pool_threads, [(), ()]) if e is None]
    assert len(got) == 2
    for env, blas in got:
        assert env == str(n) and blas and all(b == n for b in blas)


def _pid(_i):
    return os.getpid()


def test_pool_hands_each_worker_consecutive_tasks():
    """block_order deals contiguous blocks in turn, so a worker's tasks are mostly neighbours
    (the reflection stage's per-worker footprint cache relies on it); every task runs once."""
    from ibr_pipeline.executors import block_order
    for n, jobs in ((10, 2), (7, 3), (1, 2), (0, 2), (3, 8)):
        order = block_order(n, jobs)
        assert sorted(order) == list(range(n))
    assert block_order(10, 2)[:4] == [0, 5, 1, 6]
    with LocalExecutor(2) as ex:
        got = {i: (pid, e) for i, pid, e in ex.map_unordered(_pid, [(i,) for i in range(12)])}
    assert sorted(got) == list(range(12))
    assert all(e is None and isinstance(pid, int) for pid, e in got.values())


def _square(x):
    if x < 0:
        raise ValueError("negative")
    return x * x


@pytest.mark.parametrize("jobs", [1, 2])
def test_submit_returns_futures_in_process_and_on_the_pool(jobs):
    """submit starts one task and returns its Future (done already in-process); a failing task's
    exception comes out of result(); in_order tasks all run once."""
    with LocalExecutor(jobs) as ex:
        futs = [ex.submit(_square, i) for i in range(5)]
        bad = ex.submit(_square, -1)
        assert [f.result(timeout=60) for f in futs] == [0, 1, 4, 9, 16]
        with pytest.raises(ValueError, match="negative"):
            bad.result(timeout=60)
        got = dict((i, r) for i, r, e in ex.map_unordered(_square, [(i,) for i in range(6)],
                                                            in_order=True))
    assert got == {i: i * i for i in range(6)}
