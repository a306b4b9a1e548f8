"""Every stage on a synthetic scene over a grid of settings: speed against accuracy, stability.

    ibr bench pipeline SCENE [--grid quick|full] [--only NAME ...] [--stability] [--out out/bench]

Generates a synthetic scene from a seed, runs the pipeline once per setting (grid.py) and records
per setting: preprocessing seconds per stage, render ms/frame, PSNR/SSIM/FLIP on held-out views
(overall and inside reflectors), model size on disk. `--stability` adds the sweeps of
stability.py: one input degraded at a time (degrade.py). Results are appended to
OUT/results.jsonl with the machine described; charts and tables (charts.py) land in OUT/ and are
drawn from every line recorded so far, so runs accumulate and `--charts-only` redraws.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from ibr_pipeline.errors import InputError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", help="synthetic scene: mirror_room, glass_room, curved, tiny")
    p.add_argument("--out", type=Path, default=Path("out/bench"), help="output folder (default out/bench)")
    p.add_argument("--seed", type=int, default=0, help="scene seed (default 0)")
    p.add_argument("--grid", choices=("quick", "full"), default="quick",
                   help="quick: a few settings around the defaults; full: the whole grid")
    p.add_argument("--only", action="append", default=[], metavar="NAME",
                   help="run only these settings (repeatable; see --list)")
    p.add_argument("--list", action="store_true", help="list the settings and exit")
    p.add_argument("--stability", action="store_true",
                   help="also run the stability sweeps (degrade one input at a time)")
    p.add_argument("--charts-only", action="store_true",
                   help="redraw charts and tables from OUT/results.jsonl; run nothing")
    p.add_argument("--width", type=int, help="image width (default: the scene's bench default)")
    p.add_argument("--height", type=int, help="image height")
    p.add_argument("--views", type=int, help="capture views")
    p.add_argument("--jobs", "-j", type=int, default=1, help="worker processes per stage")


def main(args: argparse.Namespace) -> int:
    from .charts import draw_all
    from .common import machine
    from .grid import SCENE_DEFAULTS, log, run_setting, settings
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
