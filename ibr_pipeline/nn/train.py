"""DSRNet training loop (Xu et al. §5.2.2): Adam on random crops, progress bar, checkpoints, resume,
time budget, loss-curve PNG, deterministic for a seed.

Determinism: the weights are initialised from `torch.manual_seed(seed)` and the crops of step k
come from `numpy.random.default_rng([seed, k])`, so a run is a pure function of (data, options,
number of steps) and a resumed run continues exactly where the checkpoint left it (Adam's state is
in the checkpoint). When the time budget binds, the cosine schedule is fitted to it (`fitted_horizon`): the
decay ends at the step the budget is expected to reach instead of at `steps`, so a cut run still
ends at a small learning rate; such a run is deterministic given its horizon (recorded in the
history and the checkpoint, and reused on resume). When `steps` fit the budget nothing changes.

Files: the checkpoint holds only tensors and plain values (`torch.save` of state dicts) and is read
with `torch.load(weights_only=True)`.
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from ..workspace import atomic_path
from .data import Sample, to_tensors
from .losses import build_features, image_loss, warp_loss
from .model import DSRNet, DSRNetConfig, cpu_threads, resolve_device, torch_threads
from .options import TrainOptions

log = logging.getLogger("ibr_pipeline.nn.train")


@dataclass
class TrainResult:
    model: DSRNet
    steps: int
    stopped_by_budget: bool
    seconds: float
    history: dict = field(default_factory=dict)
    resumed_from: int = 0
    threads: int | None = None   # torch CPU threads the loop ran with (None on a GPU)


def _batch(samples: Sequence[Sample], opts: TrainOptions, step: int, device,
           capture: Sequence[Sample] = ()) -> dict:
    rng = np.random.default_rng([opts.seed, step])
    idx = rng.integers(0, len(samples), size=opts.batch)
    chosen = [samples[i] for i in idx]
    if capture and opts.capture_fraction > 0:  # each crop: a capture pair with that probability
        use = rng.random(opts.batch) < opts.capture_fraction
        cidx = rng.integers(0, len(capture), size=opts.batch)
        chosen = [capture[j] if u else s for s, u, j in zip(chosen, use, cidx)]
    b = to_tensors(chosen, crop=opts.crop, rng=rng, flip=opts.flip)
    return {k: v.to(device).contiguous(memory_format=torch.channels_last) for k, v in b.items()}


def _forward(model: DSRNet, b: dict) -> dict:
    return model(b["cur"], b["depth"], b["prev"], b["depth_prev"], b["flow"])


def total_loss(model: DSRNet, features, b: dict, opts: TrainOptions) -> tuple:
    out = _forward(model, b)
    loss = image_loss(features, out["image"], b["target"], opts.perceptual_weight,
                      opts.l1_weight)  # §5.2.2
    lw = torch.zeros((), device=loss.device)
    if model.mvr is not None and opts.warp_weight > 0:  # L_warp trains the MVR module
        lw = warp_loss(b["cur"], out["prev_warped"], out["inside"])
    return loss + opts.warp_weight * lw, loss.detach(), lw.detach()


@torch.no_grad()
def evaluate(model: DSRNet, samples: Sequence[Sample], device, baselines: bool = True,
             ssim: bool = True) -> dict:
    """Mean PSNR/SSIM (ibr_pipeline.metrics) of DSRNet, bilinear and bicubic upsampling.
    `baselines=False`: DSRNet only; `ssim=False`: PSNR only (the cheap validation of the loop)."""
    from .. import metrics
    from .infer import upsample

    if not samples:
        return {}
    model.eval()
    acc: dict = {}
    for s in samples:
        b = {k: v.to(device) for k, v in to_tensors([s]).items()}
        y = _forward(model, b)["image"].clamp(0, 1)[0].permute(1, 2, 0).cpu().numpy()
        f = s.target.shape[0] // s.cur.color.shape[0]
        cands = [("", y)]
        if baselines:
            cands += [("_bilinear", upsample(s.cur.color, f, "bilinear")),
                      ("_bicubic", upsample(s.cur.color, f, "bicubic"))]
        for suffix, img in cands:
            acc.setdefault("psnr" + suffix, []).append(metrics.psnr(s.target, img))
            if ssim:
                acc.setdefault("ssim" + suffix, []).append(metrics.ssim(s.target, img))
    model.train()
    return {k: float(np.mean(v)) for k, v in acc.items()}


def _save_checkpoint(path: Path, model, optim, step: int, history: dict, fingerprint: str) -> None:
    state = {"model": model.state_dict(), "optim": optim.state_dict(), "step": step,
             "history": history, "fingerprint": fingerprint}
    with atomic_path(Path(path)) as tmp:
        torch.save(state, tmp)


def _lr_at(opts: TrainOptions, step: int, horizon: int | None = None) -> float:
    """Linear warm-up over `warmup_steps`, then cosine decay to 0 at `horizon` (default `steps`)."""
    h = opts.steps if horizon is None else horizon
    warm = min(1.0, (step + 1) / opts.warmup_steps) if opts.warmup_steps > 0 else 1.0
    return warm * opts.lr * 0.5 * (1 + math.cos(math.pi * min(step / max(h, 1), 1.0)))


_clock = time.perf_counter  # the loop's clock (a test replaces it)
VALIDATIONS = 4   # validations per run, the last step's included
# the fit times the steps after the first FIT_SKIP ones (allocation, first-touch overhead), first
# after FIT_PROBE_STEPS of them, then at every checkpoint; FIT_MARGIN of the remaining time is used
FIT_SKIP = 5
FIT_PROBE_STEPS = 20
FIT_MARGIN = 0.97


def fitted_horizon(planned: int, step: int, steps_timed: int, timed_s: float,
                   remaining_s: float) -> int:
    """The step at which the cosine decay should end: `planned`, unless the rate of the last
    `steps_timed` steps (which took `timed_s`) says the `remaining_s` of the budget run out first;
    then the step it is expected to reach (FIT_MARGIN of the remaining time; never before
    `step` + 1). Our addition (not in Xu et al.): a budget-cut run otherwise stops at a high
    learning rate."""
    if steps_timed <= 0 or timed_s <= 0:
        return planned
    reach = step + int(FIT_MARGIN * max(0.0, remaining_s) * steps_timed / timed_s)
    return max(step + 1, min(planned, reach))


def train(config: DSRNetConfig, train_samples: Sequence[Sample], val_samples: Sequence[Sample],
          opts: TrainOptions, checkpoint: Path | None = None, fingerprint: str = "",
          capture_samples: Sequence[Sample] = (), time_budget_s: float = 0.0,
          validate_last: bool = True) -> TrainResult:
    """Train a DSRNet; resumes from `checkpoint` when it exists with the same `fingerprint`
    (the data's, given by the caller), the same options (those that affect the result) and model.
    `capture_samples` (data.capture_pairs of training views only) are mixed into the batches with
    probability `opts.capture_fraction` per crop. `time_budget_s` > 0: stop (and save) when the
    training has run that long; with `opts.fit_budget` the decay is fitted to it.
    `validate_last=False`: no validation at the last step, for a caller that evaluates the model
    it gets back anyway and records that with `record_validation`."""
    if not train_samples:
        raise ValueError("train: no training samples")
    if not (time_budget_s >= 0 and math.isfinite(time_budget_s)):
        raise ValueError(f"train: time_budget_s must be >= 0, got {time_budget_s}")
    device = resolve_device(opts.device)
    torch.manual_seed(opts.seed)
    model = DSRNet(config).to(device).train().to(memory_format=torch.channels_last)
    features = build_features(opts.vgg_weights).to(device)
    optim = torch.optim.Adam(model.parameters(), lr=opts.lr)
    fingerprint = f"{fingerprint}|{opts.digest()}|{config!r}"
    history = {"step": [], "loss": [], "image_loss": [], "warp_loss": [], "val_step": [],
               "val_psnr": [], "val_psnr_bilinear": []}
    start = 0
    if checkpoint is not None and Path(checkpoint).is_file():
        try:
            ck = torch.load(checkpoint, map_location="cpu", weights_only=True)
        except Exception as e:  # noqa: BLE001
            log.warning("supersample: ignoring unreadable checkpoint %s (%s)", checkpoint, e)
            ck = None
        if ck is not None and ck.get("fingerprint") == fingerprint:
            model.load_state_dict(ck["model"])
            optim.load_state_dict(ck["optim"])
            start, history = int(ck["step"]), ck["history"]
            log.info("supersample: resuming training at step %d from %s", start, checkpoint)
    threads = cpu_threads(opts.threads)   # also on a GPU: the crops are cut on the CPU
    if device.type == "cpu":
        log.info("supersample: training on %d CPU thread%s", threads, "s" * (threads > 1))
    with torch_threads(threads):
        result = _loop(model, features, optim, train_samples, val_samples, opts, checkpoint,
                       fingerprint, history, start, device, capture_samples, time_budget_s,
                       validate_last)
    result.threads = threads if device.type == "cpu" else None
    return result


def record_validation(history: dict, step: int, psnr: float, psnr_bilinear: float | None) -> None:
    """One point of the validation curve (the loss chart's and train.json's `val_curve`)."""
    history["val_step"].append(step)
    history["val_psnr"].append(psnr)
    history["val_psnr_bilinear"].append(psnr_bilinear)


def _loop(model, features, optim, train_samples, val_samples, opts, checkpoint, fingerprint,
          history, start, device, capture_samples=(), budget_s: float = 0.0,
          validate_last: bool = True) -> TrainResult:
    from tqdm import tqdm

    clock = _clock
    t0 = clock()
    step, stopped = start, False
    # cosine horizon: `steps`, or the one a budget fit chose (kept on resume, see `fitted_horizon`)
    horizon = int(history.get("horizon", opts.steps)) if start > 0 else opts.steps
    history["horizon"] = horizon
    fit = opts.fit_budget and budget_s > 0
    t_fit = 0.0
    bar = tqdm(total=opts.steps, initial=start, desc="supersample: training DSRNet", unit="step",
               disable=not opts.progress, leave=False)
    # validation (PSNR only; the baselines once) VALIDATIONS times a run, at checkpoint steps: it
    # runs DSRNet on every validation pair at full size, which at 640x480 costs more than the
    # training steps between two validations
    val_every = opts.checkpoint_every * max(1, math.ceil(opts.steps / VALIDATIONS
                                                         / opts.checkpoint_every))
    bilinear = None
    while step < horizon:   # the decay is complete at the horizon (= steps unless fitted)
        now = clock() - t0
        if budget_s > 0 and now > budget_s:
            stopped = True
            break
        if fit and step - start == FIT_SKIP:
            t_fit = now
        timed = step - start - FIT_SKIP
        if fit and timed > 0 and (timed == FIT_PROBE_STEPS or step % opts.checkpoint_every == 0):
            horizon = fitted_horizon(opts.steps, step, timed, now - t_fit, budget_s - now)
            history["horizon"] = horizon
        for g in optim.param_groups:
            g["lr"] = _lr_at(opts, step, horizon)
        b = _batch(train_samples, opts, step, device, capture_samples)
        loss, li, lw = total_loss(model, features, b, opts)
        optim.zero_grad(set_to_none=True)
        loss.backward()
        if opts.grad_clip > 0:
            norm = torch.nn.utils.clip_grad_norm_(model.parameters(), opts.grad_clip)
            history.setdefault("clipped", 0)
            history["clipped"] += int(norm > opts.grad_clip)
        optim.step()
        step += 1
        history["step"].append(step)
        history["loss"].append(float(loss.detach()))
        history["image_loss"].append(float(li))
        history["warp_loss"].append(float(lw))
        bar.update(1)
        bar.set_postfix(loss=f"{history['loss'][-1]:.4f}")
        if step % opts.checkpoint_every == 0 or step == horizon:
            last = step == horizon
            if val_samples and (last and validate_last or not last and step % val_every == 0):
                ev = evaluate(model, val_samples, device, baselines=bilinear is None, ssim=False)
                bilinear = ev.get("psnr_bilinear", bilinear)
                record_validation(history, step, ev["psnr"], bilinear)
            if checkpoint is not None:
                _save_checkpoint(checkpoint, model, optim, step, history, fingerprint)
    bar.close()
    model.eval()
    stopped = stopped or horizon < opts.steps   # the budget ended the run before `steps`
    return TrainResult(model, step, stopped, clock() - t0, history, start)


def plot_losses(history: dict, path: Path, title: str = "DSRNet training",
                ylabel: str = "1 − SSIM + w·filters + L_warp") -> None:
    """Loss curve (and validation PSNR) as a PNG, written atomically."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4), dpi=100)
    steps = np.asarray(history.get("step", []))
    loss = np.asarray(history.get("loss", []))
    if len(loss):
        ax.plot(steps, loss, color="0.75", lw=0.8, label="loss (per step)")
        k = max(1, len(loss) // 50)
        smooth = np.convolve(loss, np.ones(k) / k, mode="valid")
        ax.plot(steps[k - 1:], smooth, color="C0", lw=1.5, label=f"loss (mean of {k})")
    ax.set_xlabel("step")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    if history.get("val_psnr"):
        ax2 = ax.twinx()
        ax2.plot(history["val_step"], history["val_psnr"], "o-", color="C3", label="val PSNR")
        ax2.plot(history["val_step"], history["val_psnr_bilinear"], "--", color="C2",
                 label="val PSNR bilinear")
        ax2.set_ylabel("PSNR (dB)")
        ax2.legend(loc="upper center", fontsize=8)
    ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    with atomic_path(Path(path)) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
