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
    An image with no valid pixel is returned as zeros.

    The finest push touches only the holes: their bilinear upsampled value (the same formula as
    F.interpolate(..., align_corners=False)) is computed at the hole pixels alone."""
    ops.check(img, (None, None, None), "image")
    ops.check(valid, tuple(img.shape[:2]), "valid")
    if bool(valid.all()):
        return img
    if not bool(valid.any()):
        return torch.zeros_like(img)
    H, W, C = img.shape
    w = valid.to(img.dtype)[None, None]
    c = (img * w[0, 0, ..., None]).permute(2, 0, 1)[None]
    cw = torch.cat([c, w], 1)      # colour and weight pulled in one pooling pass
    levels = []
    while min(cw.shape[-2:]) > 1:
        # pull: weighted 2x2 average of valid children (ceil_mode keeps odd borders)
        cw = F.avg_pool2d(cw, 2, ceil_mode=True)
        ws = cw[:, C:]
        w = (ws > 0).to(img.dtype)
        c = cw[:, :C] / ws.clamp_min(1e-12) * w
        cw = torch.cat([c, w], 1)
        levels.append((c, w))
    if not levels:  # a 1-pixel-high / -wide image: nothing to pull from (holes stay 0)
        return img * valid[..., None].to(img.dtype)
    filled = levels[-1][0]
    for c, w in reversed(levels[:-1]):
        up = F.interpolate(filled, size=c.shape[-2:], mode="bilinear", align_corners=False)
        filled = torch.where(w > 0, c, up)  # push only into invalid pixels
    # finest level: bilinear upsample of `filled` (h, w) evaluated at the holes only
    h, wd = filled.shape[-2:]
    coarse = filled[0].permute(1, 2, 0).reshape(h * wd, C)
    hole = torch.nonzero(~valid.reshape(-1)).squeeze(-1)
    ys = ((hole // W).to(img.dtype) + 0.5) * (h / H) - 0.5
    xs = ((hole % W).to(img.dtype) + 0.5) * (wd / W) - 0.5
    ys, xs = ys.clamp_min(0), xs.clamp_min(0)
    y0, x0 = ys.floor(), xs.floor()
    ly, lx = (ys - y0)[:, None], (xs - x0)[:, None]
    y0, x0 = y0.long().clamp(max=h - 1), x0.long().clamp(max=wd - 1)
    y1, x1 = (y0 + 1).clamp(max=h - 1), (x0 + 1).clamp(max=wd - 1)
    val = (1 - ly) * ((1 - lx) * coarse[y0 * wd + x0] + lx * coarse[y0 * wd + x1]) + \
        ly * ((1 - lx) * coarse[y1 * wd + x0] + lx * coarse[y1 * wd + x1])
    out = img.reshape(H * W, C).clone()
    out[hole] = val
    return out.view(H, W, C)
