"""Running the stage table on a workspace: configs, status, execution, the timing table.

`status()` and `run()` are what `ibr status` and `ibr run` call. Everything that can be checked
before work starts (workspace, ibr.toml, config values, stage names) is checked first, so bad input
exits with nothing written.
"""
from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field
from typing import Sequence

from . import layout as L
from .config import StageConfig, build_config
from .errors import ConfigError, InputError
from .executors import Executor, LocalExecutor
from .runner import (HashCache, Stage, StageContext, StagePlan, error_line, expand, fingerprint,
                     format_traceback, make_record, output_record, plan_stage, run_view_task,
                     write_record)
from .layout import view_key
from .workspace import Workspace, atomic_path

log = logging.getLogger("ibr_pipeline")


def load_configs(stages: Sequence[Stage], ws: Workspace,
                 overrides: dict[str, dict] | None = None) -> dict[str, StageConfig]:
    """Each stage's config: defaults < ibr.toml table [stage] < overrides (command line)."""
    toml = ws.config()
    names = {s.name for s in stages}
    for key, value in toml.items():
        if key == "input":
            continue
        if key not in names:
            raise InputError(f"{ws.config_path}: unknown table [{key}] (stages: {', '.join(names)})")
        if not isinstance(value, dict):
            raise InputError(f"{ws.config_path}: [{key}] must be a table of config fields")
    overrides = overrides or {}
    for key in overrides:
        if key not in names:
            raise InputError(f"unknown stage {key!r} in --set (stages: {', '.join(names)})")
    configs = {}
    for s in stages:
        table = toml.get(s.name, {})
        try:
            build_config(s.config, s.name, table)
        except ConfigError as e:
            raise InputError(f"{ws.config_path}: {e}") from None
        configs[s.name] = build_config(s.config, s.name, table, overrides.get(s.name, {}))
    return configs


def select_stages(stages: Sequence[Stage], from_stage: str | None = None,
                  until_stage: str | None = None, only: str | None = None) -> list[Stage]:
    names = [s.name for s in stages]
    for given in (from_stage, until_stage, only):
        if given is not None and given not in names:
            raise InputError(f"unknown stage {given!r} (stages: {', '.join(names)})")
    if only is not None:
        return [s for s in stages if s.name == only]
    lo = names.index(from_stage) if from_stage else 0
    hi = names.index(until_stage) if until_stage else len(names) - 1
    if lo > hi:
        raise InputError(f"--from {from_stage} comes after --until {until_stage}")
    return list(stages[lo:hi + 1])


# the stages that read the input's own images; every later one reads them through
# layout.posed_scene (undistorted when SfM estimated a distorted lens)
_BEFORE_POSED = ("ingest", "poses")


def scene_for(ws: Workspace, stage: str, scenes: tuple | None = None):
    """The scene manifest stage `stage` reads (None before ingest has run). `scenes`: the
    (as ingested, as posed) pair already read, when nothing ran in between."""
    if scenes is None:
        if not ws.exists(ws.SCENE):
            return None
        base = ws.scene()
        scenes = (base, None)
    base, posed = scenes
    if base is None or stage in _BEFORE_POSED:
        return base
    return posed if posed is not None else L.posed_scene(ws, base)


def status(stages: Sequence[Stage], ws: Workspace, configs: dict[str, StageConfig],
           force: bool = False, selected: Sequence[Stage] | None = None) -> list[StagePlan]:
    """The plan for every stage in order: would it run, and why. Reads only."""
    hashes = HashCache(ws.hash_cache_path)
    selected_names = {s.name for s in (selected if selected is not None else stages)}
    plans, upstream = [], None
    base = ws.scene() if ws.exists(ws.SCENE) else None  # status runs nothing: read both once
    scenes = (base, None if base is None else L.posed_scene(ws, base))
    for s in stages:
        ctx = StageContext(ws, s.name, configs[s.name], scene_for(ws, s.name, scenes))
        plan = plan_stage(s, ctx, hashes, force and s.name in selected_names, upstream)
        if plan.state == "will run" and s.name not in selected_names:
            plan.reasons = ["not selected (--from/--until)"] + plan.reasons
            plan.state = "not selected"
        plans.append(plan)
        if plan.state == "will run" and upstream is None:
            upstream = s.name
    return plans


@dataclass
class StageResult:
    name: str
    result: str
    views_run: int = 0
    views_failed: int = 0
    views_total: int = 0
    seconds: float = 0.0
    cpu_seconds: float = 0.0  # every process of the stage (workers included), see _cpu_now
    failures: list[tuple[str, str]] = field(default_factory=list)  # (view, one-line error)


def _cpu_now() -> float:
    """CPU seconds of this process and of its finished children (pools a whole stage starts)."""
    import resource
    ch = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + ch.ru_utime + ch.ru_stime


def _run_whole(stage: Stage, ctx: StageContext, plan: StagePlan) -> StageResult:
    ws = ctx.ws
    t0, c0 = time.perf_counter(), _cpu_now()
    ctx = dataclasses.replace(ctx, fingerprint=fingerprint(stage, ctx.config, plan.input_hashes))
    try:
        stage.run(ctx)
        outputs = output_record(expand(stage.outputs, ctx), ws)
    except InputError:
        raise  # bad input: the CLI prints it and exits 2; the stage wrote nothing under a real name
    except Exception as e:
        dt = time.perf_counter() - t0
        _save_traceback(ws, stage.name, None, e)
        write_record(ws.state_file(stage.name),
                     make_record(stage, ctx, "failed", plan.input_hashes, seconds=dt, error=error_line(e)))
        return StageResult(stage.name, "failed", seconds=dt, failures=[("", error_line(e))])
    dt, cpu = time.perf_counter() - t0, _cpu_now() - c0
    write_record(ws.state_file(stage.name),
                 make_record(stage, ctx, "ok", plan.input_hashes, outputs=outputs, seconds=dt,
                             cpu_seconds=cpu))
    return StageResult(stage.name, "ran", seconds=dt, cpu_seconds=cpu)


def _run_views(stage: Stage, ctx: StageContext, plan: StagePlan, executor: Executor,
               progress: bool) -> StageResult:
    from tqdm import tqdm

    ws = ctx.ws
    todo = plan.views_todo
    res = StageResult(stage.name, "ran", views_total=plan.views_total)
    t0 = time.perf_counter()
    bar = tqdm(total=len(todo), desc=f"{stage.name} [{executor.name}]", unit="view",
               disable=not progress, leave=True)
    try:
        for i, out, exc in executor.map_unordered(run_view_task, [(stage, ctx, v) for v in todo]):
            view = todo[i]
            if exc is None:
                rec = make_record(stage, ctx, "ok", plan.input_hashes[view], view,
                                  out["outputs"], out["seconds"], cpu_seconds=out.get("cpu_seconds"))
                res.views_run += 1
                res.cpu_seconds += out.get("cpu_seconds") or 0.0
            elif isinstance(exc, InputError):
                # bad input or an unwritable workspace: the user must act, so stop here (exit 2);
                # the views finished so far keep their records, this one is left as it was
                raise exc
            else:
                msg = error_line(exc)
                _save_traceback(ws, stage.name, view, exc)
                rec = make_record(stage, ctx, "failed", plan.input_hashes[view], view, error=msg)
                res.views_failed += 1
                res.failures.append((view, msg))
                bar.write(f"{stage.name}: view {view} failed: {msg}")
            write_record(ws.state_file(stage.name, view), rec)
            bar.update(1)
    finally:
        bar.close()
    res.seconds = time.perf_counter() - t0
    if res.views_failed:
        res.result = "failed"
    return res


def _save_traceback(ws: Workspace, stage: str, view: str | None, exc: BaseException) -> None:
    """Keep the traceback of a stage fault under .ibr/logs/. Best effort: when the workspace itself
    cannot be written, the fault's one-line message is what the user gets, not a second traceback
    about saving the first."""
    path = ws.root / ".ibr" / "logs" / stage / f"{view_key(view) if view else 'stage'}.txt"
    try:
        with atomic_path(path) as tmp:
            tmp.write_text(format_traceback(exc))
    except (OSError, InputError) as e:
        log.warning("could not save the traceback to %s (%s)", path, e)


def run(stages: Sequence[Stage], ws: Workspace, configs: dict[str, StageConfig],
        selected: Sequence[Stage], force: bool = False, executor: Executor | None = None,
        progress: bool = True, command: Sequence[str] = ()) -> list[StageResult]:
    """Run the selected stages in order; returns one StageResult per selected stage.

    Stops after a stage that failed or is blocked. `command` (the CLI arguments) is recorded with
    the resolved configs in .ibr/runs.jsonl.
    """
    executor = executor or LocalExecutor(1)
    removed = ws.clean_temporaries()
    if removed:
        log.info("removed %d temporary file(s) left by an interrupted run", removed)
    hashes = HashCache(ws.hash_cache_path)
    results: list[StageResult] = []
    try:
        for s in selected:
            ctx = StageContext(ws, s.name, configs[s.name], scene_for(ws, s.name), progress=progress,
                               jobs=executor.jobs)
            plan = plan_stage(s, ctx, hashes, force, None)
            if plan.state == "blocked":
                log.warning("stage %-13s blocked: %s", s.name, plan.summary())
                results.append(StageResult(s.name, "blocked"))
                continue
            if plan.state == "up to date":
                log.info("stage %-13s up to date", s.name)
                results.append(StageResult(s.name, "up to date", views_total=plan.views_total))
                continue
            log.info("stage %-13s running: %s", s.name, plan.summary())
            if s.per_view:
                r = _run_views(s, ctx, plan, executor, progress)
            else:
                r = _run_whole(s, ctx, plan)
            results.append(r)
            hashes.save()
            if r.result == "failed":
                for view, msg in r.failures:
                    log.error("%s%s failed: %s", s.name, f" view {view}" if view else "", msg)
                log.error("stage %s failed; later stages not run. Tracebacks: %s. A rerun redoes "
                          "only what failed or is stale.", s.name, ws.root / ".ibr" / "logs" / s.name)
                break
    finally:
        try:
            hashes.save()
        except (OSError, InputError) as e:  # only a cache: the next run rehashes
            log.warning("could not save the hash cache (%s)", e)
        finally:
            _log_run(ws, results, {s.name: configs[s.name] for s in selected}, command)
    return results


def _log_run(ws: Workspace, results: Sequence[StageResult], configs: dict[str, StageConfig],
             command: Sequence[str]) -> None:
    """Append this run's command, resolved configs (defaults < ibr.toml < --set, every field) and
    per-stage results to WS/.ibr/runs.jsonl (read by `ibr report`): what a record's outputs were
    made with stays findable. Best effort: a full disk must not hide the error that stopped the run."""
    if not results:
        return
    import json
    entry = {"finished": time.strftime("%Y-%m-%dT%H:%M:%S"), "command": list(command),
             "config": {name: cfg.to_dict() for name, cfg in configs.items()},
             "stages": [{"stage": r.name, "result": r.result, "seconds": round(r.seconds, 3),
                         "cpu_seconds": round(r.cpu_seconds, 3), "views_run": r.views_run,
                         "views_failed": r.views_failed,
                         "views_total": r.views_total} for r in results]}
    path = ws.root / ".ibr" / "runs.jsonl"
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "a") as f:
            f.write(json.dumps(entry) + "\n")
    except OSError as e:
        log.warning("could not append to %s (%s)", path, e)


def timing_table(results: Sequence[StageResult]) -> str:
    rows = [("stage", "result", "views run", "failed", "seconds", "cpu s")]
    for r in results:
        views = f"{r.views_run}/{r.views_total}" if r.views_total else "-"
        rows.append((r.name, r.result, views, str(r.views_failed or "-"), f"{r.seconds:.2f}",
                     f"{r.cpu_seconds:.2f}"))
    rows.append(("total", "", "", "", f"{sum(r.seconds for r in results):.2f}",
                 f"{sum(r.cpu_seconds for r in results):.2f}"))
    widths = [max(len(row[i]) for row in rows) for i in range(6)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(row, widths)).rstrip() for row in rows]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def status_table(plans: Sequence[StagePlan]) -> str:
    width = max(len(p.stage.name) for p in plans)
    return "\n".join(f"{p.stage.name.ljust(width)}  {p.state.ljust(12)}  {p.summary()}" for p in plans)
