"""Hierarchical push-pull hole filling (Gortler et al. 1996, "The Lumigraph"), as used by
Lochmann et al. 2014, §3.5: "filled using a hierarchical hole filling approach [GGSC96] on each
node independently which skips pulling and pushing from and to invalid pixels".

Pull: each coarser level averages the valid pixels of its 2x2 children (invalid ones are skipped,
weight 0). Push: an invalid pixel takes the bilinearly upsampled value of the level above; valid
pixels keep their own value (they are never pushed to).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from . import ops


def push_pull(img: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Fill the invalid pixels of (H, W, C) from the valid ones; valid pixels are unchanged.
    An image with no valid pixel is returned as zeros."""
    ops.check(img, (None, None, None), "image")
    ops.check(valid, tuple(img.shape[:2]), "valid")
    if bool(valid.all()):
        return img
    if not bool(valid.any()):
        return torch.zeros_like(img)
    c = (img.permute(2, 0, 1)[None] * valid[None, None]).to(img.dtype)
    w = valid[None, None].to(img.dtype)
    levels = [(c, w)]
    while min(c.shape[-2:]) > 1:
        # pull: weighted 2x2 average of valid children (ceil_mode keeps odd borders)
        cs = F.avg_pool2d(c, 2, ceil_mode=True)
        ws = F.avg_pool2d(w, 2, ceil_mode=True)
        c = torch.where(ws > 0, cs / ws.clamp_min(1e-12), torch.zeros_like(cs))
        w = (ws > 0).to(img.dtype)
        c = c * w
        levels.append((c, w))
    filled = levels[-1][0]
    for c, w in reversed(levels[:-1]):
        up = F.interpolate(filled, size=c.shape[-2:], mode="bilinear", align_corners=False)
        filled = torch.where(w > 0, c, up)  # push only into invalid pixels
    return filled[0].permute(1, 2, 0)
