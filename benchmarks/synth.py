"""Synthetic scene generation: seconds per scene (median of repeats), appended as JSON lines.

Each run generates the whole scene (capture views, held-out views, fly-through, ground-truth
layers, ray trees) into a scratch folder, as `ibr synth NAME OUT` does, and removes it. One line
per scene: its size, the median and every run's seconds, and the machine.
"""
from __future__ import annotations

import argparse
import json
import shutil
import statistics
import tempfile
import time
from pathlib import Path

from ibr_pipeline.errors import InputError

from .common import logger, machine

log = logger()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("names", metavar="NAME", nargs="*", default=["tiny", "mirror_room"],
                        help="scenes to time (default: tiny mirror_room); each at its default "
                             "size unless --width/--height/--views are given")
    parser.add_argument("--repeats", type=int, default=3,
                        help="runs per scene; the median is reported (default 3)")
    parser.add_argument("--width", type=int, default=None, help="override the image width")
    parser.add_argument("--height", type=int, default=None, help="override the image height")
    parser.add_argument("--views", type=int, default=None, help="override the number of views")
    parser.add_argument("--seed", type=int, default=0, help="scene seed (default 0)")
    parser.add_argument("--jobs", type=int, default=None,
                        help="worker processes (default: min(2, CPU count))")
    parser.add_argument("--output", type=Path, default=Path("synth_bench.jsonl"),
                        help="JSON-lines file the results are appended to (default synth_bench.jsonl)")
    parser.add_argument("--workdir", type=Path, default=None,
                        help="where scenes are generated (default: a temporary folder, removed)")


def main(args: argparse.Namespace) -> int:
    if args.repeats < 1:
        raise InputError(f"--repeats must be >= 1, got {args.repeats}")
    from ibr_pipeline.synthetic.scenes import SCENES
    bad = [n for n in args.names if n not in SCENES]
    if bad:
        raise InputError(f"NAME: unknown scene(s) {bad} (choose from {', '.join(SCENES)})")
    run_bench(args.names, repeats=args.repeats, width=args.width, height=args.height,
              views=args.views, seed=args.seed, jobs=args.jobs, output=args.output,
              workdir=args.workdir)
    return 0


def run_bench(names, repeats: int = 3, width=None, height=None, views=None, seed: int = 0,
              jobs=None, output: Path | None = None, workdir: Path | None = None) -> list[dict]:
    from ibr_pipeline.synthetic.generate import SynthOptions, generate

    results = []
    base = Path(workdir) if workdir else Path(tempfile.mkdtemp(prefix="ibr-bench-synth-"))
    try:
        for name in names:
            opts = SynthOptions(name, seed=seed, width=width, height=height, views=views, jobs=jobs,
                                progress=False).resolved()
            times = []
            for r in range(repeats):
                out = base / f"{name}-{r}"
                shutil.rmtree(out, ignore_errors=True)
                t0 = time.perf_counter()
                generate(opts, out)
                times.append(time.perf_counter() - t0)
                log.info("%s run %d: %.1f s", name, r + 1, times[-1])
                shutil.rmtree(out, ignore_errors=True)
            rec = {"bench": "synth", "scene": name, "width": opts.width, "height": opts.height,
                   "views": opts.views, "test_views": opts.test_views,
                   "flythrough": opts.flythrough, "gt_layers": opts.gt_layers, "jobs": opts.jobs,
                   "repeats": repeats, "median_s": round(statistics.median(times), 2),
                   "times_s": [round(t, 2) for t in times], "machine": machine(),
                   "date": time.strftime("%Y-%m-%d")}
            results.append(rec)
            if output is not None:
                with open(output, "a") as f:
                    f.write(json.dumps(rec) + "\n")
    finally:
        if workdir is None:
            shutil.rmtree(base, ignore_errors=True)
    print(f"{'scene':<12} {'size':>9} {'views':>5} {'+test':>5} {'+fly':>5} {'median s':>9}  runs")
    for r in results:
        print(f"{r['scene']:<12} {r['width']}x{r['height']:<5} {r['views']:>5} {r['test_views']:>5} "
              f"{r['flythrough']:>5} {r['median_s']:>9.1f}  {', '.join(f'{t:.1f}' for t in r['times_s'])}")
    return results
