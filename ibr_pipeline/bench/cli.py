"""`ibr bench SCENE`. Light at import time: work happens in main."""
from __future__ import annotations

import argparse
from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser("bench", help="run the pipeline on a synthetic scene over a grid of settings "
                       "(speed vs accuracy, stability sweeps); JSON lines + charts",
                       description="Generate a synthetic scene from a seed, run the pipeline once "
                       "per setting, and record per setting: preprocessing seconds per stage, render "
                       "ms/frame, PSNR/SSIM/FLIP on held-out views (overall and inside reflectors), "
                       "model size on disk. Results are appended to OUT/results.jsonl with the "
                       "machine described; charts land in OUT/.")
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
    p.set_defaults(func=bench_main)


def bench_main(args: argparse.Namespace) -> int:
    from .grid import run_bench
    return run_bench(args)
