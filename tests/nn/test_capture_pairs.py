"""Capture pairs (our extension beyond §6): the captured image area-downsampled, with its render's
depth, as input; the capture as target. Properties: the dataset never holds a validation view,
the input is a faithful downsampling, the mix ratio picks the crops, a tiny mixed run learns, and
the learning-rate warm-up."""
import dataclasses

import cv2
import numpy as np
import pytest

from ibr_pipeline.nn.data import (capture_low_res, capture_pairs, make_sample, render_low_res,
                                  sequence_pairs, split_views, to_tensors)
from ibr_pipeline.nn.model import DSRNetConfig
from ibr_pipeline.nn.train import TrainOptions, _batch, _lr_at, train
from ibr_pipeline.render.low_res import StandInRenderer

SMALL = DSRNetConfig(feature_channels=(8, 8, 4), mvr_channels=(8, 8), reweight_channels=(8, 8),
                     unet_channels=(8, 12))


@pytest.fixture(scope="module")
def data(tiny_scene):
    r = StandInRenderer(tiny_scene[0])
    cams = r.cameras()
    names = list(cams)
    frames = render_low_res(names, cams, r, 2)
    targets = {n: r.gt_image(n) for n in names}
    tr, va = split_views(names, 0.25)
    pairs = sequence_pairs(tr, tr)
    return dict(frames=frames, targets=targets, train=tr, val=va, pairs=pairs,
                render=[make_sample(c, p, frames, targets[c]) for c, p in pairs],
                capture=capture_pairs(pairs, frames, targets),
                val_samples=[make_sample(c, p, frames, targets[c])
                             for c, p in sequence_pairs(names, va) if p not in va])


def test_capture_pairs_never_hold_a_validation_view(data):
    assert data["val"] and data["capture"]
    used = {s.name for s in data["capture"]} | {s.prev_name for s in data["capture"]}
    assert used <= set(data["train"]) and not used & set(data["val"])
    assert len(data["capture"]) == len(data["pairs"])


def test_capture_input_is_the_downsampled_capture(data):
    s = data["capture"][0]
    frame = data["frames"][s.name]
    h, w = frame.depth.shape
    assert s.cur.color.shape == (h, w, 3) and s.target.shape[:2] == (2 * h, 2 * w)
    # same camera and depth as the render; colour = the capture, not the render
    np.testing.assert_array_equal(s.cur.depth, frame.depth)
    assert s.cur.camera is frame.camera
    tgt = s.target
    assert abs(float(s.cur.color.mean()) - float(tgt.mean())) < 1e-3  # area keeps the mean
    up = cv2.resize(s.cur.color, (2 * w, 2 * h), interpolation=cv2.INTER_LINEAR)
    render_up = cv2.resize(frame.color, (2 * w, 2 * h), interpolation=cv2.INTER_LINEAR)
    assert np.abs(up - tgt).mean() < np.abs(render_up - tgt).mean()  # no render artefacts
    with pytest.raises(ValueError, match="multiple"):
        capture_low_res(tgt[:-1], frame)


def test_mix_ratio_picks_the_crops(data, monkeypatch):
    import ibr_pipeline.nn.train as T
    opts = TrainOptions(batch=8, crop=16, progress=False)
    capture_ids = {id(s) for s in data["capture"]}
    picked = []
    orig = T.to_tensors
    monkeypatch.setattr(T, "to_tensors", lambda samples, **kw: (picked.append(samples),
                                                                orig(samples, **kw))[1])

    def n_capture(frac, step):
        picked.clear()
        _batch(data["render"], dataclasses.replace(opts, capture_fraction=frac), step, "cpu",
               data["capture"])
        return sum(id(s) in capture_ids for s in picked[0])

    assert all(n_capture(0.0, k) == 0 for k in range(5))
    assert all(n_capture(1.0, k) == 8 for k in range(5))
    half = sum(n_capture(0.5, k) for k in range(40)) / (40 * 8)
    assert 0.35 < half < 0.65


def test_tiny_mixed_run_lowers_the_loss(data):
    """Loss on the training frames (one render pair + one capture pair, whole frames) before vs
    after a short mixed run."""
    import torch

    from ibr_pipeline.nn.losses import build_features
    from ibr_pipeline.nn.model import DSRNet
    from ibr_pipeline.nn.train import total_loss

    render, capture = data["render"][:1], data["capture"][:1]
    opts = TrainOptions(steps=150, batch=2, crop=1000, lr=3e-3, warmup_steps=20,
                        checkpoint_every=1000, progress=False, threads=1,
                        capture_fraction=0.5, flip=False)
    batch = to_tensors(render + capture)
    feats = build_features("")
    torch.manual_seed(opts.seed)
    before = DSRNet(SMALL).eval()  # the initial weights of `train` (same seed)
    res = train(SMALL, render, [], opts, capture_samples=capture)
    with torch.no_grad():
        l0 = float(total_loss(before, feats, batch, opts)[1])
        l1 = float(total_loss(res.model, feats, batch, opts)[1])
    assert np.isfinite(res.history["loss"]).all()
    assert l1 < 0.95 * l0


def test_warmup_then_cosine():
    o = TrainOptions(steps=1000, lr=1e-3, warmup_steps=100)
    lrs = np.array([_lr_at(o, k) for k in range(1000)])
    assert lrs[0] <= 0.02 * o.lr and np.all(np.diff(lrs[:100]) > 0)
    assert lrs[99] == pytest.approx(o.lr, rel=0.03)  # the cosine has begun
    assert np.all(np.diff(lrs[100:]) <= 0) and lrs[-1] < 1e-3 * o.lr
    assert _lr_at(dataclasses.replace(o, warmup_steps=0), 0) == pytest.approx(o.lr)
