"""The stage runner: what is up to date, why a stage reruns, and running what is not.

A stage is up to date only when its outputs exist unchanged and its fingerprint matches: the
content hashes of its declared inputs, its config, and its code version (`Stage.version`, bumped by
hand whenever a change alters what the stage writes). Per-view stages keep one record per view in
`.ibr/state/<stage>/<view>.json`, written by the coordinating process right after that view's
outputs have been renamed into place, so a run killed at any moment resumes without redoing finished
views, and a file is never taken as done unless its record (with its size and hash) exists.

Executors (local process pool, Dask) live in `executors.py`; the stage table in `stages/__init__.py`.
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
import time
import traceback
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence, Union

from .config import StageConfig, diff_configs
from .workspace import Workspace, atomic_path, file_sha256

log = logging.getLogger("ibr_pipeline.runner")

# An input/output declaration: templates ("global/mesh.ply", "{view_dir}/depth.npy") or a function
# of the context (and the view, for per-view declarations) returning workspace keys.
IOSpec = Union[Sequence[str], Callable[..., Sequence[str]]]


@dataclass(frozen=True)
class StageContext:
    """What a stage function receives: the workspace, its validated config, the scene manifest,
    and (whole-scene stages) the fingerprint the runner will record for this run: a stage keeps
    resumable work (caches, checkpoints) under it instead of hashing anything itself."""

    ws: Workspace
    stage: str
    config: StageConfig
    scene: object | None = None  # scene.Scene once `ingest` has run
    progress: bool = True        # False with `ibr ... --no-progress`: the stage's own bars too
    fingerprint: str = ""
    jobs: int = 1                # whole-scene stages: worker processes they may use (`--jobs`)

    def path(self, key: str) -> Path:
        return self.ws.path(key)


@dataclass(frozen=True)
class Stage:
    """One row of the stage table.

    run:  whole-scene stages: run(ctx) writes `outputs`. Per-view stages: run(ctx, view) writes the
          view's `view_outputs`.
    """

    name: str
    help: str
    config: type[StageConfig]
    version: str
    run: Callable
    per_view: bool = False
    inputs: IOSpec = ()
    outputs: IOSpec = ()
    view_inputs: IOSpec = ()
    view_outputs: IOSpec = ()
    views: Callable | None = None  # ctx -> view names to process (default: every view in the scene)
    needs_scene: bool = True


def expand(spec: IOSpec, ctx: StageContext, view: str | None = None) -> list[str]:
    if callable(spec):
        return list(spec(ctx) if view is None else spec(ctx, view))
    subs = {} if view is None else {"view_dir": ctx.ws.view_dir(view), "view": view}
    return [s.format(**subs) for s in spec]


def stage_views(stage: Stage, ctx: StageContext) -> list[str]:
    if stage.views is not None:
        return list(stage.views(ctx))
    return list(ctx.scene.names) if ctx.scene is not None else []


# --- content hashes ---------------------------------------------------------------------------
class HashCache:
    """sha256 of files, cached by (size, mtime_ns) so unchanged files are not re-read."""

    def __init__(self, path: Path):
        self.path = path
        self.entries: dict[str, list] = {}
        self.dirty = False
        if path.is_file():
            try:
                self.entries = json.loads(path.read_text())
            except (OSError, json.JSONDecodeError):
                self.entries = {}

    def digest(self, file: Path) -> str | None:
        """The file's content hash, or None when it does not exist."""
        try:
            st = os.stat(file)
        except FileNotFoundError:
            return None
        key = str(file)
        e = self.entries.get(key)
        if e and e[0] == st.st_size and e[1] == st.st_mtime_ns:
            return e[2]
        sha = file_sha256(file)
        self.entries[key] = [st.st_size, st.st_mtime_ns, sha]
        self.dirty = True
        return sha

    def save(self) -> None:
        if self.dirty and self.path.parent.is_dir():
            with atomic_path(self.path) as tmp:
                tmp.write_text(json.dumps(self.entries))
            self.dirty = False


# --- records ----------------------------------------------------------------------------------
def read_record(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None  # missing or unreadable: treated as never run


def write_record(path: Path, record: dict) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(record, indent=1))


def stale_reasons(stage: Stage, record: dict | None, config: dict, inputs: dict[str, str | None],
                  ws: Workspace, hashes: HashCache, declared: Sequence[str] = ()) -> list[str]:
    """Why a stage (or one view of it) must run; empty when it is up to date."""
    if record is None:
        return ["never run"]
    if record.get("status") == "failed":
        return [f"failed last time: {record.get('error', '?')}"]
    reasons = []
    if record.get("version") != stage.version:
        reasons.append(f"code version changed: {record.get('version')} → {stage.version}")
    changes = diff_configs(stage.name, record.get("config", {}), config)
    if changes:
        reasons.append("config changed: " + "; ".join(changes))
    old = record.get("inputs", {})
    kinds: dict[str, list[str]] = {}  # one line per kind of change, naming the first file
    for key in sorted(set(old) | set(inputs)):
        if key not in old:
            kinds.setdefault("input added", []).append(key)
        elif key not in inputs:
            kinds.setdefault("input removed", []).append(key)
        elif old[key] != inputs[key]:
            kinds.setdefault("input changed", []).append(key)
    for key, meta in record.get("outputs", {}).items():
        sha = hashes.digest(ws.path(key))
        if sha is None:
            kinds.setdefault("output missing", []).append(key)
        elif sha != meta["sha256"]:
            kinds.setdefault("output changed on disk", []).append(key)
    new = [k for k in declared if k not in record.get("outputs", {})]
    if new:  # the stage now writes a file its last run did not
        kinds["output never written"] = new
    reasons += [f"{kind}: {keys[0]}" + (f" (+{len(keys) - 1} more)" if len(keys) > 1 else "")
                for kind, keys in kinds.items()]
    return reasons


def hash_inputs(keys: Sequence[str], ws: Workspace, hashes: HashCache) -> dict[str, str | None]:
    return {k: hashes.digest(ws.path(k)) for k in keys}


def fingerprint(stage: Stage, config: StageConfig, inputs: dict[str, str | None]) -> str:
    """What decides a stage's outputs: its code version, the config fields that affect them
    (Options.fingerprint) and the content hashes of its inputs."""
    blob = json.dumps({"version": stage.version, "config": config.fingerprint(), "inputs": inputs},
                      sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:24]


def output_record(keys: Sequence[str], ws: Workspace) -> dict:
    """Hash the declared outputs after a stage ran; a missing one is a bug in the stage."""
    out = {}
    for key in keys:
        p = ws.path(key)
        if not p.is_file():
            raise RuntimeError(f"stage did not write its declared output {key}")
        out[key] = {"sha256": file_sha256(p), "size": p.stat().st_size}
    return out


def run_view_task(stage: Stage, ctx: StageContext, view: str) -> dict:
    """Executed on a worker (process pool or Dask): run one view, hash its outputs."""
    t0, c0 = time.perf_counter(), time.process_time()
    stage.run(ctx, view)
    outputs = output_record(expand(stage.view_outputs, ctx, view), ctx.ws)
    # process_time counts every thread of the worker: the CPU a view costs (`ibr bench speed`)
    return {"outputs": outputs, "seconds": time.perf_counter() - t0,
            "cpu_seconds": time.process_time() - c0}


# --- planning ---------------------------------------------------------------------------------
@dataclass
class StagePlan:
    stage: Stage
    state: str  # "up to date" | "will run" | "blocked" | "not selected"
    reasons: list[str] = field(default_factory=list)
    views_todo: list[str] = field(default_factory=list)
    views_total: int = 0
    view_reasons: dict[str, list[str]] = field(default_factory=dict)
    input_hashes: dict = field(default_factory=dict)  # key -> sha (whole) or view -> {key: sha}

    def summary(self) -> str:
        if not self.stage.per_view or self.state != "will run" or not self.view_reasons:
            return "; ".join(self.reasons)
        counts = Counter(r for v in self.views_todo for r in self.view_reasons.get(v, []))
        parts = [f"{n} view{'s' * (n > 1)}: {r}" for r, n in counts.most_common(4)]
        if len(counts) > 4:
            parts.append(f"... {len(counts) - 4} more reasons")
        return f"{len(self.views_todo)}/{self.views_total} views — " + "; ".join(parts)


def plan_stage(stage: Stage, ctx: StageContext, hashes: HashCache, force: bool,
               upstream_running: str | None) -> StagePlan:
    """Decide whether `stage` would run now, and why."""
    ws = ctx.ws
    if upstream_running is not None:
        return StagePlan(stage, "will run", [f"upstream stage {upstream_running!r} will run"])
    if stage.needs_scene and ctx.scene is None:
        return StagePlan(stage, "blocked", ["no scene manifest: stage 'ingest' has not run"])
    config = ctx.config.fingerprint()
    shared = hash_inputs(expand(stage.inputs, ctx), ws, hashes)
    missing = [k for k, v in shared.items() if v is None]
    if missing:
        return StagePlan(stage, "blocked", [f"missing input: {missing[0]}"
                                            + (f" (+{len(missing) - 1} more)" if len(missing) > 1 else "")])
    if not stage.per_view:
        record = read_record(ws.state_file(stage.name))
        reasons = ["forced"] if force else stale_reasons(stage, record, config, shared, ws, hashes,
                                                         expand(stage.outputs, ctx))
        return StagePlan(stage, "will run" if reasons else "up to date", reasons, input_hashes=shared)
    views = stage_views(stage, ctx)
    plan = StagePlan(stage, "up to date", views_total=len(views))
    for view in views:
        inputs = dict(shared)
        inputs.update(hash_inputs(expand(stage.view_inputs, ctx, view), ws, hashes))
        plan.input_hashes[view] = inputs
        gone = [k for k, v in inputs.items() if v is None]
        if gone:
            reasons = [f"missing input: {gone[0]}"]
        elif force:
            reasons = ["forced"]
        else:
            reasons = stale_reasons(stage, read_record(ws.state_file(stage.name, view)), config,
                                    inputs, ws, hashes)
        if reasons:
            plan.views_todo.append(view)
            plan.view_reasons[view] = reasons
    if plan.views_todo:
        plan.state = "will run"
    plan.reasons = [f"{len(views)} views up to date"] if not plan.views_todo else []
    return plan


def make_record(stage: Stage, ctx: StageContext, status: str, inputs: dict, view: str | None = None,
                outputs: dict | None = None, seconds: float = 0.0, error: str = "",
                cpu_seconds: float | None = None) -> dict:
    rec = {"stage": stage.name, "status": status, "version": stage.version,
           "config": ctx.config.fingerprint(), "inputs": inputs, "outputs": outputs or {},
           "seconds": round(seconds, 4), "finished": time.strftime("%Y-%m-%dT%H:%M:%S")}
    if cpu_seconds is not None:
        rec["cpu_seconds"] = round(cpu_seconds, 4)
    if view is not None:
        rec["view"] = view
    if error:
        rec["error"] = error
    return rec


def error_line(exc: BaseException) -> str:
    lines = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {lines[0] if lines else ''}"


def format_traceback(exc: BaseException) -> str:
    return "".join(traceback.format_exception(exc))
