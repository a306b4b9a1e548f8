"""Training loop: determinism with a seed, exact resume from a checkpoint, budget, loss curve,
and the accuracy property: DSRNet beats bicubic upsampling of the same low-res input.

Data: the STAND-IN low-res renderer (ground truth with IBR-like artefacts, render/low_res.py):
the tests of the loop need no reconstruction stages before it."""
import dataclasses

import numpy as np
import pytest
import torch
from helpers import standin_samples

from ibr_pipeline.nn.model import DSRNetConfig, load_model, save_model
from ibr_pipeline.nn.train import TrainOptions, evaluate, plot_losses, train

SMALL = DSRNetConfig(feature_channels=(8, 8, 4), mvr_channels=(8, 8), reweight_channels=(8, 8),
                     unet_channels=(8, 12))
OPTS = TrainOptions(steps=6, batch=2, crop=24, checkpoint_every=3, progress=False, threads=1)


@pytest.fixture(scope="module")
def tiny_samples(tiny_scene):
    return standin_samples(tiny_scene[0])


def _weights(model):
    return torch.cat([p.detach().flatten() for p in model.state_dict().values()])


def test_deterministic_and_resume_exact(tiny_samples, tmp_path):
    tr, va, _ = tiny_samples
    a = train(SMALL, tr, va, OPTS)
    b = train(SMALL, tr, va, OPTS)
    assert torch.equal(_weights(a.model), _weights(b.model))
    # killed right after the checkpoint of step 3, then resumed to 6: the same weights as straight
    ck = tmp_path / "ck.pt"
    _interrupt_after(3, SMALL, tr, va, OPTS, ck)
    resumed = train(SMALL, tr, va, OPTS, ck, "d")
    assert resumed.resumed_from == 3 and resumed.steps == 6
    assert torch.allclose(_weights(resumed.model), _weights(a.model), atol=1e-6)
    # a time budget stops early and says so
    cut = train(SMALL, tr, va, OPTS, time_budget_s=1e-9)
    assert cut.stopped_by_budget and cut.steps < 6
    # another data fingerprint: the checkpoint is ignored
    assert train(SMALL, tr, va, OPTS, ck, "other").resumed_from == 0


def _interrupt_after(n, cfg, tr, va, opts, ck):
    """Simulate a kill after the checkpoint of step n: train n steps with the same schedule."""
    import ibr_pipeline.nn.train as T
    orig = T._save_checkpoint
    saved = {}

    def save_then_stop(path, model, optim, step, history, fp):
        orig(path, model, optim, step, history, fp)
        if step >= n:
            saved["done"] = True
            raise KeyboardInterrupt

    T._save_checkpoint = save_then_stop
    try:
        with pytest.raises(KeyboardInterrupt):
            train(cfg, tr, va, opts, ck, "d")
    finally:
        T._save_checkpoint = orig
    assert saved


def test_model_file_roundtrip_and_plot(tiny_samples, tmp_path):
    tr, va, _ = tiny_samples
    res = train(SMALL, tr, va, OPTS)
    save_model(tmp_path / "m.pt", res.model)
    state = torch.load(tmp_path / "m.pt", weights_only=True)  # plain state dict, no pickled code
    assert state["format"].startswith("ibr_pipeline.dsrnet")
    m = load_model(tmp_path / "m.pt")
    assert torch.equal(_weights(m), _weights(res.model))
    plot_losses(res.history, tmp_path / "loss.png")
    assert (tmp_path / "loss.png").stat().st_size > 1000


@pytest.mark.slow
def test_overfits_one_frame_beyond_bicubic(tiny_samples):
    """Overfit setting on `tiny` (~40 s): trained on one frame, the network beats bicubic in SSIM
    (what its loss, 1 - SSIM + w filters, optimises) and bilinear in PSNR. Its PSNR stays within
    0.3 dB of bicubic here: the stand-in's random sub-pixel misalignment cannot be learned."""
    _, va, _ = tiny_samples
    opts = TrainOptions(steps=200, batch=2, crop=24, lr=1e-3, checkpoint_every=1000,
                        progress=False, threads=1)
    res = train(DSRNetConfig(use_mvr=False), va[:1], [], opts)
    ev = evaluate(res.model, va[:1], "cpu")
    assert ev["ssim"] > ev["ssim_bicubic"] + 0.02, ev
    assert ev["psnr"] > ev["psnr_bilinear"] + 0.1, ev
    assert ev["psnr"] > ev["psnr_bicubic"] - 0.3, ev


@pytest.mark.slow
def test_beats_bicubic_on_held_out_views(sample_scene):
    """Generalisation on sample_data/mirror_room (21 training views; the 2 validation views are
    never trained on), 400 steps (~2-3 min): beats bicubic and bilinear in PSNR and SSIM."""
    tr, va, _ = standin_samples(sample_scene)
    opts = TrainOptions(steps=400, batch=4, crop=48, lr=1e-3, checkpoint_every=1000,
                        progress=False, threads=1)
    res = train(DSRNetConfig(), tr, va, opts)
    ev = evaluate(res.model, va, "cpu")
    assert ev["psnr"] > ev["psnr_bicubic"] + 0.2, ev
    assert ev["psnr"] > ev["psnr_bilinear"] + 0.8, ev
    assert ev["ssim"] > ev["ssim_bicubic"], ev
    assert np.isfinite(res.history["loss"]).all()


def test_split_falls_back_to_no_validation_with_two_views():
    import pytest

    from ibr_pipeline.nn.data import split_views
    assert split_views(["a", "b"]) == (["a", "b"], [])
    tr, va = split_views([f"{i:04d}" for i in range(20)])
    assert len(va) == 2 and not set(tr) & set(va)
    with pytest.raises(ValueError, match="at least 2"):
        split_views(["a"])


def test_fitted_horizon_only_shortens_when_the_budget_binds():
    from ibr_pipeline.nn.train import FIT_MARGIN, fitted_horizon
    # 100 steps took 10 s and 990 s remain: 9 900 more fit, so a 5000-step plan stands
    assert fitted_horizon(5000, 100, 100, 10.0, 990.0) == 5000
    # 100 steps took 50 s and 50 s remain: about 100 more steps (with the margin), not 5000
    h = fitted_horizon(5000, 100, 100, 50.0, 50.0)
    assert h == 100 + int(FIT_MARGIN * 50.0 * 100 / 50.0) and 190 <= h <= 200
    # never before the next step, never past the plan, nothing timed = the plan
    assert fitted_horizon(5000, 100, 100, 50.0, 0.0) == 101
    assert fitted_horizon(5000, 100, 100, 50.0, -3.0) == 101
    assert fitted_horizon(150, 100, 100, 50.0, 50.0) == 150
    assert fitted_horizon(5000, 100, 0, 0.0, 50.0) == 5000


def test_budget_fit_ends_the_decay_inside_the_budget(tiny_samples, monkeypatch):
    """With a fake clock (1 s per step) and a 30 s budget for 60 planned steps, the fitted run
    ends at its horizon with the learning rate decayed; without the fit the budget cuts it at a
    high learning rate."""
    import ibr_pipeline.nn.train as T
    tr, va, _ = tiny_samples
    opts = dataclasses.replace(OPTS, steps=60, checkpoint_every=10,
                               warmup_steps=0)

    def run(fit):
        ticks = iter(range(10_000))
        monkeypatch.setattr(T, "_clock", lambda: float(next(ticks)))
        return train(SMALL, tr[:2], [], dataclasses.replace(opts, fit_budget=fit), time_budget_s=30.0)

    fitted, cut = run(True), run(False)
    h = fitted.history["horizon"]
    assert fitted.stopped_by_budget and fitted.steps == h and 20 < h < 30
    assert T._lr_at(opts, fitted.steps - 1, h) < 0.05 * opts.lr
    assert cut.stopped_by_budget and cut.history["horizon"] == 60 and 25 <= cut.steps <= 31
    assert T._lr_at(opts, cut.steps - 1, 60) > 0.4 * opts.lr


def test_gradient_clipping_bounds_the_norm_and_counts_clipped_steps(tiny_samples, monkeypatch):
    tr, va, _ = tiny_samples
    norms = []
    real = torch.nn.utils.clip_grad_norm_

    def spy(params, max_norm):
        params = list(params)
        before = real(params, max_norm)
        after = torch.sqrt(sum((p.grad.detach() ** 2).sum() for p in params if p.grad is not None))
        norms.append((float(before), float(after)))
        return before

    monkeypatch.setattr(torch.nn.utils, "clip_grad_norm_", spy)
    tight = train(SMALL, tr, va, dataclasses.replace(OPTS, grad_clip=1e-4))
    assert tight.history["clipped"] == 6 and len(norms) == 6
    assert all(b > 1e-4 and a <= 1e-4 * 1.001 for b, a in norms)   # clipped to the bound
    norms.clear()
    loose = train(SMALL, tr, va, dataclasses.replace(OPTS, grad_clip=1e9))
    assert loose.history["clipped"] == 0 and all(abs(a - b) <= 1e-6 * b for b, a in norms)
    off = train(SMALL, tr, va, dataclasses.replace(OPTS, grad_clip=0.0))
    assert "clipped" not in off.history and len(norms) == 6              # not called when off
    # a bound that never binds changes nothing
    assert torch.equal(_weights(loose.model), _weights(off.model))


def test_validations_spread_over_the_run_and_the_last_left_to_the_caller(tiny_samples):
    tr, va, _ = tiny_samples
    opts = dataclasses.replace(OPTS, steps=12, checkpoint_every=1)
    full = train(SMALL, tr, va, opts)
    assert full.history["val_step"] == [3, 6, 9, 12]   # 4 a run, at steps // 4, the last one's too
    own = train(SMALL, tr, va, opts, validate_last=False)
    assert own.history["val_step"] == [3, 6, 9]
    assert own.history["val_psnr"] == full.history["val_psnr"][:3]   # the same run otherwise
    ev = evaluate(own.model, va, torch.device("cpu"), ssim=False)
    assert abs(ev["psnr"] - full.history["val_psnr"][-1]) < 1e-3
