"""The settings of `ibr bench pipeline SCENE`: the pipeline over a grid that trades speed for quality.

Each setting is a synthetic scene size (resolution, capture views) plus stage-config overrides
(the same `stage.field=value` a user passes to `ibr run --set`). For each setting the bench
generates the scene (cached by its options), runs every stage in a fresh workspace, and appends one
JSON line to OUT/results.jsonl: the machine, the setting, seconds per stage, render ms/frame,
held-out PSNR/SSIM/FLIP (overall and inside reflectors, from the `evaluate` stage's
eval/metrics.json), and the model size on disk per view. Charts and tables are then drawn from
*all* lines in results.jsonl (`charts.py`), so runs accumulate and `--charts-only` redraws.
"""
from __future__ import annotations

import hashlib
import json
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

from ibr_pipeline import layout as L

from .common import logger

log = logger()

VIEW_DIRS = "views/*"  # every view's folder (layout.view_dir), as a glob

# Scene sizes for the bench (width, height, views): small enough to sweep on 2 cores.
SCENE_DEFAULTS = {"tiny": (160, 120, 8), "mirror_room": (320, 240, 24), "glass_room": (320, 240, 24),
                  "curved": (320, 240, 24)}


@dataclass(frozen=True)
class Setting:
    name: str
    help: str
    overrides: dict = field(default_factory=dict)  # {stage: {field: value}}
    scale: float = 1.0                              # image resolution factor
    views: float = 1.0                              # fraction of capture views
    group: str = "grid"                             # grid | baseline | stability
    degrade: tuple = ()                             # (kind, amount) for stability sweeps


def settings(grid: str) -> list[Setting]:
    """The settings table. 'quick' is a subset of 'full'. The single-layer baseline and the oracle
    are measured in every run (the evaluate stage scores both next to ours), so they need no
    setting of their own; DSRNet is scored against bicubic upsampling by the supersample stage."""
    s = [
        Setting("default", "every stage at its default"),
        Setting("tri_low", "per-view vertex budget 5 000 per 640x480 (default 20 000)",
                {"view_mesh": {"max_vertices_640x480": 5000}}),
        Setting("blend_2", "blend at most the 2 closest selected views",
                {"render_views": {"renderer": {"max_views": 2}}}),
        Setting("half_res", "images at half resolution", scale=0.5),
        Setting("views_50", "half of the capture views", views=0.5),
    ]
    if grid == "full":
        s += [
            Setting("tri_high", "per-view vertex budget 40 000 per 640x480 (the paper's)",
                    {"view_mesh": {"max_vertices_640x480": 40000}}),
            Setting("blend_4", "blend at most the 4 closest selected views",
                    {"render_views": {"renderer": {"max_views": 4}}}),
            Setting("no_warp", "reflection without the ARAP grid warp (Eqs. 4-5)",
                    {"reflection": {"decompose": {"use_warp": False}}}),
            Setting("multiview", "reflection with the multi-view pass (Eqs. 11-13)",
                    {"reflection": {"decompose": {"multiview": True}}}),
            Setting("views_25", "a quarter of the capture views", views=0.25),
        ]
    return s


# Every bench run caps DSRNet training so that a grid fits in an afternoon on 2 cores; the
# supersample stage records its own held-out comparison with bicubic upsampling either way.
BENCH_DEFAULTS = {"supersample": {"time_budget_s": 60}}
# Stability settings score the renders (before supersampling): DSRNet gets a token budget there.
STABILITY_DEFAULTS = {"supersample": {"time_budget_s": 15}}


def scene_folder(cache: Path, scene: str, seed: int, width: int, height: int, views: int) -> Path:
    """Generate (once) the synthetic scene for these options; returns its folder."""
    from ibr_pipeline.synthetic.generate import SynthOptions, generate
    key = hashlib.sha256(json.dumps([scene, seed, width, height, views]).encode()).hexdigest()[:10]
    out = cache / f"{scene}-{width}x{height}-{views}v-s{seed}-{key}"
    if not (out / "gt" / "scene.json").is_file():
        if out.exists():
            shutil.rmtree(out)
        log.info("bench: generating %s %dx%d, %d views (seed %d)", scene, width, height, views, seed)
        generate(SynthOptions(scene, seed=seed, width=width, height=height, views=views,
                              progress=False), out)
    return out


def model_size_bytes(ws: Path) -> dict:
    """Bytes on disk of what the renderer needs: per-view meshes, layer textures, images, network."""
    sizes = {"meshes": 0, "textures": 0, "network": 0}
    for p in ws.glob(f"{VIEW_DIRS}/*"):
        if p.suffix == ".ply":
            sizes["meshes"] += p.stat().st_size
        elif p.name in (L.I0, L.I1, L.BETA):
            sizes["textures"] += p.stat().st_size
    nn = ws / L.MODEL
    if nn.is_file():
        sizes["network"] = nn.stat().st_size
    return sizes


def _file_bytes(p: Path) -> int:
    return p.stat().st_size if p.is_file() else 0


def _render_ms(ws: Path, which: str) -> float | None:
    t = ws / L.render_file(which, "timings.json")
    if not t.is_file():
        return None
    d = json.loads(t.read_text())
    frames = [f["ms"] for f in d.get("frames", []) if "ms" in f] if isinstance(d, dict) else []
    if len(frames) >= 2:  # the first frame also pays the GL warm-up (shader compiles, uploads)
        frames = sorted(frames[1:])
        return float(frames[len(frames) // 2])
    return d.get("median_ms") if isinstance(d, dict) else None


def _metrics(ws: Path) -> dict:
    p = ws / L.EVAL_METRICS
    if not p.is_file():
        return {}
    d = json.loads(p.read_text())
    return d.get("summary", d) if isinstance(d, dict) else {}


def _stage_seconds(ws: Path) -> dict:
    """Task seconds per stage from the runner's records (sum over views), so a setting that reused
    another's up-to-date stages still reports what those stages cost."""
    out = {}
    state = ws / ".ibr" / "state"   # the runner's records (workspace.py)
    for rec in list(state.glob("*.json")) + list(state.glob("*/*.json")):
        d = json.loads(rec.read_text())
        out[d["stage"]] = round(out.get(d["stage"], 0.0) + float(d.get("seconds", 0.0)), 3)
    return out


def _merge(a: dict, b: dict) -> dict:
    out = {k: dict(v) for k, v in a.items()}
    for k, v in b.items():
        out.setdefault(k, {}).update(v)
    return out


def run_setting(s: Setting, scene: str, seed: int, base: tuple[int, int, int], out: Path,
                jobs: int = 1) -> dict:
    from ibr_pipeline.executors import make_executor
    from ibr_pipeline.pipeline import load_configs, run
    from ibr_pipeline.scene import cameras_from_json
    from ibr_pipeline.stages import STAGES
    from ibr_pipeline.workspace import Workspace

    from .degrade import degrade_input

    w, h, n = base
    w, h = int(round(w * s.scale / 8)) * 8, int(round(h * s.scale / 8)) * 8
    src = scene_folder(out / "scenes", scene, seed, w, h, n)
    if s.views != 1.0:
        # fewer capture views (at least 4) of the SAME scene, evenly spaced as the `views`
        # degradation keeps them, so the held-out test cameras -- half-way between consecutive
        # captures of the full path -- and hence the scores stay comparable with `default`
        keep = max(4, int(round(n * s.views)))
        src = degrade_input(src, out / "degraded" / f"{s.name}-subset", "views", keep / n, seed=seed)
        n = len(cameras_from_json(src / "cameras.json"))
    if s.degrade:
        src = degrade_input(src, out / "degraded" / s.name, *s.degrade, seed=seed)
    ws_path = out / "ws" / s.name
    if ws_path.exists():
        shutil.rmtree(ws_path)
    default_ws = out / "ws" / "default"
    if (s.name != "default" and not s.degrade and (s.scale, s.views) == (1.0, 1.0)
            and (default_ws / ".ibr" / "runs.jsonl").is_file()):
        # same input as `default`: start from its workspace, so the runner reruns only the stages
        # whose config differs (fingerprints) -- what a user tuning one knob would do
        shutil.copytree(default_ws, ws_path, ignore=shutil.ignore_patterns("report", "runs.jsonl"))
        reused = "default"
    else:
        ws_path.mkdir(parents=True)
        reused = None
    (ws_path / "ibr.toml").write_text(f"[input]\npath = {json.dumps(str(src.resolve()))}\n")
    ws = Workspace(ws_path)
    overrides = _merge(STABILITY_DEFAULTS if s.group == "stability" else BENCH_DEFAULTS,
                       s.overrides)
    t0 = time.perf_counter()
    with make_executor(jobs, None, 0) as ex:
        results = run(STAGES, ws, load_configs(STAGES, ws, overrides), STAGES, executor=ex,
                      progress=False)
    wall = time.perf_counter() - t0
    sizes = model_size_bytes(ws_path)
    n_views = max(1, len(list(ws_path.glob(VIEW_DIRS))))
    secs = _stage_seconds(ws_path)
    pre = {k: v for k, v in secs.items() if k not in ("render_views", "evaluate")}
    nn = ws_path / L.TRAIN_JSON
    dsr = json.loads(nn.read_text()).get("validation", {}) if nn.is_file() else {}
    return {"setting": s.name, "group": s.group, "help": s.help, "scene": scene, "seed": seed,
            "width": w, "height": h, "views": n, "overrides": overrides, "reused": reused,
            "degrade": list(s.degrade), "stage_seconds": secs,
            "preprocess_s": round(sum(pre.values()), 3), "wall_s": round(wall, 3),
            "stage_results": {r.name: r.result for r in results},
            "render_ms": _render_ms(ws_path, "test"),
            "render_ms_single": _render_ms(ws_path, "test_single"),
            "metrics": _metrics(ws_path), "dsrnet": dsr,
            "model_bytes": sizes, "mb_per_view": round(sum(sizes.values()) / n_views / 1e6, 4),
            "naive_mb_per_view": round(_file_bytes(ws_path / L.GLOBAL_MESH) / n_views / 1e6, 4),
            "fallbacks": _fallbacks(ws_path)}


def _fallbacks(ws: Path) -> list[str]:
    """What the pipeline did instead of failing, as the stages recorded it."""
    notes = []
    rep = ws / L.GLOBAL_REPORT
    if rep.is_file():
        d = json.loads(rep.read_text())
        if d.get("unregistered"):
            notes.append(f"global_mesh: {len(d['unregistered'])} view(s) not registered, excluded")
    for lj in ws.glob(f"{VIEW_DIRS}/{L.LAYERS}"):
        d = json.loads(lj.read_text())
        if d.get("fallback"):
            notes.append(f"reflection {lj.parent.name}: {d['fallback']}")
        for x in d.get("discarded") or []:
            notes.append(f"reflection {lj.parent.name}: {x.get('name')} single-layer "
                         f"({x.get('discarded', 'discarded')})")
    nn = ws / L.TRAIN_JSON
    if nn.is_file() and json.loads(nn.read_text()).get("fallback"):
        notes.append(f"supersample: {json.loads(nn.read_text())['fallback']}")
    return notes
