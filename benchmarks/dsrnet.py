"""Benchmark of DSRNet (Xu et al. §5.2, §6.2): accuracy against synthetic ground truth and speed.

    ibr bench dsrnet [--scene tiny|mirror_room | --folder SYNTH_DIR]
        [--steps 1200] [--time-budget 0] [--preset cpu|paper] [--device cpu|cuda|auto]
        [--no-ablation] [--sequence 12] [--repeats 5] [--out bench_dsrnet.json]
        [--workspace WS [--model WS/nn/dsrnet.pt [--model-no-mvr WS2/nn/dsrnet.pt]]]
        [--capture-fraction 0.5] [--self-ensemble]

Data: the STAND-IN low-res renderer (nn/data.py: ground truth + IBR-like artefacts), so the figures
say what the network does with blur/misalignment/holes, not with real IBR renders. With
`--workspace WS` (a workspace of a synthetic input after view_mesh, + reflection) the real
leave-one-out renders of the IBR renderer (`render.ibr.IBRModel`) are used instead, for training,
validation, the full-resolution baseline and the dense sequence (ground truth from the tracer).
`--model FILE` (with `--workspace`) trains nothing: it measures a trained network, e.g. the stage's
own `WS/nn/dsrnet.pt`, on the same held-out views (the stage's split) against the full-resolution
render; `--model-no-mvr FILE` adds a network trained separately with `supersample.use_mvr=false`
(the Table 3 ablation on real renders, same held-out views and sequence). `--capture-fraction`
mixes capture pairs into training (`data.capture_pairs`, docs/DSRNET.md). `--self-ensemble`
also measures every net as NAME_self_ensemble (`nn.infer.run_network`: the mean of the net on the
frame and on its mirror image) and its inference time.

Measured:
* held-out capture views (the 10 % split, never trained on): PSNR/SSIM of DSRNet with MVR,
  DSRNet without MVR (Table 3 ablation, trained separately with the same steps), bilinear and
  bicubic upsampling of the same half-resolution input, and the full-resolution stand-in render
  (same artefacts, no DSRNet);
* a dense held-out sequence (`--sequence N` consecutive frames of the synthetic scene's inner loop,
  traced here; never trained on): the same metrics per frame, and flicker = mean over frames of
  |(O_t − O_{t−1}) − (G_t − G_{t−1})| (temporal change that the ground truth does not have);
* speed: training steps/s and total, inference per frame at 2x the input size given by
  `--infer-size` (default 640x480 output), median of `--repeats`.
"""
from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from ibr_pipeline.errors import InputError


def _scene_folder(args) -> Path:
    from .common import SAMPLE, tiny_scene
    if args.folder:
        return Path(args.folder)
    if args.scene == "mirror_room":
        return SAMPLE
    return tiny_scene(Path(tempfile.mkdtemp(prefix="bench_dsrnet_")) / "tiny")


def dense_sequence(folder: Path, n: int):
    """n consecutive frames of the scene's inner loop (`paths.inner_loop_path`: not on the capture path), traced
    with the synthetic ray tracer: [(name, camera, image, depth)]."""
    from ibr_pipeline.synthetic.paths import inner_loop_path
    from ibr_pipeline.synthetic.scenes import build_world
    from ibr_pipeline.synthetic.tracer import Tracer

    meta = json.loads((folder / "gt/scene.json").read_text())
    o = meta["options"]
    world = build_world(o["name"], o["seed"])
    # the inner loop sampled densely (96 frames, ~3.75 degrees apart): consecutive frames as a
    # viewer would see them; the loop is not the capture path (docs/SYNTHETIC.md)
    cams = inner_loop_path(world, 96, o["width"], o["height"], o["seed"], every=1)
    tracer = Tracer(world)
    out = []
    for i, cam in enumerate(cams[1:n + 1]):  # frames 1..n (as in the figures measured so far)
        r = tracer.trace(cam)
        img = np.clip(np.round(r["image"] * 255) / 255, 0, 1).astype(np.float32)
        out.append((f"seq_{i:03d}.png", cam, img, r["depth"].astype(np.float32)))
    return out


def _metrics(gt, img):
    from ibr_pipeline import metrics
    return metrics.psnr(gt, img), metrics.ssim(gt, img)


def _run_model(model, sample, device, self_ensemble: bool = False):
    import torch

    from ibr_pipeline.nn.data import to_tensors
    from ibr_pipeline.nn.infer import run_network
    b = {k: v.to(device) for k, v in to_tensors([sample]).items()}
    with torch.no_grad():
        y = run_network(model, b["cur"], b["depth"], b["prev"], b["depth_prev"], b["flow"],
                        self_ensemble)
    return y.clamp(0, 1)[0].permute(1, 2, 0).cpu().numpy()


def evaluate_methods(samples, models: dict, full_res: dict, device, scale: int,
                     self_ensemble: bool = False) -> dict:
    """Per method: mean PSNR/SSIM over samples, plus per-frame outputs for flicker. With
    `self_ensemble`, every model is also measured as NAME_self_ensemble (nn.infer.run_network)."""
    from ibr_pipeline.nn.infer import upsample
    res, outs = {}, {}
    for s in samples:
        cands = {name: _run_model(m, s, device) for name, m in models.items()}
        if self_ensemble:
            cands.update({f"{name}_self_ensemble": _run_model(m, s, device, True)
                          for name, m in models.items()})
        cands["bilinear"] = upsample(s.cur.color, scale, "bilinear")
        cands["bicubic"] = upsample(s.cur.color, scale, "bicubic")
        if s.name in full_res:
            cands["full_res_render"] = full_res[s.name]
        for k, img in cands.items():
            p, q = _metrics(s.target, img)
            res.setdefault(k, {"psnr": [], "ssim": []})
            res[k]["psnr"].append(p)
            res[k]["ssim"].append(q)
            outs.setdefault(k, []).append(img)
    summary = {k: {"psnr": float(np.mean(v["psnr"])), "ssim": float(np.mean(v["ssim"]))}
               for k, v in res.items()}
    return {"mean": summary, "frames": len(samples)}, outs


def error_breakdown(samples, outs: dict, full_depth: dict, scale: int) -> dict:
    """Where each method loses against the ground truth, pooled over samples:
    PSNR of the mean squared error per region and per frequency band, and how good the inputs are.

    Regions of the full-resolution image: `depth_edges` (5x5 around a > 3 % jump of the
    full-resolution render's depth), `holes` (no depth in that render), `textured` (top 20 % of the
    ground truth's gradient magnitude, off depth edges), `flat` (the rest). Bands: `low` = both
    images blurred with a Gaussian of sigma 2 px, `high` = the remainder. `bicubic_of_gt` is the
    bicubic upsampling of the area-downsampled ground truth (what an ideal half-resolution input
    gives without a network). `input_psnr`: the half-resolution render and the area-downsampled
    full-resolution render, both against the area-downsampled ground truth."""
    import cv2

    from ibr_pipeline.nn.infer import upsample

    def area(img):
        h, w = img.shape[:2]
        return cv2.resize(img, (w // scale, h // scale), interpolation=cv2.INTER_AREA)

    blur = lambda x: cv2.GaussianBlur(x, (0, 0), 2.0)  # noqa: E731
    sq = {}  # method -> key -> [sum of squared error, pixel count]
    inp = {"render_half_res": [], "full_res_render_downsampled": []}
    outs = dict(outs)
    outs["bicubic_of_gt"] = [upsample(area(s.target), scale, "bicubic") for s in samples]
    for i, s in enumerate(samples):
        g = s.target
        gray = cv2.cvtColor(g, cv2.COLOR_RGB2GRAY)
        grad = np.hypot(cv2.Sobel(gray, cv2.CV_32F, 1, 0), cv2.Sobel(gray, cv2.CV_32F, 0, 1))
        regions = {"all": np.ones(gray.shape, bool)}
        d = full_depth.get(s.name)
        if d is not None:
            dd = np.where(d > 0, d, np.nan)
            jump = np.zeros(gray.shape, bool)
            with np.errstate(invalid="ignore"):
                jump[:, 1:] |= np.abs(np.diff(dd, axis=1)) > 0.03 * dd[:, 1:]
                jump[1:] |= np.abs(np.diff(dd, axis=0)) > 0.03 * dd[1:]
            edges = cv2.dilate(jump.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
            regions["depth_edges"], regions["holes"] = edges, d <= 0
        else:
            edges = np.zeros(gray.shape, bool)
        regions["textured"] = (grad > np.percentile(grad, 80)) & ~edges
        regions["flat"] = ~regions["textured"] & ~edges
        for k, imgs in outs.items():
            if len(imgs) != len(samples):
                continue
            e = ((imgs[i] - g) ** 2).mean(-1)
            acc = sq.setdefault(k, {})
            for r, m in regions.items():
                a = acc.setdefault(r, [0.0, 0])
                a[0] += float(e[m].sum())
                a[1] += int(m.sum())
            lo = ((blur(imgs[i]) - blur(g)) ** 2).mean()
            hi = (((imgs[i] - blur(imgs[i])) - (g - blur(g))) ** 2).mean()
            for r, v in (("low_band", lo), ("high_band", hi)):
                a = acc.setdefault(r, [0.0, 0])
                a[0] += float(v) * e.size
                a[1] += e.size
        ref = area(g)
        inp["render_half_res"].append(float(((s.cur.color - ref) ** 2).mean()))
        if "full_res_render" in outs:
            inp["full_res_render_downsampled"].append(
                float(((area(outs["full_res_render"][i]) - ref) ** 2).mean()))
    to_db = lambda m: float(-10 * np.log10(max(m, 1e-12)))  # noqa: E731
    out = {k: {r: to_db(a[0] / max(a[1], 1)) for r, a in acc.items()} for k, acc in sq.items()}
    first = next(iter(sq.values()), {})
    out["pixel_share"] = {r: a[1] / max(first["all"][1], 1) for r, a in first.items()
                         if not r.endswith("_band")}
    out["input_psnr"] = {k: to_db(float(np.mean(v))) for k, v in inp.items() if v}
    return out


def flicker(outputs: list, gts: list) -> float:
    """Mean |(O_t − O_{t−1}) − (G_t − G_{t−1})| over consecutive frames."""
    e = [np.abs((outputs[t] - outputs[t - 1]) - (gts[t] - gts[t - 1])).mean()
         for t in range(1, len(outputs))]
    return float(np.mean(e)) if e else float("nan")


def add_arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--scene", choices=("tiny", "mirror_room"), default="mirror_room",
                    help="tiny: generated in a temporary folder; mirror_room: sample_data/ (default)")
    ap.add_argument("--folder", help="a synthetic scene folder (overrides --scene)")
    ap.add_argument("--workspace", help="a workspace after view_mesh (+ reflection) of a synthetic "
                    "input: use the real leave-one-out renders of the IBR renderer instead of the "
                    "stand-in")
    ap.add_argument("--model", help="a trained DSRNet file (with --workspace): measure it, train "
                    "nothing (no ablation)")
    ap.add_argument("--model-no-mvr", help="with --model: a trained W/O MVR DSRNet file (the stage "
                    "with use_mvr=false), measured beside it")
    ap.add_argument("--capture-fraction", type=float, default=0.0,
                    help="share of training crops from capture pairs (0 = render pairs only)")
    ap.add_argument("--preset", choices=("cpu", "paper"), default="cpu", help="network size (cpu)")
    ap.add_argument("--steps", type=int, default=1200, help="training steps (1200)")
    ap.add_argument("--time-budget", type=float, default=0.0, help="training budget, s (0 = none)")
    ap.add_argument("--lr", type=float, default=1e-3, help="learning rate (1e-3)")
    ap.add_argument("--crop", type=int, default=48, help="training crop size, px (48)")
    ap.add_argument("--batch", type=int, default=4, help="training batch size (4)")
    ap.add_argument("--device", choices=("auto", "cpu", "cuda"), default="cpu", help="torch device (cpu)")
    ap.add_argument("--threads", type=int, default=0, help="CPU threads of torch (0: default)")
    ap.add_argument("--no-ablation", action="store_true", help="skip the W/O MVR training")
    ap.add_argument("--sequence", type=int, default=12, help="dense held-out frames (0 = none)")
    ap.add_argument("--repeats", type=int, default=5, help="runs of the inference timing (5)")
    ap.add_argument("--infer-size", default="640x480", help="output size of the speed test")
    ap.add_argument("--self-ensemble", action="store_true",
                    help="also measure every net with the mirror-image self-ensemble (2 passes)")
    ap.add_argument("--seed", type=int, default=0, help="stand-in renderer and training seed (0)")
    ap.add_argument("--out", default="bench_dsrnet.json", help="JSON result (default bench_dsrnet.json)")


def main(args: argparse.Namespace) -> int:
    if args.model and not args.workspace:
        raise InputError("bench dsrnet: --model needs --workspace")
    if args.model_no_mvr and not args.model:
        raise InputError("bench dsrnet: --model-no-mvr needs --model")
    if args.steps < 1 or args.repeats < 1 or args.sequence < 0:
        raise InputError("bench dsrnet: --steps/--repeats must be >= 1, --sequence >= 0")
    import torch

    from ibr_pipeline.nn.data import (capture_pairs, low_res_camera, make_sample, render_low_res,
                                      sequence_pairs, split_views)
    from ibr_pipeline.nn.infer import SuperSampler
    from ibr_pipeline.nn.model import (count_parameters, cpu_threads, preset, resolve_device,
                                       torch_threads)
    from ibr_pipeline.nn.train import TrainOptions, train
    from ibr_pipeline.render.low_res import StandInRenderer

    device = resolve_device(args.device)
    t0 = time.perf_counter()
    if args.workspace:
        from ibr_pipeline.io.images import read_image
        from ibr_pipeline.layout import registered_cameras
        from ibr_pipeline.render.low_res import IBRRenderer
        from ibr_pipeline.workspace import Workspace
        ws = Workspace(args.workspace)
        folder = ws.input_root
        renderer = IBRRenderer(ws)
        scene = ws.scene()
        cams = registered_cameras(ws)
        names = [n for n in scene.names if n in cams]
        gt_of = {n: read_image(ws.path(scene.view(n).image)) for n in names}
        renderer.gt_image = gt_of.__getitem__
        renderer.extra = {}
    else:
        folder = _scene_folder(args)
        renderer = StandInRenderer(folder, seed=args.seed)
        cams = renderer.cameras()
        names = list(cams)
    scale = 2
    frames = render_low_res(names, cams, renderer, scale)
    train_names, val_names = split_views(names)
    gt = {n: renderer.gt_image(n) for n in names}
    tr_pairs = sequence_pairs(train_names, train_names)
    tr = [make_sample(c, p, frames, gt[c]) for c, p in tr_pairs]
    cap = capture_pairs(tr_pairs, frames, gt) if args.capture_fraction > 0 else []
    va = [make_sample(c, p, frames, gt[c]) for c, p in sequence_pairs(names, val_names)
          if p not in val_names]
    full_renders = {n: renderer(n, cams[n]) for n in val_names}
    full_res = {n: c for n, (c, _) in full_renders.items()}
    full_depth = {n: d for n, (_, d) in full_renders.items()}
    report = {"scene": str(folder), "renderer": "ibr" if args.workspace else "standin", "preset": args.preset,
              "device": str(device), "train_pairs": len(tr), "val_views": val_names,
              "capture_pairs": len(cap), "capture_fraction": args.capture_fraction,
              "data_seconds": time.perf_counter() - t0}
    opts = TrainOptions(steps=args.steps, batch=args.batch,
                        crop=args.crop, lr=args.lr, seed=args.seed, device=str(device),
                        threads=args.threads, checkpoint_every=max(args.steps // 6, 1),
                        progress=False, capture_fraction=args.capture_fraction)
    models, trainings = {}, {}
    variants = [("dsrnet", True)] + ([] if args.no_ablation else [("dsrnet_no_mvr", False)])
    if args.model:
        from ibr_pipeline.nn.model import load_model
        models["dsrnet"] = load_model(Path(args.model), device)
        report["model"] = str(args.model)
        if args.model_no_mvr:
            models["dsrnet_no_mvr"] = load_model(Path(args.model_no_mvr), device)
            if models["dsrnet_no_mvr"].mvr is not None:
                raise InputError(f"bench dsrnet: {args.model_no_mvr} has MVR (train it with "
                                 "supersample.use_mvr=false)")
            report["model_no_mvr"] = str(args.model_no_mvr)
        variants = []
    for key, mvr in variants:
        cfg = preset(args.preset, use_mvr=mvr)
        r = train(cfg, tr, va, opts, capture_samples=cap, time_budget_s=args.time_budget)
        models[key] = r.model
        trainings[key] = {"steps": r.steps, "seconds": r.seconds,
                          "s_per_step": r.seconds / max(r.steps - r.resumed_from, 1),
                          "stopped_by_budget": r.stopped_by_budget, "threads": r.threads,
                          "parameters": count_parameters(r.model),
                          "val_curve": list(zip(r.history["val_step"], r.history["val_psnr"]))}
        print(f"trained {key}: {r.steps} steps in {r.seconds:.0f} s", flush=True)
    report["training"] = trainings
    threads = cpu_threads(args.threads)
    report["eval_threads"] = threads if device.type == "cpu" else None
    with torch_threads(threads):
        val_res, val_outs = evaluate_methods(va, models, full_res, device, scale,
                                             args.self_ensemble)
        report["heldout_views"] = val_res
        report["heldout_error_breakdown"] = error_breakdown(va, val_outs, full_depth, scale)
        if args.sequence:
            t_seq = time.perf_counter()
            seq = dense_sequence(folder, args.sequence)
            sframes, sgt = {}, {}
            for name, cam, img, depth in seq:
                renderer.extra[name] = (img, depth)  # GT for the stand-in; unused by the IBR one
                cams[name] = cam
                sgt[name] = img
            sframes = render_low_res([s[0] for s in seq], cams, renderer, scale)
            full = {s[0]: renderer(s[0], cams[s[0]])[0] for s in seq}
            order = [s[0] for s in seq]
            samples = [make_sample(order[i], order[max(i - 1, 0)], sframes, sgt[order[i]])
                       for i in range(len(order))]
            seq_res, outs = evaluate_methods(samples, models, full, device, scale,
                                             args.self_ensemble)
            gts = [sgt[n] for n in order]
            seq_res["flicker"] = {k: flicker(v, gts) for k, v in outs.items()}
            seq_res["seconds"] = time.perf_counter() - t_seq  # trace + renders + all methods
            report["sequence"] = seq_res
        # inference speed at --infer-size output (random content: speed only)
        W, H = (int(x) for x in args.infer_size.lower().split("x"))
        cam_lr = low_res_camera(list(cams.values())[0].resized(W, H), scale)
        rng = np.random.default_rng(0)
        col = rng.random((cam_lr.height, cam_lr.width, 3), dtype=np.float32)
        dep = np.full((cam_lr.height, cam_lr.width), 2.0, np.float32)
        for key, ens in (("inference_ms", False), ("inference_ms_self_ensemble", True)):
            if ens and not args.self_ensemble:
                continue
            sampler = SuperSampler(models["dsrnet"].to(device), device, ens)
            ms = []
            for i in range(args.repeats + 1):
                if device.type == "cuda":
                    torch.cuda.synchronize()
                t = time.perf_counter()
                sampler(col, dep, cam_lr)
                if device.type == "cuda":
                    torch.cuda.synchronize()
                if i:  # the first call warms up
                    ms.append((time.perf_counter() - t) * 1000)
            report[key] = {"output": f"{W}x{H}", "median": statistics.median(ms), "runs": ms}
    text = json.dumps(report, indent=1)
    Path(args.out).write_text(text)
    print(_summary(report))
    print(f"written {args.out}")
    return 0


def _summary(r: dict) -> str:
    lines = [f"DSRNet bench on {r['scene']} ({r['preset']}, {r['device']})"]
    for key, t in r["training"].items():
        lines.append(f"  train {key}: {t['steps']} steps, {t['seconds']:.0f} s "
                     f"({t['s_per_step']:.3f} s/step), {t['parameters']} parameters")
    for part in ("heldout_views", "sequence"):
        if part in r:
            lines.append(f"  {part} ({r[part]['frames']} frames): " + ", ".join(
                f"{k} {v['psnr']:.2f} dB / {v['ssim']:.4f}" for k, v in r[part]["mean"].items()))
    eb = r.get("heldout_error_breakdown")
    if eb:
        lines.append("  held-out error breakdown (PSNR of pooled MSE, dB; pixel share " + ", ".join(
            f"{k} {v:.3f}" for k, v in eb["pixel_share"].items()) + "):")
        for k, v in eb.items():
            if k not in ("pixel_share", "input_psnr"):
                lines.append(f"    {k:18s} " + ", ".join(f"{r} {x:.2f}" for r, x in v.items()))
        lines.append("    inputs vs area-downsampled GT: " + ", ".join(
            f"{k} {v:.2f}" for k, v in eb["input_psnr"].items()))
    if "sequence" in r:
        lines.append("  flicker: " + ", ".join(f"{k} {v:.4f}"
                                                for k, v in r["sequence"]["flicker"].items()))
    lines.append(f"  inference at {r['inference_ms']['output']}: "
                 f"{r['inference_ms']['median']:.0f} ms (median)")
    if "inference_ms_self_ensemble" in r:
        lines.append(f"  inference with the self-ensemble: "
                     f"{r['inference_ms_self_ensemble']['median']:.0f} ms (median)")
    return "\n".join(lines)
