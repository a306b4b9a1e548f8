"""Benchmark of the ray-tree warper (Lochmann et al. 2014).

  ibr bench raytree [--cases mirror,chrome,crystal,pane] [--size 320x240]
         [--supersample 3] [--move 5 --yaw 3] [--speed-size 1280x720] [--repeats 5]
         [--device cpu|cuda] [--threads 2] [--backend auto|torch|numba] [--out out/bench_raytree]
         [--skip-speed]

Accuracy: for every case (synthetic.raytree_cases.CASES) a ray tree is traced at an old camera and the
exact render at the new camera (moved `--move` cm right and yawed `--yaw` deg); PSNR of our warp
and of the naive diffuse warp (everything warped with the first-hit depth) against it, over all
pixels except the disoccluded ones (first hit not seen by the old camera) and inside the specular
regions (first surface reflective / refractive). Writes a Fig. 7-like side-by-side image
(naive | ground truth | ours) and a Fig. 8-like plot of the gradient-descent energy per step.
Speed: median wall time per frame of decode + warp + fill + composite at `--speed-size`, three
nodes, with a Table 1-like breakdown per stage, and the median CPU time (time.process_time, all
threads of this process) per frame, which is less inflated than wall time on a shared machine;
the naive warp of the same tree is timed interleaved in the same run as a baseline (ratio
ours / naive: comparable between runs on a loaded machine). JSON: OUT/bench_raytree.json.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from ibr_pipeline.errors import InputError


def _argv() -> list[str]:
    """This run's benchmark arguments as typed (what follows `bench raytree` on the command line)."""
    argv = sys.argv[1:]
    for i in range(len(argv) - 1):
        if argv[i:i + 2] == ["bench", "raytree"]:
            return argv[i + 2:]
    return argv


def _size(s: str) -> tuple[int, int]:
    try:
        w, h = (int(x) for x in s.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must be WxH, got {s!r}") from None
    if not (16 <= w <= 4096 and 16 <= h <= 4096):
        raise argparse.ArgumentTypeError(f"size out of range: {s}")
    return w, h


def accuracy(cases, size, supersample, move, yaw, device, out: Path, progress=True,
             figures: Path | None = None, backend: str = "auto") -> list[dict]:
    from ibr_pipeline.io.images import write_image
    from ibr_pipeline.metrics import psnr
    from ibr_pipeline.raytree.decode import DecodeOptions, decode
    from ibr_pipeline.raytree.warp import WarpOptions, naive_warp, warp_decoded
    from ibr_pipeline.synthetic.raytree_cases import make_case

    rows, panels, hist = [], [], None
    for name in cases:
        t0 = time.perf_counter()
        c = make_case(name, *size, move_cm=move, yaw_deg=yaw, supersample=supersample)
        t_trace = time.perf_counter() - t0
        keep = ~c.disoccluded
        spec = c.specular & keep
        row = {"case": name, "size": list(size), "supersample": supersample, "move_cm": move,
               "yaw_deg": yaw, "pixels": int(keep.size), "disoccluded": int(c.disoccluded.sum()),
               "specular_pixels": int(spec.sum()), "trace_s": round(t_trace, 2)}
        for normals in ("reconstruct", "exact"):
            o = WarpOptions(decode=DecodeOptions(normals=normals), backend=backend)
            dec = decode(c.tree, device, o.decode, backend=backend)
            r = warp_decoded(dec, c.new, o, record_history=(normals == "reconstruct"))
            img = np.clip(r.image, 0, 1)
            tag = "" if normals == "reconstruct" else "_exact_normals"
            row["psnr" + tag] = round(psnr(img, c.gt_image, keep), 3)
            row["psnr_specular" + tag] = round(psnr(img, c.gt_image, spec), 3)
            if normals == "reconstruct":
                nv = np.clip(naive_warp(dec, c.new, o), 0, 1)
                row["psnr_naive"] = round(psnr(nv, c.gt_image, keep), 3)
                row["psnr_specular_naive"] = round(psnr(nv, c.gt_image, spec), 3)
                row["specular_gain_db"] = round(row["psnr_specular"] - row["psnr_specular_naive"], 3)
                row["psnr_incl_disoccluded"] = round(psnr(img, c.gt_image), 3)
                dif = keep & ~c.specular   # first surface diffuse in the new view
                row["psnr_diffuse_only"] = round(psnr(img, c.gt_image, dif), 3)
                row["psnr_diffuse_only_naive"] = round(psnr(nv, c.gt_image, dif), 3)
                # specular search: undefined pixels (Delta > eps, §3.4) per node, where they
                # are, and how many the position-domain fill (our extension) leaves to push-pull
                row["undefined_specular"] = [int((g & ~d).sum()) for g, d in zip(r.region[1:], r.defined[1:])]
                row["undefined_split"] = [_undefined_split(g & ~d, c) for g, d in zip(r.region[1:], r.defined[1:])]
                row["unfilled_after_position_fill"] = [int((g & ~d & ~f).sum()) for g, d, f in
                                                       zip(r.region[1:], r.defined[1:], r.filled[1:])]
                # the paper's hole filling alone (push-pull of colours, §3.5), same search
                op = WarpOptions(decode=o.decode, backend=backend,
                                 specular=replace(o.specular, fill_radius=0))
                rp = np.clip(warp_decoded(dec, c.new, op).image, 0, 1)
                row["psnr_specular_pushpull_only"] = round(psnr(rp, c.gt_image, spec), 3)
                row["specular_gain_db_pushpull_only"] = round(row["psnr_specular_pushpull_only"]
                                                              - row["psnr_specular_naive"], 3)
                panels.append(np.concatenate([nv, c.gt_image, img], 1))
                if name == "chrome" or (hist is None and r.history):
                    hist = (name, r.history)
        rows.append(row)
        if progress:
            print(json.dumps(row), flush=True)
    out.mkdir(parents=True, exist_ok=True)
    if panels:  # Fig. 7: naive | ground truth | ours, display gamma 2.2
        fig7 = np.concatenate(panels, 0).clip(0, 1) ** (1 / 2.2)
        write_image(out / "fig7_side_by_side.png", fig7)
        if figures is not None:
            _small_png(fig7, figures / "raytree_fig7.png", [r["case"] for r in rows])
    if hist is not None:
        _plot_energy(hist, out / "fig8_energy.png")
        if figures is not None:
            _plot_energy(hist, figures / "raytree_fig8.png", dpi=80)
    return rows


def _undefined_split(und: np.ndarray, c) -> dict:
    """Where the undefined pixels of a node are (new view, ground-truth masks of the case):
    disoccluded (outside the PSNR masks), not specular in the ground truth (the old tree labels
    the surface specular, the new view sees e.g. the mirror frame), on the specular region's
    rim (within 2 px of its border: sphere silhouette, mirror border) or inside it."""
    spec = c.specular
    pad = np.pad(spec, 2, mode="edge")
    H, W = spec.shape
    inner = np.ones_like(spec)
    for dy in range(5):
        for dx in range(5):
            inner &= pad[dy:dy + H, dx:dx + W]
    kept = und & ~c.disoccluded
    return {"disoccluded": int((und & c.disoccluded).sum()), "not_specular_gt": int((kept & ~spec).sum()),
            "rim_2px": int((kept & spec & ~inner).sum()), "interior": int((kept & spec & inner).sum())}


def _small_png(img: np.ndarray, path: Path, names: list[str]) -> None:
    """Commit-sized Fig. 7: the side-by-side with column / row labels, 80-colour palette PNG (< 300 KB)."""
    from PIL import Image, ImageDraw
    path.parent.mkdir(parents=True, exist_ok=True)
    h, w = img.shape[0] // max(len(names), 1), img.shape[1] // 3
    im = Image.fromarray((img * 255 + 0.5).astype(np.uint8))
    d = ImageDraw.Draw(im)
    for r, name in enumerate(names):
        for col, label in enumerate(("naive", "ground truth", "ours")):
            d.rectangle([col * w, r * h, col * w + 8 + 7 * len(f"{name}: {label}"), r * h + 13], fill=(0, 0, 0))
            d.text((col * w + 4, r * h + 1), f"{name}: {label}", fill=(255, 255, 0))
    im.quantize(80, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE).save(path, optimize=True)


def _plot_energy(hist, path: Path, n: int = 12, dpi: int = 120) -> None:
    """Fig. 8: Delta (degrees) over the gradient-descent steps for sample pixels."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    name, h = hist
    node = sorted(h)[0]
    pix, E = h[node][:2]
    E = np.degrees(E)
    moving = np.nonzero(E[0] > E[-1] + 1e-3)[0]
    pick = moving if len(moving) else np.arange(E.shape[1])
    rng = np.random.default_rng(0)
    pick = rng.choice(pick, size=min(n, len(pick)), replace=False)
    fig, ax = plt.subplots(figsize=(6, 4))
    for j in pick:
        ax.plot(np.arange(E.shape[0]), E[:, j], marker="o", ms=3, lw=1,
                label=f"({pix[j][0]}, {pix[j][1]})")
    ax.plot(np.arange(E.shape[0]), np.median(E, axis=1), "k--", lw=2, label="median, all pixels")
    ax.axhline(1.0, color="r", lw=0.8, ls=":", label="epsilon = 1 deg")
    ax.set_yscale("symlog", linthresh=1e-2)
    ax.set_xlabel("gradient-descent step")
    ax.set_ylabel("Delta (degrees)")
    ax.set_title(f"specular search energy, case {name} (node {node})")
    ax.legend(fontsize=6, ncol=2)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)


def speed_case(size, tree_file: Path | None = None):
    """(tree, new camera) of the chrome case at `size`: traced here, or read from `tree_file`
    (written by --save-speed-tree; lets the speed run happen on a machine without the tracer's
    open3d, e.g. a GPU box). The new camera is the same 5 cm / 3 degree move."""
    from ibr_pipeline.scene import moved_camera
    from ibr_pipeline.synthetic.raytree_cases import make_case
    if tree_file is not None:
        from ibr_pipeline.raytree.encoding import read_tree
        tree = read_tree(tree_file)
        return tree, moved_camera(tree.camera())
    c = make_case("chrome", *size, supersample=1)
    return c.tree, c.new


def speed(size, repeats, device, tree_file: Path | None = None, backend: str = "auto") -> dict:
    """Median per-frame time of decode + warp (ours) and, interleaved in the same run, of the
    naive baseline (decode + first-hit-depth warp of the composited image + push-pull, with the
    same backend: on numba it shares the decode, diffuse-flow and push-pull kernels): their
    ratio is comparable across runs on a loaded machine, the absolute times are not. One warm-up
    frame of each first (numba compiles or loads its cached kernels there)."""
    import torch

    from ibr_pipeline.raytree.backend import numba_available, resolve
    from ibr_pipeline.raytree.decode import decode
    from ibr_pipeline.raytree.warp import WarpOptions, naive_warp, warp

    tree, new = speed_case(size, tree_file)
    size = tree.size
    runs, cpu, base_wall, base_cpu = [], [], [], []
    o = WarpOptions(backend=backend)
    used = resolve(backend, device)

    def baseline():
        naive_warp(decode(tree, device, o.decode, backend=backend), new, o)

    w0 = time.perf_counter()
    warp(tree, new, o, device=device)  # warm-up (numba compile / cache load, allocations, CUDA)
    baseline()
    warmup = time.perf_counter() - w0
    for _ in range(repeats):
        p0 = time.process_time()   # CPU time of this process (all its threads): less affected
        runs.append(warp(tree, new, o, device=device).timings)  # by other users' load
        cpu.append(time.process_time() - p0)
        p0, t0 = time.process_time(), time.perf_counter()
        baseline()
        _sync(device)
        base_cpu.append(time.process_time() - p0)
        base_wall.append(time.perf_counter() - t0)
    keys = list(runs[0])
    med = {k: round(1e3 * float(np.median([r.get(k, 0.0) for r in runs])), 2) for k in keys}
    try:
        load = open("/proc/loadavg").read().split()[:3]
    except OSError:
        load = None
    ours_cpu, ours_wall = float(np.median(cpu)), float(np.median([r["total"] for r in runs]))
    threads = torch.get_num_threads()
    if used == "numba" and numba_available():
        import numba
        threads = numba.get_num_threads()
    return {"size": list(size), "nodes": tree.n_nodes, "device": str(device), "backend": used,
            "threads": threads, "repeats": repeats, "warmup_s": round(warmup, 2),
            "median_ms": med, "total_runs_ms": [round(r["total"] * 1e3, 1) for r in runs],
            "cpu_ms_per_frame_median": round(1e3 * ours_cpu, 1),
            "cpu_runs_ms": [round(x * 1e3, 1) for x in cpu],
            "baseline": f"naive warp (decode + first-hit-depth warp + push-pull), interleaved, {used} backend",
            "baseline_wall_ms_median": round(1e3 * float(np.median(base_wall)), 1),
            "baseline_cpu_ms_median": round(1e3 * float(np.median(base_cpu)), 1),
            "ratio_wall_vs_baseline": round(ours_wall / max(float(np.median(base_wall)), 1e-9), 3),
            "ratio_cpu_vs_baseline": round(ours_cpu / max(float(np.median(base_cpu)), 1e-9), 3),
            "loadavg": load}


def _sync(device) -> None:
    import torch
    if str(device).startswith("cuda"):
        torch.cuda.synchronize()


def add_arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--cases", default="mirror,chrome,crystal,pane",
                    help="comma-separated cases of synthetic.raytree_cases (default all four)")
    ap.add_argument("--scene", choices=("tiny", "mirror_room"), help="shortcut: tiny = mirror case at "
                    "160x120, no supersampling, 320x240 speed run; mirror_room = the defaults")
    ap.add_argument("--size", type=_size, default=(320, 240), help="accuracy size WxH (320x240)")
    ap.add_argument("--supersample", type=int, default=3, help="odd; anti-aliased renders (3)")
    ap.add_argument("--move", type=float, default=5.0, help="cm to the right (5)")
    ap.add_argument("--yaw", type=float, default=3.0, help="degrees (3)")
    ap.add_argument("--speed-size", type=_size, default=(1280, 720), help="speed size WxH (1280x720)")
    ap.add_argument("--repeats", type=int, default=5, help="timed frames (5)")
    ap.add_argument("--device", default="cpu", help="torch device (cpu)")
    ap.add_argument("--threads", type=int, default=2, help="CPU threads of torch and numba (2; 0: default)")
    ap.add_argument("--backend", choices=("auto", "torch", "numba"), default="auto",
                    help="raytree backend (auto: numba on the CPU when installed, else torch)")
    ap.add_argument("--out", type=Path, default=Path("out/bench_raytree"),
                    help="output folder (default out/bench_raytree)")
    ap.add_argument("--skip-speed", action="store_true", help="accuracy only")
    ap.add_argument("--figures", type=Path, help="also write commit-sized raytree_fig7.png / "
                    "raytree_fig8.png here (e.g. docs/figures)")
    ap.add_argument("--skip-accuracy", action="store_true", help="speed only")
    ap.add_argument("--speed-tree", type=Path, help="time this ray tree file instead of tracing the "
                    "chrome case (for machines without open3d)")
    ap.add_argument("--save-speed-tree", type=Path, help="write the traced speed case's tree here")


def main(args: argparse.Namespace) -> int:
    from ibr_pipeline.raytree.backend import passive_omp_wait
    passive_omp_wait()   # before torch loads libgomp (see backend.passive_omp_wait)
    import torch
    if args.threads > 0:
        from ibr_pipeline.raytree.backend import set_threads
        set_threads(args.threads)
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        raise InputError("bench raytree: --device cuda but CUDA is not available")
    if args.scene == "tiny":
        args.cases, args.size, args.supersample, args.speed_size = "mirror", (160, 120), 1, (320, 240)
    cases = [c for c in args.cases.split(",") if c]
    from ibr_pipeline.synthetic.raytree_cases import CASES
    bad = [c for c in cases if c not in CASES]
    if bad or args.supersample < 1 or args.supersample % 2 == 0 or args.repeats < 1:
        raise InputError(f"bench raytree: bad --cases {bad} / --supersample (odd >= 1) / "
                         "--repeats (>= 1)")
    result = {"command": "ibr bench raytree " + " ".join(_argv())}
    if not args.skip_accuracy:
        result["accuracy"] = accuracy(cases, args.size, args.supersample, args.move, args.yaw,
                                      args.device, args.out, figures=args.figures, backend=args.backend)
    if args.save_speed_tree is not None:
        from ibr_pipeline.raytree.encoding import write_tree
        write_tree(args.save_speed_tree, speed_case(args.speed_size)[0])
        print(f"wrote {args.save_speed_tree}")
    if not args.skip_speed:
        result["speed"] = speed(args.speed_size, args.repeats, args.device, args.speed_tree, args.backend)
        print(json.dumps(result["speed"], indent=1))
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "bench_raytree.json").write_text(json.dumps(result, indent=1))
    print(f"wrote {args.out / 'bench_raytree.json'}")
    return 0
