"""Speed of the pipeline and the renderer: per-stage CPU seconds per view and per megapixel, frame
time, their ratios to Xu et al.'s figures, and to other code trees measured in the same run.

    ibr bench speed [--views 24,120] [--width 640 --height 480] [--stages S1,S2,...]
        [--variant NAME=SRC[,STAGE.FIELD=VALUE...]]... [--jobs 2] [--frames 24] [--out OUT]

For each view count a synthetic mirror_room (`--depth-scale 1.0`, as `make demo-full`) is made
once under OUT/scenes and run up to the first timed stage once (untimed). Then, for each variant,
a copy of that workspace runs each timed stage as its own `ibr run WS --from S --until S`
process (the variant's source tree first on PYTHONPATH, its `--set` overrides added): wall
seconds, and CPU seconds of the process and its workers (RUSAGE_CHILDREN), imports included as a
user pays them. After the stages, `speed_frames.py` (run with the variant's tree) renders the
fly-through twice with hysteresis (median ms of the second pass) and the held-out test cameras
three times (PSNR against gt/test/images; median ms of the last two passes).

Variants: `--variant before=/tmp/base` times a checkout of an older commit (`git worktree add
/tmp/base HEAD~3`); `--variant ref=.,reflection.decompose.kernels=reference` this tree with an
override. The first variant is the baseline of every ratio; without --variant, this tree alone.

Figures of Xu et al. 2021 (their GPU machine, §6 and Table 2): the per-view decomposition took
1.5 h for the 2289 views of Living Room 1 (Table 1) rendered at 1280x960, i.e. 5400 / (2289 x
1.2288) = 1.92 seconds per megapixel on their CPU + GPU machine; view warping 30.7 ms per
1280x960 frame (25.0 ms per megapixel). Ours are CPU seconds on this machine, per megapixel of
each reflective view (the stricter count: Xu's figure divides by all views).
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

from .common import REPO, logger, machine

XU_DECOMP_S_PER_MP = 5400.0 / (2289 * 1280 * 960 / 1e6)  # Table 2 / Table 1 (1.92)
XU_FRAME_MS = 30.7                                        # §6: view warping, 1280x960
XU_FRAME_MS_PER_MP = XU_FRAME_MS / (1280 * 960 / 1e6)     # 24.98
STAGE_ORDER = ("ingest", "poses", "global_mesh", "view_depth", "view_mesh", "reflectors",
               "reflection", "render_views", "supersample", "evaluate")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--views", default="24,120", help="capture view counts, comma-separated "
                   "(default 24,120: the 5x growth of issue #28's linearity target)")
    p.add_argument("--width", type=int, default=640, help="image width of the scenes (px)")
    p.add_argument("--height", type=int, default=480, help="image height of the scenes (px)")
    p.add_argument("--test-views", type=int, default=8, help="held-out cameras of each scene")
    p.add_argument("--frames", type=int, default=24, help="fly-through frames timed")
    p.add_argument("--stages",
                   default="global_mesh,view_depth,view_mesh,reflectors,reflection,render_views",
                   help="stages timed, in pipeline order (the ones before are run untimed once); "
                   "a tree without a stage gets no row for it (an older tree's `reflection` "
                   "detects the planes itself)")
    p.add_argument("--variant", action="append", default=[], metavar="NAME=SRC[,SET...]",
                   help="a code tree to time (repeatable; the first is the baseline of the "
                   "ratios); SET = STAGE.FIELD=VALUE overrides for its runs")
    p.add_argument("--jobs", type=int, default=2, help="worker processes of the per-view stages")
    p.add_argument("--no-frames", action="store_true", help="skip the frame-time measurement")
    p.add_argument("--out", default="out/bench_speed", help="output folder (scenes, workspaces, "
                   "speed.json, speed.md)")


def _variants(specs: list[str]) -> list[dict]:
    from ibr_pipeline.errors import InputError
    out = []
    for spec in specs or [f"this={REPO}"]:
        name, _, rest = spec.partition("=")
        if not name or not rest:
            raise InputError(f"--variant {spec!r}: expected NAME=SRC[,STAGE.FIELD=VALUE...]")
        src, *sets = rest.split(",")
        src = Path(src).resolve()
        if not (src / "ibr_pipeline" / "__init__.py").is_file():
            raise InputError(f"--variant {name}: {src} holds no ibr_pipeline/ package (give a "
                             "checkout of this repository, e.g. from `git worktree add`)")
        out.append({"name": name, "src": src, "sets": sets})
    if len({v["name"] for v in out}) != len(out):
        raise InputError("--variant: names must differ")
    return out


def _ibr(src: Path, args: list[str]) -> tuple[float, float]:
    """Run `python -m ibr_pipeline ARGS` with `src` first on the path: (wall s, CPU s of it
    and every worker it waited for)."""
    env = dict(os.environ, PYTHONPATH=str(src))
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    res = subprocess.run([sys.executable, "-m", "ibr_pipeline"] + args, cwd=src, env=env,
                         capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if res.returncode != 0:
        raise RuntimeError(f"ibr {' '.join(args)} (src {src}) exited {res.returncode}:\n"
                           f"{(res.stdout + res.stderr)[-3000:]}")
    return wall, cpu


def _scene(root: Path, views: int, a) -> Path:
    from ibr_pipeline.synthetic.generate import SynthOptions, generate
    path = root / f"mirror_room_{a.width}x{a.height}_{views}"
    if not (path / "gt" / "scene.json").is_file():
        logger().info("speed: generating %s", path)
        generate(SynthOptions("mirror_room", seed=0, width=a.width, height=a.height, views=views,
                              test_views=a.test_views, flythrough=a.frames, depth_scale=1.0,
                              progress=False), path)
    return path


def _reflective_views(ws: Path) -> int:
    n = 0
    for p in (ws / "views").glob("*/layers.json"):
        if json.loads(p.read_text()).get("reflector") is not None:
            n += 1
    return n


def _frames(src: Path, ws: Path, scene: Path) -> dict:
    script = Path(__file__).with_name("speed_frames.py")
    env = dict(os.environ, PYTHONPATH=str(src))
    res = subprocess.run([sys.executable, str(script), str(ws), str(scene)], cwd=src, env=env,
                         capture_output=True, text=True)
    if res.returncode != 0:
        raise RuntimeError(f"speed_frames.py (src {src}) exited {res.returncode}:\n"
                           f"{(res.stdout + res.stderr)[-3000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def main(a: argparse.Namespace) -> int:
    from ibr_pipeline.errors import InputError
    log = logger()
    variants = _variants(a.variant)
    stages = [s for s in a.stages.split(",") if s]
    bad = [s for s in stages if s not in STAGE_ORDER]
    if bad:
        raise InputError(f"--stages: unknown stage {bad[0]!r} (choose from {', '.join(STAGE_ORDER)})")
    stages.sort(key=STAGE_ORDER.index)
    first = STAGE_ORDER[STAGE_ORDER.index(stages[0]) - 1] if stages[0] != "ingest" else None
    counts = sorted({int(v) for v in a.views.split(",") if v})
    out = Path(a.out).resolve()  # the timed processes run inside each variant's tree
    out.mkdir(parents=True, exist_ok=True)
    mp = a.width * a.height / 1e6
    rows = []
    for n in counts:
        scene = _scene(out / "scenes", n, a)
        prep = out / f"prep_{a.width}x{a.height}_{n}"
        if first is not None:  # the stages before the timed ones, once, with this tree
            _ibr(REPO, ["-q", "run", str(prep), "--input", str(scene), "--until", first,
                        "--jobs", str(a.jobs), "--no-progress"])
        for v in variants:
            ws = out / f"ws_{a.width}x{a.height}_{n}_{v['name']}"
            shutil.rmtree(ws, ignore_errors=True)
            if first is not None:
                shutil.copytree(prep, ws, symlinks=True)
            sets = [x for s in v["sets"] for x in ("--set", s)]
            for s in stages:
                if not (Path(v["src"]) / "ibr_pipeline" / "stages" / f"{s}.py").is_file():
                    log.info("speed: %s has no stage %s", v["name"], s)
                    continue
                log.info("speed: %d views, %s, %s", n, v["name"], s)
                args = ["-q", "run", str(ws), "--from", s, "--until", s, "--jobs", str(a.jobs),
                        "--no-progress", *sets]
                if first is None and s == "ingest":
                    args += ["--input", str(scene)]
                wall, cpu = _ibr(v["src"], args)
                row = {"views": n, "variant": v["name"], "stage": s, "wall_s": round(wall, 2),
                       "cpu_s": round(cpu, 2), "cpu_s_per_view": round(cpu / n, 4),
                       "cpu_s_per_mp": round(cpu / (n * mp), 3)}
                if s == "reflection":
                    k = _reflective_views(ws)
                    row["reflective_views"] = k
                    if k:
                        row["cpu_s_per_mp_reflective"] = round(cpu / (k * mp), 3)
                        row["x_xu"] = round(cpu / (k * mp) / XU_DECOMP_S_PER_MP, 2)
                rows.append(row)
            if not a.no_frames and STAGE_ORDER.index(stages[-1]) >= STAGE_ORDER.index("view_mesh"):
                fr = _frames(v["src"], ws, scene)
                fr.update(views=n, variant=v["name"], stage="frame",
                          ms_per_mp=round(fr["median_ms"] / mp, 2),
                          x_xu=round(fr["median_ms"] / mp / XU_FRAME_MS_PER_MP, 2))
                rows.append(fr)
    result = {"machine": machine(), "size": [a.width, a.height], "views": counts,
              "jobs": a.jobs, "variants": [{k: str(x) if isinstance(x, Path) else x
                                            for k, x in v.items()} for v in variants],
              "xu": {"decomp_s_per_mp": round(XU_DECOMP_S_PER_MP, 3), "frame_ms": XU_FRAME_MS,
                     "frame_ms_per_mp": round(XU_FRAME_MS_PER_MP, 2)},
              "rows": rows, "linearity": _linearity(rows, counts)}
    (out / "speed.json").write_text(json.dumps(result, indent=1))
    md = markdown(result)
    (out / "speed.md").write_text(md)
    print(md)
    return 0


def _linearity(rows: list[dict], counts: list[int]) -> list[dict]:
    """CPU(most views) / CPU(fewest views) per variant and stage, against the view ratio."""
    if len(counts) < 2:
        return []
    lo, hi = counts[0], counts[-1]
    by = {(r["variant"], r["stage"], r["views"]): r for r in rows if "cpu_s" in r}
    out = []
    for (var, st, n), r in by.items():
        if n != hi or (var, st, lo) not in by or not by[(var, st, lo)]["cpu_s"]:
            continue
        out.append({"variant": var, "stage": st, "views_ratio": round(hi / lo, 2),
                    "cpu_ratio": round(r["cpu_s"] / by[(var, st, lo)]["cpu_s"], 2)})
    return out


def markdown(res: dict) -> str:
    """The tables of docs/BENCHMARKS.md: stages, frames, linearity; ratios to the first variant."""
    rows = res["rows"]
    base = res["variants"][0]["name"]
    ref = {(r["views"], r["stage"]): r for r in rows if r["variant"] == base}
    w, h = res["size"]
    lines = [f"{w}x{h}, jobs {res['jobs']}; CPU seconds include the workers; x base = CPU / "
             f"the `{base}` variant's; Xu: {res['xu']['decomp_s_per_mp']} s/MP (decomposition), "
             f"{res['xu']['frame_ms']} ms per 1280x960 frame", "",
             "| views | variant | stage | wall s | CPU s | CPU s/view | CPU s/MP | x base | "
             "reflective views | CPU s/MP per reflective view | x Xu |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if "cpu_s" not in r:
            continue
        b = ref.get((r["views"], r["stage"]))
        xb = f"{r['cpu_s'] / b['cpu_s']:.2f}" if b and b["cpu_s"] else ""
        lines.append(f"| {r['views']} | {r['variant']} | {r['stage']} | {r['wall_s']} | "
                     f"{r['cpu_s']} | {r['cpu_s_per_view']} | {r['cpu_s_per_mp']} | {xb} | "
                     f"{r.get('reflective_views', '')} | {r.get('cpu_s_per_mp_reflective', '')} | "
                     f"{r.get('x_xu', '')} |")
    fr = [r for r in rows if r["stage"] == "frame"]
    if fr:
        lines += ["", "| views | variant | frame median ms | p90 ms | GL ms | post ms | views "
                  "blended | ms/MP | x Xu | x base | held-out ms (GL / post) | held-out holes | "
                  "held-out PSNR dB | PSNR - base |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in fr:
            b = ref.get((r["views"], "frame"))
            lines.append(f"| {r['views']} | {r['variant']} | {r['median_ms']:.1f} | "
                         f"{r['p90_ms']:.1f} | {r['median_gl_ms']:.1f} | {r['median_post_ms']:.1f} | "
                         f"{r['mean_selected_views']:.1f} | {r['ms_per_mp']} | {r['x_xu']} | "
                         f"{r['median_ms'] / b['median_ms']:.2f} | {r['heldout_median_ms']:.1f} "
                         f"({r['heldout_median_gl_ms']:.1f} / {r['heldout_median_post_ms']:.1f}) | "
                         f"{100 * r['heldout_holes']:.2f} % | {r['psnr']:.3f} | "
                         f"{r['psnr'] - b['psnr']:+.3f} |" if b else "")
    if res["linearity"]:
        lines += ["", "| variant | stage | views ratio | CPU ratio |", "|---|---|---|---|"]
        lines += [f"| {x['variant']} | {x['stage']} | {x['views_ratio']} | {x['cpu_ratio']} |"
                  for x in res["linearity"]]
    return "\n".join(lines) + "\n"
