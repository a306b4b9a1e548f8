"""Runner semantics on the toy stages: up-to-date checks, reasons, partial failure, atomic writes."""
import json

import pytest
import toy_stages
from toy_stages import STAGES

from ibr_pipeline.errors import ConfigError, InputError
from ibr_pipeline.pipeline import load_configs, run, select_stages, status
from ibr_pipeline.workspace import Workspace


def _run(ws_root, overrides=None, force=False, selected=None):
    ws = Workspace(ws_root)
    configs = load_configs(STAGES, ws, overrides or {})
    return {r.name: r for r in run(STAGES, ws, configs, selected or STAGES, force, progress=False)}


def _plans(ws_root, overrides=None):
    ws = Workspace(ws_root)
    return {p.stage.name: p for p in status(STAGES, ws, load_configs(STAGES, ws, overrides or {}))}


def _ranlog(ws_root):
    p = ws_root / "ranlog.txt"
    return p.read_text().split() if p.exists() else []


def test_first_run_then_up_to_date(toy_ws):
    plans = _plans(toy_ws)
    assert plans["listing"].state == "will run" and plans["listing"].summary() == "never run"
    assert plans["upper"].state == "will run" and "upstream stage 'listing'" in plans["upper"].summary()
    res = _run(toy_ws)
    assert res["listing"].result == "ran" and res["upper"].views_run == 6
    out = (toy_ws / "views" / "v03" / "out.txt").read_text()
    assert out == "VIEW NUMBER 3\n!\nEND\n"
    assert len(_ranlog(toy_ws)) == 6
    # second run: nothing to do, nothing executed
    plans = _plans(toy_ws)
    assert plans["listing"].state == "up to date" and plans["upper"].state == "up to date"
    res = _run(toy_ws)
    assert res["upper"].result == "up to date" and len(_ranlog(toy_ws)) == 6


def test_config_change_reruns_with_reason(toy_ws):
    _run(toy_ws)
    (toy_ws / "ibr.toml").write_text((toy_ws / "ibr.toml").read_text() + '\n[upper]\nsuffix = "?"\n')
    plans = _plans(toy_ws)
    assert plans["listing"].state == "up to date"
    assert plans["upper"].state == "will run"
    assert "6/6 views" in plans["upper"].summary()
    assert "config changed: upper.suffix ! → ?" in plans["upper"].summary()
    _run(toy_ws)
    assert (toy_ws / "views" / "v00" / "out.txt").read_text().endswith("?\nEND\n")
    # a command-line override is a config change too, and is seen by status
    assert "upper.repeat 1 → 2" in _plans(toy_ws, {"upper": {"repeat": "2"}})["upper"].summary()


def test_input_change_reruns_only_affected_view(toy_ws):
    _run(toy_ws)
    data = toy_ws.parent / "input" / "data"
    (data / "v02.txt").write_text("changed\n")
    plans = _plans(toy_ws)
    assert plans["listing"].state == "will run"
    assert "input changed: input/data/v02.txt" in plans["listing"].summary()
    _run(toy_ws)
    # listing rewrote an identical views.json: content hashes say the other views are still fine
    assert _ranlog(toy_ws)[6:] == ["v02"]
    assert (toy_ws / "views" / "v02" / "out.txt").read_text().startswith("CHANGED")


def test_new_input_file_is_seen(toy_ws):
    _run(toy_ws)
    (toy_ws.parent / "input" / "data" / "v99.txt").write_text("new\n")
    assert "input added: input/data/v99.txt" in _plans(toy_ws)["listing"].summary()
    # the view list (a shared input of every view of `upper`) changed: every view reruns
    assert _plans(toy_ws)["upper"].summary() == "upstream stage 'listing' will run"
    _run(toy_ws)
    assert sorted(_ranlog(toy_ws)[6:]) == sorted([f"v{i:02d}" for i in range(6)] + ["v99"])


def test_code_version_change_reruns(toy_ws, monkeypatch):
    import dataclasses
    _run(toy_ws)
    bumped = (STAGES[0], dataclasses.replace(STAGES[1], version="2"))
    monkeypatch.setattr(toy_stages, "STAGES", bumped)
    ws = Workspace(toy_ws)
    plans = {p.stage.name: p for p in status(bumped, ws, load_configs(bumped, ws))}
    assert "code version changed: 1 → 2" in plans["upper"].summary()


def test_a_newly_declared_output_reruns_the_stage(toy_ws, monkeypatch):
    """A whole-scene stage that now writes one more file (its outputs depend on the data) is not
    up to date just because its recorded outputs are unchanged."""
    import dataclasses
    _run(toy_ws)

    def listing_twice(ctx):
        toy_stages.listing_run(ctx)
        ctx.ws.write_json("toy/extra.json", [])
    grown = (dataclasses.replace(STAGES[0], run=listing_twice,
                                 outputs=("toy/views.json", "toy/extra.json")), STAGES[1])
    monkeypatch.setattr(toy_stages, "STAGES", grown)
    ws = Workspace(toy_ws)
    plans = {p.stage.name: p for p in status(grown, ws, load_configs(grown, ws))}
    assert plans["listing"].state == "will run"
    assert "output never written: toy/extra.json" in plans["listing"].summary()
    res = {r.name: r for r in run(grown, ws, load_configs(grown, ws), grown, progress=False)}
    assert res["listing"].result == "ran" and (toy_ws / "toy" / "extra.json").is_file()
    plans = {p.stage.name: p for p in status(grown, ws, load_configs(grown, ws))}
    assert plans["listing"].state == "up to date"


def test_output_deleted_or_tampered_reruns(toy_ws):
    _run(toy_ws)
    (toy_ws / "views" / "v01" / "out.txt").unlink()
    (toy_ws / "views" / "v04" / "out.txt").write_text("truncated")
    s = _plans(toy_ws)["upper"].summary()
    assert "2/6 views" in s
    assert "output missing: views/v01/out.txt" in s and "output changed on disk: views/v04/out.txt" in s
    _run(toy_ws)
    assert sorted(_ranlog(toy_ws)[6:]) == ["v01", "v04"]


def test_partial_failure_keeps_other_views_and_rerun_redoes_only_failed(toy_ws):
    res = _run(toy_ws, {"upper": {"fail_on": "v01,v04"}})
    assert res["upper"].result == "failed"
    assert res["upper"].views_run == 4 and res["upper"].views_failed == 2
    assert {v for v, _ in res["upper"].failures} == {"v01", "v04"}
    assert "toy failure for v01" in dict(res["upper"].failures)["v01"]
    assert not (toy_ws / "views" / "v01" / "out.txt").exists()
    assert (toy_ws / "views" / "v00" / "out.txt").exists()
    tb = (toy_ws / ".ibr" / "logs" / "upper" / "v01.txt").read_text()
    assert "Traceback" in tb and "toy failure" in tb
    plan = _plans(toy_ws, {"upper": {"fail_on": "v01,v04"}})["upper"]
    assert plan.views_todo == ["v01", "v04"]
    assert "failed last time: ValueError: toy failure" in plan.summary()
    # the bug is fixed (same config otherwise would fail again): only the failed views rerun
    record = json.loads((toy_ws / ".ibr" / "state" / "upper" / "v00.json").read_text())
    assert record["status"] == "ok"
    _run(toy_ws, {"upper": {"fail_on": "v01,v04"}})  # still failing: 2 more runs
    log = _ranlog(toy_ws)
    assert sorted(log[6:]) == ["v01", "v04"]


def test_force_and_selection(toy_ws):
    _run(toy_ws)
    res = _run(toy_ws, force=True, selected=select_stages(STAGES, from_stage="upper", until_stage="upper"))
    assert "listing" not in res and res["upper"].views_run == 6
    with pytest.raises(InputError, match="unknown stage 'nope'"):
        select_stages(STAGES, from_stage="nope")
    with pytest.raises(InputError, match="comes after"):
        select_stages(STAGES, from_stage="upper", until_stage="listing")


def test_missing_declared_output_is_a_stage_failure(toy_ws, monkeypatch):
    import dataclasses
    broken = (dataclasses.replace(STAGES[0], run=toy_stages.missing_output_run),)
    ws = Workspace(toy_ws)
    res = run(broken, ws, load_configs(broken, ws), broken, progress=False)
    assert res[0].result == "failed" and "did not write its declared output" in res[0].failures[0][1]
    assert "failed last time" in status(broken, ws, load_configs(broken, ws))[0].summary()


def test_config_errors_name_the_field(toy_ws):
    ws = Workspace(toy_ws)
    with pytest.raises(ConfigError, match=r"upper\.repeat: must be >= 1, got 0"):
        load_configs(STAGES, ws, {"upper": {"repeat": "0"}})
    with pytest.raises(ConfigError, match=r"upper\.sleep: expected a number"):
        load_configs(STAGES, ws, {"upper": {"sleep": "soon"}})
    with pytest.raises(ConfigError, match=r"upper\.sleep: must be a finite number"):
        load_configs(STAGES, ws, {"upper": {"sleep": "nan"}})
    with pytest.raises(ConfigError, match=r"upper\.colour: unknown field"):
        load_configs(STAGES, ws, {"upper": {"colour": "red"}})
    (toy_ws / "ibr.toml").write_text((toy_ws / "ibr.toml").read_text() + "\n[upper]\nrepeat = 5000\n")
    with pytest.raises(InputError, match=r"ibr.toml: invalid config upper\.repeat: must be <= 1000"):
        load_configs(STAGES, Workspace(toy_ws))


def test_temporaries_of_a_killed_write_are_cleaned(toy_ws):
    ws = Workspace(toy_ws)
    with pytest.raises(RuntimeError):
        with ws.atomic_write("a/b.txt", "w") as f:
            f.write("half")
            raise RuntimeError("crash")
    assert not ws.path("a/b.txt").exists()
    assert list(ws.path("a").iterdir()) == []
    # a SIGKILL leaves the temporary behind; the next run removes it
    (ws.path("a") / ".b.ibrtmp-xyz.txt").write_text("half")
    _run(toy_ws)
    assert list(ws.path("a").iterdir()) == []
