"""The benchmark table: every benchmark of `ibr bench NAME`, once, in order.

The benchmarks live outside the product package and use only its public API. Each module named
here defines `add_arguments(parser)` (its flags) and `main(args) -> int` (exit code); its
docstring, which says what it measures, is the description of `ibr bench NAME --help`. This table
imports nothing, so `ibr --help` stays fast: a benchmark's module is imported only when it runs
or its help is asked (ibr_pipeline/commands/bench.py). Figures measured with them are recorded in
docs/BENCHMARKS.md (benchmarks/README.md says which command gives which).
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Benchmark:
    name: str    # `ibr bench NAME`
    module: str  # importable module with add_arguments(parser) and main(args) -> int
    help: str    # one line for `ibr bench --help`


BENCHMARKS: tuple[Benchmark, ...] = (
    Benchmark("pipeline", "benchmarks.pipeline",
              "every stage over a grid of settings (speed vs accuracy), stability sweeps, charts"),
    Benchmark("global_mesh", "benchmarks.global_mesh",
              "global_mesh: F-score of RGB-D fusion and MVS, SfM pose errors, MVS speed"),
    Benchmark("view_depth", "benchmarks.view_depth",
              "view_depth + view_mesh: depth-edge recall, edge-band depth error, mesh fidelity"),
    Benchmark("reflection", "benchmarks.reflection",
              "reflection: plane and layer accuracy, ablation, held-out re-rendering, speed"),
    Benchmark("render", "benchmarks.render",
              "IBR renderer: held-out PSNR/SSIM/FLIP (oracle, single layer, ours) and ms/frame"),
    Benchmark("dsrnet", "benchmarks.dsrnet",
              "DSRNet supersampling: held-out and sequence PSNR/SSIM, flicker, train/infer speed"),
    Benchmark("raytree", "benchmarks.raytree",
              "ray-tree warper: PSNR vs the naive warp on specular cases, ms/frame"),
    Benchmark("real", "benchmarks.real",
              "a real capture, LLFF protocol: held-out PSNR/SSIM/FLIP vs naive warp, nearest image, "
              "published figures; holes, coverage, seconds per stage"),
    Benchmark("speed", "benchmarks.speed",
              "per-stage CPU s per view and per megapixel, frame time, against Xu et al.'s "
              "figures and other code trees (variants) in the same run"),
    Benchmark("viewer", "benchmarks.viewer",
              "browser viewer in headless Chromium: load time, frame time vs the offline renderer, "
              "agreement PSNR on held-out cameras"),
    Benchmark("synth", "benchmarks.synth",
              "synthetic scene generation: median seconds per scene"),
)


def benchmark_by_name(name: str) -> Benchmark:
    for b in BENCHMARKS:
        if b.name == name:
            return b
    raise KeyError(name)
