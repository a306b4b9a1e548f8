"""`ibr bench SCENE`: the pipeline over a grid of settings that trade speed for quality.

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
import logging
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import InputError

log = logging.getLogger("ibr_pipeline.bench")

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
    """The settings table. 'quick' is a subset of 'full'."""
    s = [
        Setting("default", "every stage at its default"),
        Setting("single_layer", "baseline: no reflection decomposition (single-layer IBR)",
                {"reflection": {"enabled": False}}, group="baseline"),
        Setting("half_res", "images at half resolution", scale=0.5),
        Setting("views_50", "half of the capture views", views=0.5),
        Setting("tri_low", "per-view triangle budget / 4", {"view_mesh": {"budget_scale": 0.25}}),
        Setting("blend_4", "at most 4 blended views", {"render_views": {"max_views": 4}}),
    ]
    if grid == "full":
        s += [
            Setting("views_25", "a quarter of the capture views", views=0.25),
            Setting("tri_high", "per-view triangle budget x 2", {"view_mesh": {"budget_scale": 2.0}}),
            Setting("blend_2", "at most 2 blended views", {"render_views": {"max_views": 2}}),
            Setting("blend_16", "at most 16 blended views", {"render_views": {"max_views": 16}}),
        ]
    return s


def scene_folder(cache: Path, scene: str, seed: int, width: int, height: int, views: int) -> Path:
    """Generate (once) the synthetic scene for these options; returns its folder."""
    from ..synthetic.generate import SynthOptions, generate
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
    for p in ws.glob("views/*/*"):
        if p.suffix == ".ply":
            sizes["meshes"] += p.stat().st_size
        elif p.name in ("I0.png", "I1.png", "beta.npy"):
            sizes["textures"] += p.stat().st_size
    nn = ws / "nn" / "dsrnet.pt"
    if nn.is_file():
        sizes["network"] = nn.stat().st_size
    return sizes


def _render_ms(ws: Path) -> float | None:
    vals = []
    for t in ws.glob("renders/*/timings.json"):
        d = json.loads(t.read_text())
        frames = d.get("frames", d) if isinstance(d, dict) else d
        if isinstance(frames, list):
            vals += [f["ms"] for f in frames if isinstance(f, dict) and "ms" in f]
        elif isinstance(d, dict) and "median_ms" in d:
            vals.append(d["median_ms"])
    if not vals:
        return None
    vals.sort()
    return float(vals[len(vals) // 2])


def _metrics(ws: Path) -> dict:
    p = ws / "eval" / "metrics.json"
    if not p.is_file():
        return {}
    d = json.loads(p.read_text())
    return d.get("summary", d) if isinstance(d, dict) else {}


def run_setting(s: Setting, scene: str, seed: int, base: tuple[int, int, int], out: Path,
                jobs: int = 1) -> dict:
    from ..executors import make_executor
    from ..pipeline import load_configs, run
    from ..stages import STAGES
    from ..workspace import Workspace
    from .degrade import degrade_input

    w, h, n = base
    w, h = int(round(w * s.scale / 8)) * 8, int(round(h * s.scale / 8)) * 8
    n = max(4, int(round(n * s.views)))
    src = scene_folder(out / "scenes", scene, seed, w, h, n)
    if s.degrade:
        src = degrade_input(src, out / "degraded" / s.name, *s.degrade, seed=seed)
    ws_path = out / "ws" / s.name
    if ws_path.exists():
        shutil.rmtree(ws_path)
    ws_path.mkdir(parents=True)
    (ws_path / "ibr.toml").write_text(f"[input]\npath = {json.dumps(str(src.resolve()))}\n")
    ws = Workspace(ws_path)
    t0 = time.perf_counter()
    with make_executor(jobs, None, 0) as ex:
        results = run(STAGES, ws, load_configs(STAGES, ws, {k: dict(v) for k, v in
                                                            s.overrides.items()}),
                      STAGES, executor=ex, progress=False)
    wall = time.perf_counter() - t0
    sizes = model_size_bytes(ws_path)
    n_views = max(1, len(list(ws_path.glob("views/*"))))
    pre = {r.name: round(r.seconds, 3) for r in results
           if r.name not in ("render_views", "evaluate") and r.result == "ran"}
    return {"setting": s.name, "group": s.group, "help": s.help, "scene": scene, "seed": seed,
            "width": w, "height": h, "views": n, "overrides": s.overrides,
            "degrade": list(s.degrade), "stage_seconds": pre,
            "preprocess_s": round(sum(pre.values()), 3), "wall_s": round(wall, 3),
            "stage_results": {r.name: r.result for r in results},
            "render_ms": _render_ms(ws_path), "metrics": _metrics(ws_path),
            "model_bytes": sizes, "mb_per_view": round(sum(sizes.values()) / n_views / 1e6, 4),
            "fallbacks": _fallbacks(ws_path)}


def _fallbacks(ws: Path) -> list[str]:
    """What the pipeline did instead of failing, as the stages recorded it."""
    notes = []
    rep = ws / "global" / "report.json"
    if rep.is_file():
        d = json.loads(rep.read_text())
        if d.get("unregistered"):
            notes.append(f"global_mesh: {len(d['unregistered'])} view(s) not registered, excluded")
    for lj in ws.glob("views/*/layers.json"):
        d = json.loads(lj.read_text())
        if d.get("fallback"):
            notes.append(f"reflection {lj.parent.name}: {d['fallback']}")
    return notes


def run_bench(args) -> int:
    from ..synthetic.bench import machine
    from .charts import draw_all
    from .stability import stability_settings

    if args.scene not in SCENE_DEFAULTS:
        raise InputError(f"bench: unknown scene {args.scene!r} (choose from {', '.join(SCENE_DEFAULTS)})")
    base = list(SCENE_DEFAULTS[args.scene])
    for i, v in enumerate((args.width, args.height, args.views)):
        if v is not None:
            if v < 8:
                raise InputError(f"bench: --{('width', 'height', 'views')[i]} {v} is too small")
            base[i] = v
    todo = settings(args.grid) + (stability_settings() if args.stability else [])
    if args.list:
        for s in todo:
            print(f"{s.name:16s} [{s.group}] {s.help}")
        return 0
    if args.only:
        unknown = set(args.only) - {s.name for s in todo}
        if unknown:
            raise InputError(f"bench: unknown setting(s) {', '.join(sorted(unknown))} (see --list)")
        todo = [s for s in todo if s.name in args.only]
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    results = out / "results.jsonl"
    if not args.charts_only:
        from tqdm import tqdm
        mach = machine()
        for s in tqdm(todo, desc=f"bench {args.scene}", unit="setting"):
            try:
                rec = run_setting(s, args.scene, args.seed, tuple(base), out, args.jobs)
            except Exception as e:  # a setting that crashes is a finding, not the end of the bench
                log.error("bench: setting %s crashed: %s", s.name, e)
                rec = {"setting": s.name, "group": s.group, "help": s.help, "scene": args.scene,
                       "degrade": list(s.degrade), "crashed": f"{type(e).__name__}: {e}"}
            rec["machine"] = mach
            rec["time"] = time.strftime("%Y-%m-%dT%H:%M:%S")
            with open(results, "a") as f:
                f.write(json.dumps(rec) + "\n")
    if not results.is_file():
        raise InputError(f"{results}: no results yet (run without --charts-only first)")
    written = draw_all(results, out)
    for p in written:
        print(p)
    return 0
