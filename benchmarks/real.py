"""A real capture under the LLFF/NeRF protocol: every 8th image held out, SfM on all images, the
reconstruction on the rest, the held-out photographs as ground truth.

    ibr bench real --input DIR [--name NAME] [--holdout 8] [--set STAGE.FIELD=VALUE ...] [--out out/bench_real]

Runs the default pipeline (`ibr run`, only `poses.holdout_every` set, plus any `--set`) on the
folder and records: held-out PSNR / SSIM / FLIP on the stored (sRGB) pixel values for ours, the
single-layer renderer, the naive warp of the global mesh and the nearest training image; the
fraction of each held-out frame left to hole filling; how much of each view the global mesh
covers and how much depth completion added; the scene frame and SfM statistics; seconds per stage
and end to end; and the published figures of other methods on the same scene when known
(`PUBLISHED`, with their source and resolution: compare only at the same resolution). One JSON
line per run is appended to OUT/results.jsonl; OUT/NAME/result.json and OUT/NAME/heldout.png
(the evaluate stage's side-by-sides of the first held-out views) hold the latest.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from ibr_pipeline.errors import InputError

# Published held-out figures (LLFF protocol: every 8th image held out). Values as printed in the
# papers' per-scene tables; `resolution` is the image size they were measured at.
PUBLISHED = {
    "llff_room": [
        {"method": "NeRF", "psnr": 32.70, "ssim": 0.948, "resolution": "1008x756",
         "source": "Mildenhall et al. 2020, NeRF, supplementary per-scene table (LLFF data)"},
        {"method": "LLFF", "psnr": 28.42, "ssim": 0.932, "resolution": "1008x756",
         "source": "same table (Mildenhall et al. 2019, Local Light Field Fusion)"},
    ],
    "llff_horns": [
        {"method": "NeRF", "psnr": 27.45, "ssim": 0.828, "resolution": "1008x756",
         "source": "Mildenhall et al. 2020, NeRF, supplementary per-scene table (LLFF data)"},
        {"method": "LLFF", "psnr": 24.70, "ssim": 0.840, "resolution": "1008x756",
         "source": "same table (Mildenhall et al. 2019, Local Light Field Fusion)"},
    ],
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--input", type=Path, required=True, help="the capture: a folder of photos "
                   "(images/ or top level), optionally with a COLMAP sparse/0")
    p.add_argument("--name", help="name of the capture in the results (default: the folder name; "
                   f"known published figures: {', '.join(PUBLISHED)})")
    p.add_argument("--holdout", type=int, default=8, help="hold out every N-th image (default 8)")
    p.add_argument("--set", action="append", default=[], metavar="STAGE.FIELD=VALUE",
                   help="a pipeline setting (repeatable), as for `ibr run`")
    p.add_argument("--out", type=Path, default=Path("out/bench_real"), help="output folder")
    p.add_argument("--jobs", "-j", type=int, default=2, help="worker processes per stage (default 2)")
    p.add_argument("--fresh", action="store_true", help="delete the benchmark's workspace first "
                   "(default: resume it; finished stages are not redone)")


def _stage_seconds(ws: Path) -> dict:
    """{stage: seconds of its last run that did work} from the workspace's run log."""
    out = {}
    p = ws / ".ibr" / "runs.jsonl"
    for line in p.read_text().splitlines() if p.is_file() else []:
        for s in json.loads(line).get("stages", []):
            if s.get("result") == "ran":
                out[s["stage"]] = s["seconds"]
    return out


def _coverage(ws: Path) -> dict:
    import numpy as np
    reps = [json.loads(p.read_text()) for p in sorted((ws / "views").glob("*/depth_report.json"))]
    g = json.loads((ws / "global" / "report.json").read_text())
    if not reps:
        return {"mvs_valid_fraction": g.get("mvs_valid_fraction")}
    return {"mvs_valid_fraction": g.get("mvs_valid_fraction"),
            "g_empty_fraction": float(np.mean([r.get("empty_in_g", 0.0) for r in reps])),
            # view_depth step 1b: what the view took from its own MVS depth in front of G
            "mvs_in_front_fraction": float(np.mean([r.get("mvs_in_front", 0) / np.prod(r["size"])
                                                    for r in reps])),
            "depth_valid_fraction": float(np.mean([r["valid_fraction"] for r in reps])),
            "depth_valid_min": float(np.min([r["valid_fraction"] for r in reps]))}


def _montage(ws: Path, dst: Path, n: int = 3) -> None:
    import numpy as np

    from ibr_pipeline.io.images import read_image, write_image
    frames = sorted((ws / "eval" / "side_by_side").glob("*.png"))[:n]
    if frames:
        write_image(dst, np.concatenate([read_image(f) for f in frames], 0))


def main(args: argparse.Namespace) -> int:
    import shutil

    from ibr_pipeline.cli import main as ibr

    from .common import logger, machine
    log = logger()
    src = args.input.resolve()
    if not src.is_dir():
        raise InputError(f"--input {args.input}: not a folder")
    if args.holdout < 2:
        raise InputError(f"--holdout must be at least 2, got {args.holdout}")
    name = args.name or src.name
    out = args.out / name
    ws = out / "ws"
    if args.fresh and ws.exists():
        shutil.rmtree(ws)
    out.mkdir(parents=True, exist_ok=True)
    cmd = ["run", str(ws), "--input", str(src), "--jobs", str(args.jobs),
           "--set", f"poses.holdout_every={args.holdout}"]
    for s in args.set:
        cmd += ["--set", s]
    log.info("bench real: ibr %s", " ".join(cmd))
    t0 = time.perf_counter()
    code = ibr(cmd)
    wall = time.perf_counter() - t0
    if code != 0:
        log.error("bench real: the pipeline failed (exit %d); the workspace is %s", code, ws)
        return code
    metrics = json.loads((ws / "eval" / "metrics.json").read_text())
    poses = json.loads((ws / "global" / "poses.json").read_text())
    s = metrics["summary"]
    first = json.loads((ws / "renders" / "test" / "timings.json").read_text())
    result = {
        "bench": "real", "name": name, "input": str(src), "settings": args.set,
        "holdout_every": args.holdout, "size": first.get("size"),
        "images": poses["counts"]["images"], "training": poses["counts"]["training"],
        "heldout": poses["counts"]["heldout"], "test_source": metrics["source"],
        "scene_frame": {"units": poses["units"], "scale": poses["scale"],
                        "median_scene_depth": poses.get("median_scene_depth"),
                        "method": poses["alignment"].get("method")},
        "sfm": poses.get("sfm"), "path_jumps": poses.get("path_jumps"),
        "heldout_metrics": {m: {k: s.get(f"{m}_{k}" if m != "ours" else k)
                                for k in ("psnr", "ssim", "flip", "psnr_mask", "ssim_mask", "flip_mask")}
                            for m in ("ours", "single", "naive", "nearest")},
        "reflector_pixels": [v.get("reflector_pixels", 0) for v in metrics["per_view"]],
        "holes": s.get("holes"), "coverage": _coverage(ws),
        "stage_seconds": _stage_seconds(ws), "wall_s": wall,
        "published": PUBLISHED.get(name, []), "machine": machine(),
        "finished": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }
    (out / "result.json").write_text(json.dumps(result, indent=1))
    with open(args.out / "results.jsonl", "a") as f:
        f.write(json.dumps(result) + "\n")
    _montage(ws, out / "heldout.png")
    hm = result["heldout_metrics"]
    fmt = lambda v: "n/a" if v is None else f"{v:.2f}"  # noqa: E731
    print(f"{name}: {result['heldout']} held-out of {result['images']} at "
          f"{'x'.join(map(str, result['size'] or []))}, scene frame {poses['units']}")
    for m in ("ours", "single", "naive", "nearest"):
        print(f"  {m:8s} PSNR {fmt(hm[m]['psnr'])} dB  SSIM {fmt(hm[m]['ssim'])}  FLIP {fmt(hm[m]['flip'])}"
              + (f"  | inside reflectors {fmt(hm[m]['psnr_mask'])} dB" if hm[m]["psnr_mask"] is not None
                 else ""))
    for p in result["published"]:
        print(f"  {p['method']:8s} PSNR {p['psnr']:.2f} dB  SSIM {p['ssim']:.3f}  at {p['resolution']} "
              f"({p['source']})")
    cov = result["coverage"]
    print(f"  holes {100 * (result['holes'] or 0):.1f} %, global mesh empty in "
          f"{100 * cov.get('g_empty_fraction', 0):.1f} % of each view (MVS in front of it on "
          f"{100 * cov.get('mvs_in_front_fraction', 0):.1f} %), depth on "
          f"{100 * cov.get('depth_valid_fraction', 0):.1f} % after completion")
    print("  seconds: " + ", ".join(f"{k} {v:.0f}" for k, v in result["stage_seconds"].items())
          + f"; end to end {wall:.0f} s (this run)")
    print(f"  {out / 'result.json'}, {out / 'heldout.png'}")
    return 0
