"""The same per-view tasks give byte-identical outputs in-process, on a process pool and on Dask."""
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
