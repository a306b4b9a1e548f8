"""Shared helpers for the DSRNet tests: a stand-in low-res dataset from a synthetic scene."""
from __future__ import annotations

from ibr_pipeline.nn.data import make_sample, render_low_res, sequence_pairs, split_views
from ibr_pipeline.render.low_res import StandInRenderer


def standin_samples(folder, scale: int = 2, seed: int = 0):
    """(train samples, val samples, renderer) from the STAND-IN renderer (GT + IBR-like artefacts)."""
    r = StandInRenderer(folder, seed=seed)
    cams = r.cameras()
    names = list(cams)
    frames = render_low_res(names, cams, r, scale)
    tr, va = split_views(names)
    train = [make_sample(c, p, frames, r.gt_image(c)) for c, p in sequence_pairs(tr, tr)]
    val = [make_sample(c, p, frames, r.gt_image(c)) for c, p in sequence_pairs(names, va)]
    return train, val, r
