"""Benchmark of the IBR renderer: held-out accuracy and frame time.

    ibr bench render [--scene tiny|mirror_room | --root DIR] [--ws WS] [--width 640 --height 480]
        [--frames 24] [--repeats 3] [--device cpu|cuda] [--out FILE]

Accuracy (held-out cameras of the scene, against gt/test/images): the oracle representation
(GT depth + GT layers, `render/oracle.py`) with two layers and with one (the single-layer
baseline), and — with `--ws` — the workspace's own representation (`IBRModel.load`, i.e. what
view_mesh/reflection reconstructed). PSNR/SSIM/FLIP overall, inside reflectors (GT materials that
reflect: kr > 0, or glass) and over covered pixels only; hole fraction.
Speed: the fly-through cameras (or the test cameras) resized to --width x --height, rendered in
sequence with hysteresis, median ms per frame over `repeats` passes (view selection, GL passes,
read-back, hole filling, composition all included) for the oracle (`speed`) and, with `--ws`, for
the workspace's meshes (`speed_ours`), with their mean triangles per view. `--device cuda` only
checks that the GL renderer is an NVIDIA one (EGL picks the GPU); the code path is the same.
"""
from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np

from ibr_pipeline.errors import InputError


def _scene_root(name: str, cache: Path) -> Path:
    from .common import SAMPLE, tiny_scene
    return SAMPLE if name == "mirror_room" else tiny_scene(cache / name)


def accuracy(model, root: Path, with_flip: bool = True) -> dict:
    from ibr_pipeline import metrics
    from ibr_pipeline.io.images import read_image
    from ibr_pipeline.scene import cameras_from_json
    from ibr_pipeline.synthetic.materials import reflecting_indices
    test = cameras_from_json(root / "gt" / "test_cameras.json")
    mats = json.loads((root / "gt" / "scene.json").read_text())["materials"]
    kinds = reflecting_indices(mats)
    rows = []
    for name, cam in test.items():
        ref = read_image(root / "gt" / "test" / "images" / name)
        with np.load(root / "gt" / "test" / "geom" / f"{Path(name).stem}.npz") as z:
            mask = np.isin(z["material"], kinds)
        f = model.render(cam)
        r = metrics.all_metrics(ref, f.color, mask if mask.any() else None, with_flip=with_flip)
        r["psnr_covered"] = metrics.psnr(ref, f.color, f.covered)
        r["holes"] = float(1 - f.covered.mean())
        rows.append(r)
    from ibr_pipeline.stages.evaluate import mean_metrics
    out = mean_metrics(rows)
    out["views"] = len(rows)
    return out


def speed(model, cams: list, repeats: int) -> dict:
    runs = []
    for _ in range(repeats):
        prev, ms, parts = None, [], []
        for cam in cams:
            f = model.render(cam, previous=prev)
            prev = f
            ms.append(f.ms)
            parts.append([f.timings["select_ms"], f.timings["gl_ms"], f.timings["post_ms"],
                          len(f.selected)])
        runs.append((ms, parts))
    ms = np.concatenate([np.array(r[0]) for r in runs[1:] or runs])  # first pass warms up GL
    parts = np.concatenate([np.array(r[1]) for r in runs[1:] or runs])
    return {"median_ms": float(np.median(ms)), "p90_ms": float(np.percentile(ms, 90)),
            "frames": len(cams), "repeats": repeats, "median_select_ms": float(np.median(parts[:, 0])),
            "median_gl_ms": float(np.median(parts[:, 1])), "median_post_ms": float(np.median(parts[:, 2])),
            "mean_selected_views": float(parts[:, 3].mean())}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene", choices=("tiny", "mirror_room"), default="mirror_room",
                   help="tiny: generated in --cache; mirror_room: sample_data/ (default)")
    p.add_argument("--root", type=Path, help="a synthetic scene folder (`ibr synth` output) to use "
                   "instead of --scene, e.g. a 120-view mirror_room")
    p.add_argument("--ws", type=Path, help="also score this workspace's representation")
    p.add_argument("--width", type=int, default=640, help="frame width of the speed path (640)")
    p.add_argument("--height", type=int, default=480, help="frame height of the speed path (480)")
    p.add_argument("--frames", type=int, default=24, help="frames of the speed path")
    p.add_argument("--repeats", type=int, default=3, help="passes over the speed path (3)")
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu",
                   help="cuda: check that the GL renderer is an NVIDIA one")
    p.add_argument("--no-flip", action="store_true", help="skip the FLIP metric (slow on CPU)")
    p.add_argument("--cache", type=Path, default=Path("out/bench_render"),
                   help="where generated scenes and the JSON go (default out/bench_render)")
    p.add_argument("--out", type=Path, help="JSON output (default out/bench_render/render_<scene>.json)")


def main(a: argparse.Namespace) -> int:
    if a.width < 16 or a.height < 16 or a.frames < 1 or a.repeats < 1:
        raise InputError("bench render: --width/--height >= 16, --frames/--repeats >= 1")
    from ibr_pipeline.render.gl import renderer_name
    from ibr_pipeline.render.oracle import GroundTruth
    from ibr_pipeline.render.video import interpolate_path
    from ibr_pipeline.scene import cameras_from_json

    gl_name = renderer_name()
    if a.device == "cuda" and "nvidia" not in gl_name.lower():
        raise InputError(f"bench render: --device cuda but the GL renderer is {gl_name}")
    root = a.root if a.root is not None else _scene_root(a.scene, a.cache)
    gt = GroundTruth(root)
    t0 = time.perf_counter()
    two = gt.model(layers=True)
    build_s = time.perf_counter() - t0
    one = gt.model(layers=False)
    res = {"scene": a.scene if a.root is None else a.root.name, "root": str(root), "renderer": gl_name,
           "machine": platform.node(),
           "python": platform.python_version(), "oracle_build_s": build_s,
           "accuracy": {"oracle": accuracy(two, root, not a.no_flip),
                        "single_layer": accuracy(one, root, not a.no_flip)}}
    fly = root / "gt" / "flythrough_cameras.json"
    base = list(cameras_from_json(fly).values()) if fly.is_file() else \
        list(cameras_from_json(root / "gt" / "test_cameras.json").values())
    path = interpolate_path(base + base[:1], a.frames) if len(base) >= 2 else base
    cams = [c.resized(a.width, a.height) for c in path]
    if a.ws is not None:
        from ibr_pipeline.render.ibr import IBRModel
        from ibr_pipeline.workspace import Workspace
        ours = IBRModel.load(Workspace(a.ws), layers=True)
        res["accuracy"]["ours"] = accuracy(ours, root, not a.no_flip)
        # the frame time with the reconstructed meshes (their size is view_mesh's budget, not
        # the oracle's): the same path, timed right after the oracle's below
        res["speed_ours"] = {"size": [a.width, a.height], **speed(ours, cams, a.repeats),
                             "mean_triangles_per_view": _mean_triangles(ours)}
        ours.release()
    res["speed"] = {"size": [a.width, a.height], **speed(two, cams, a.repeats),
                    "mean_triangles_per_view": _mean_triangles(two)}
    acc = res["accuracy"]
    res["targets"] = {
        "reflector_gain_db (oracle vs single)": _diff(acc["oracle"], acc["single_layer"], "psnr_mask"),
        "oracle_gap_db (oracle - ours)": _diff(acc["oracle"], acc.get("ours"), "psnr"),
    }
    two.release()
    one.release()
    out = a.out or a.cache / f"render_{res['scene']}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=1))
    print(json.dumps(res, indent=1))
    return 0


def _mean_triangles(model) -> dict:
    """Mean triangles per view of each layer (llvmpipe's frame time grows with them)."""
    out = {}
    for i in (0, 1):
        n = [len(v.layers[i].faces) for v in model.views if v.layers[i] is not None]
        out[f"layer{i}"] = float(np.mean(n)) if n else 0.0
    return out


def _diff(a, b, k):
    if not a or not b or a.get(k) is None or b.get(k) is None:
        return None
    return a[k] - b[k]
