"""`ibr synth-bench`: time scene generation (median of repeats) and append JSON lines."""
from __future__ import annotations

import json
import logging
import os
import platform
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

log = logging.getLogger("ibr_pipeline.synthetic")


def machine() -> dict:
    return {"cpu_count": os.cpu_count(), "platform": platform.platform(),
            "processor": platform.processor() or platform.machine(),
            "python": sys.version.split()[0]}


def run_bench(names, repeats: int = 3, width=None, height=None, views=None, seed: int = 0,
              jobs=None, output: Path | None = None, workdir: Path | None = None) -> list[dict]:
    from .generate import SynthOptions, generate

    results = []
    base = Path(workdir) if workdir else Path(tempfile.mkdtemp(prefix="ibr-synth-bench-"))
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
