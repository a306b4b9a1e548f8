"""Stage `supersample`: train DSRNet on the scene's own capture views (Xu et al. §5.2, §6).

Leave-one-out renders of the registered capture views at 1/scale resolution (the real renderer of
`render_views`, render/low_res.py's IBRRenderer, with the settings render_views rendered with,
renders/settings.json: each view rendered without itself) are paired
with the captured full-resolution images; consecutive capture views give the previous frame;
90 % / 10 % split (§6), the validation views are never trained on. Writes the trained network
`nn/dsrnet.pt` (read by `nn.infer.SuperSampler`, `ibr render --supersample`), `nn/train.json`
(options, steps, time, validation PSNR/SSIM against bilinear/bicubic upsampling) and `nn/loss.png`.

An interrupted run resumes: renders are cached in `nn/cache/` and the training state in
`nn/checkpoint.pt` (both removed after success, and ignored when the inputs or options changed).
`renderer = "standin"` is for tests/benchmarks on synthetic scenes only (nn/data.py says what it is).
"""
from __future__ import annotations

import dataclasses
import json
import logging
import time
from dataclasses import dataclass

from .. import layout as L
from ..config import StageConfig, param
from ..errors import ConfigError, InputError
from ..nn.options import TrainOptions
from ..runner import Stage, StageContext
from .common import registered_views

log = logging.getLogger("ibr_pipeline.supersample")



@dataclass(frozen=True)
class SupersampleConfig(StageConfig):
    preset: str = param("cpu", "channel widths: 'cpu' (trains on 2 cores in the demo budget) or "
                        "'paper' (RSSNet/DSRNet widths, for a GPU)", choices=("cpu", "paper"))
    scale: int = param(2, "supersampling factor: renders at 1/scale resolution (§5.2: x2)",
                       choices=(2, 3, 4))
    use_mvr: bool = param(True, "motion-vector rectification (Eq. 16); off = Table 3 'W/O MVR'")
    time_budget_s: float = param(150.0, "wall-clock budget of the whole stage (renders + "
                                 "training): training stops early and saves; 0 = none",
                                 min=0.0, max=7 * 86400.0)
    exclude_nearest: int = param(0, "also train on a second render of each training view that "
                                 "leaves out its N nearest capture views too (farther sources: "
                                 "the artefacts of views off the capture path; our extension "
                                 "beyond §6); 0 = leave-one-out renders only (§6)",
                                 min=0, max=10_000)
    val_fraction: float = param(0.1, "share of capture views held out for validation (§6: 0.1)",
                                min=0.05, max=0.5)
    renderer: str = param("ibr", "low-res renderer: 'ibr' (the render_views renderer) or "
                          "'standin' (synthetic scenes only: ground truth with IBR-like "
                          "artefacts, for tests)", choices=("ibr", "standin"))
    train: TrainOptions = param(TrainOptions(), "DSRNet training")

    def check(self, prefix: str) -> None:
        if self.exclude_nearest and self.renderer != "ibr":
            raise ConfigError(prefix + "exclude_nearest", "needs renderer = 'ibr' (the stand-in "
                              "renderer has no source views to leave out)")


def inputs(ctx: StageContext) -> list[str]:
    keys = [L.REGISTERED_CAMERAS]
    if not ctx.ws.exists(L.REGISTERED_CAMERAS):
        return keys
    views = registered_views(ctx)
    keys += [ctx.scene.view(v).image for v in views]
    if ctx.config.renderer == "ibr":  # what the render_views renderer reads, and its settings
        if ctx.ws.exists(L.RENDER_SETTINGS):  # before render_views ran: the defaults
            keys.append(L.RENDER_SETTINGS)
        for v in views:
            keys += L.renderer_files(ctx.ws, v)
    else:
        keys += [L.INPUT_CAMERAS]
    return keys


def run(ctx: StageContext) -> None:
    import shutil

    import numpy as np

    from ..io.images import read_image
    from ..nn.data import (capture_pairs, make_sample, nearest_views, render_low_res,
                           sequence_pairs, split_views, supersampled_size)
    from ..nn.model import count_parameters, preset, resolve_device, save_model
    from ..nn.train import evaluate, plot_losses, record_validation, train
    from ..render.low_res import IBRRenderer, StandInRenderer
    from ..workspace import atomic_path

    from collections import Counter

    t_start = time.perf_counter()
    ws, cfg = ctx.ws, ctx.config
    cams = L.registered_cameras(ws)
    names = registered_views(ctx)
    sizes = Counter(cams[n].size for n in names)
    if len(sizes) > 1:
        # DSRNet learns one upsampling and batches frames: it trains on the views of the most
        # common size (a capture mixing cameras has a main one); the others are left out
        main = max(sizes, key=lambda sz: (sizes[sz], sz))
        left = [n for n in names if cams[n].size != main]
        names = [n for n in names if cams[n].size == main]
        log.info("supersample: views of %d sizes; training on the %d at %dx%d, leaving out %d (%s)",
                 len(sizes), len(names), *main, len(left), ", ".join(left[:5]))
    tcfg = cfg.train
    if tcfg.vgg_weights and not ws.path(tcfg.vgg_weights).is_file():
        raise InputError(f"{ws.path(tcfg.vgg_weights)}: supersample.train.vgg_weights file not found")
    try:
        train_names, val_names = split_views(names, cfg.val_fraction)
    except ValueError as e:
        raise InputError(f"{ws.path(L.REGISTERED_CAMERAS)}: {e}") from None
    try:
        resolve_device(tcfg.device)
    except ValueError as e:
        raise ConfigError("supersample.train.device", str(e)) from None
    if cfg.exclude_nearest and cfg.exclude_nearest >= len(names) - 1:
        raise InputError(f"supersample.exclude_nearest = {cfg.exclude_nearest} would leave out "
                         f"every other view ({len(names)} registered views)")
    if cfg.renderer == "standin":
        renderer = StandInRenderer(ws.input_root, seed=tcfg.seed)
    else:
        renderer = IBRRenderer(ws)

    digest = ctx.fingerprint   # renders and checkpoint belong to this run's inputs and config
    cache_dir = ws.path(L.CACHE)
    meta = cache_dir / "meta.json"
    if meta.is_file() and json.loads(meta.read_text()).get("digest") != digest:
        shutil.rmtree(cache_dir, ignore_errors=True)  # a killed run with other inputs
    cache_dir.mkdir(parents=True, exist_ok=True)
    with atomic_path(meta) as tmp:
        tmp.write_text(json.dumps({"digest": digest}))

    def cache_as(suffix=""):
        def cache(name, compute):
            from ..layout import view_key
            f = cache_dir / f"{view_key(name)}{suffix}.npz"
            if f.is_file():
                with np.load(f) as z:
                    return z["color"], z["depth"]
            color, depth = compute()
            with atomic_path(f) as tmp:
                np.savez(tmp, color=color, depth=depth)
            return color, depth
        return cache

    t0 = time.perf_counter()
    show = tcfg.progress and ctx.progress   # `ibr ... --no-progress` silences the stage's bars too
    frames = render_low_res(names, cams, renderer, cfg.scale, show, cache_as())
    far_frames = {}
    if cfg.exclude_nearest:  # training views only: no validation view is ever a target
        near = nearest_views(cams, train_names, cfg.exclude_nearest)
        far_frames = render_low_res(train_names, cams, renderer.excluding(near), cfg.scale, show,
                                    cache_as(f"__far{cfg.exclude_nearest}"))
    render_s = time.perf_counter() - t0
    targets = {}
    for n in names:
        img = read_image(ws.path(ctx.scene.view(n).image), ctx.scene.image_encoding)
        if img.shape[:2] != (cams[n].height, cams[n].width):
            raise InputError(f"{ws.path(ctx.scene.view(n).image)}: image is "
                             f"{img.shape[1]}x{img.shape[0]}, its camera "
                             f"{cams[n].width}x{cams[n].height}")
        w, h = supersampled_size(cams[n].width, cams[n].height, cfg.scale)
        targets[n] = img[:h, :w]   # odd sizes: the last row / column has no low-res pixel
    train_pairs = sequence_pairs(train_names, train_names)
    train_samples = [make_sample(c, p, frames, targets[c]) for c, p in train_pairs]
    far_samples = ([make_sample(c, p, far_frames, targets[c]) for c, p in train_pairs]
                   if far_frames else [])
    train_samples += far_samples
    # capture pairs of the training views only (never a validation view, not even as previous)
    capture_samples = capture_pairs(train_pairs, frames, targets) if tcfg.capture_fraction > 0 else []
    val_samples = [make_sample(c, p, frames, targets[c]) for c, p in sequence_pairs(names, val_names)
                   if p not in val_names]

    model_cfg = preset(cfg.preset, scale=cfg.scale, use_mvr=cfg.use_mvr)
    reserve = 10.0 + 2.0 * len(val_samples)  # final evaluation + saving (measured ~16 s loaded)
    budget = 0.0
    if cfg.time_budget_s > 0:
        budget = max(1e-3, cfg.time_budget_s - (time.perf_counter() - t_start) - reserve)
    opts = dataclasses.replace(tcfg, progress=show, vgg_weights=(str(ws.path(tcfg.vgg_weights))
                                                                 if tcfg.vgg_weights else ""))
    result = train(model_cfg, train_samples, val_samples, opts, ws.path(L.CHECKPOINT), digest,
                   capture_samples=capture_samples, time_budget_s=budget, validate_last=False)
    device = next(result.model.parameters()).device
    val = evaluate(result.model, val_samples, device)
    if val:  # the curve's last point: this evaluation, not a second pass over the same views
        record_validation(result.history, result.steps, val["psnr"], val["psnr_bilinear"])
    save_model(ws.path(L.MODEL), result.model, {"trained_steps": result.steps})
    horizon = int(result.history.get("horizon", tcfg.steps))
    fitted = horizon < tcfg.steps
    plot_losses(result.history, ws.path(L.LOSS_PNG),
                f"DSRNet ({cfg.preset}, {'MVR' if cfg.use_mvr else 'no MVR'}), {result.steps} steps"
                + (f" (of {tcfg.steps}: fitted to the time budget)" if fitted else ""),
                "1 − SSIM + w·filters" + (" + L1" if tcfg.l1_weight > 0 else "")
                + (" + L_warp" if tcfg.warp_weight > 0 else ""))
    report = {
        "preset": cfg.preset, "model": model_cfg.to_dict(),
        "parameters": count_parameters(result.model), "renderer": cfg.renderer,
        "train_views": train_names, "val_views": val_names,
        "train_pairs": len(train_samples), "far_pairs": len(far_samples),
        "exclude_nearest": cfg.exclude_nearest, "capture_pairs": len(capture_samples),
        "capture_fraction": tcfg.capture_fraction, "val_pairs": len(val_samples),
        "steps": result.steps, "steps_planned": tcfg.steps, "resumed_from_step": result.resumed_from,
        "lr_horizon": horizon,
        "clipped_steps": int(result.history.get("clipped", 0)),
        "val_curve": [[int(a), float(b)] for a, b in zip(result.history.get("val_step", []),
                                                         result.history.get("val_psnr", []))],
        "stopped_by_time_budget": result.stopped_by_budget,
        "seconds": {"render": render_s, "train": result.seconds,
                    "total": time.perf_counter() - t_start},
        "device": str(device), "validation": val,
        "torch_threads": result.threads,
        "final_loss": float(np.mean(result.history["loss"][-20:])) if result.history["loss"] else None,
    }
    if not val_names:
        report["fallback"] = (f"only {len(names)} registered views: all trained on, no held-out "
                              "validation (needs >= 3)")
        log.warning("supersample: %s", report["fallback"])
    if val:
        log.info("supersample: %d steps in %.0f s; held-out PSNR %.2f dB (bilinear %.2f, bicubic "
                 "%.2f)", result.steps, result.seconds, val["psnr"], val["psnr_bilinear"],
                 val["psnr_bicubic"])
    ws.write_json(L.TRAIN_JSON, report)
    ws.path(L.CHECKPOINT).unlink(missing_ok=True)
    shutil.rmtree(cache_dir, ignore_errors=True)


STAGE = Stage(name="supersample", help="train DSRNet (Xu §5.2) on leave-one-out renders",
              config=SupersampleConfig, version="8", run=run, inputs=inputs,
              outputs=(L.MODEL, L.TRAIN_JSON, L.LOSS_PNG))
