"""DSRNet training losses (Xu et al. §5.2.2).

    L(I_f, I_gt) = 1 − SSIM(I_f, I_gt) + w Σ_{i=1..5} ‖conv_i(I_f) − conv_i(I_gt)‖²,   w = 0.1
    L_warp = L1(G(I_n), G(M_r ⊙ I_{n−1})) + L1(I_n, M_r ⊙ I_{n−1}),   G: 5x5 Gaussian

The paper's conv_i are pre-computed VGG filters (a perceptual loss). No weights can be downloaded
here, so the default `FilterBank` is a fixed, hand-designed stand-in with the same structure: five
"layers" i = 1..5 at the strides of VGG's five blocks (1, 2, 4, 8, 16), each a bank of oriented
first-derivative-of-Gaussian filters (0°, 45°, 90°, 135°) plus a Laplacian of Gaussian, applied per
colour channel. The first-layer filters learned by VGG-like networks are themselves oriented
edge/Gabor-like detectors (Zeiler & Fergus 2014), so this bank compares local multi-scale edge and
blob structure as the lower VGG layers do; it has no learned semantic features (deeper VGG layers).
`VGGFeatures` loads a user-supplied VGG-16 `features` state dict (torchvision key layout) when one is
given (config `vgg_weights`) and then uses relu1_2, relu2_2, relu3_3, relu4_3, relu5_3 as conv_1..5.
‖·‖² is taken as the mean squared difference per layer (the usual normalisation of a perceptual
loss; a raw sum would make w depend on the image size).
"""
from __future__ import annotations

import math
from pathlib import Path

import torch
import torch.nn as nn
import torch.nn.functional as F

from .options import PERCEPTUAL_WEIGHT

WARP_GAUSSIAN_SIZE = 5  # §5.2.2: "the Gaussian filter with 5x5 kernels"


def _check_pair(a, b, what: str) -> None:
    if a.ndim != 4 or a.shape != b.shape:
        raise ValueError(f"{what}: expected two (B, C, H, W) tensors of the same shape, got "
                         f"{tuple(a.shape)} and {tuple(b.shape)}")


def gaussian_1d(size: int, sigma: float, dtype=torch.float32) -> torch.Tensor:
    """Normalised (size,) Gaussian; its outer product with itself is the 2D kernel."""
    x = torch.arange(size, dtype=dtype) - (size - 1) / 2
    g = torch.exp(-x ** 2 / (2 * sigma ** 2))
    return g / g.sum()


def gaussian_blur(x, size: int, sigma: float):
    """Per-channel Gaussian filter of (B, C, H, W) `x` with replicated borders. Separable: a row
    pass then a column pass over the padded image, the same sums as the 2D kernel's (to rounding)
    at 2·size instead of size² taps; the 2D depthwise convolution's backward pass was the most
    expensive op of a DSRNet training step on the CPU (docs/DSRNET.md)."""
    c, pad = x.shape[1], size // 2
    g = gaussian_1d(size, sigma, x.dtype).to(x.device)
    x = F.pad(x, (pad, pad, pad, pad), mode="replicate")
    x = F.conv2d(x, g.view(1, 1, 1, size).expand(c, 1, 1, size), groups=c)
    return F.conv2d(x, g.view(1, 1, size, 1).expand(c, 1, size, 1), groups=c)


def ssim(a, b, size: int = 11, sigma: float = 1.5):
    """Mean SSIM (Wang et al. 2004; same constants as ibr_pipeline.metrics), differentiable."""
    _check_pair(a, b, "ssim")
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    blur = lambda x: gaussian_blur(x, size, sigma)  # noqa: E731
    mx, my = blur(a), blur(b)
    vx = blur(a * a) - mx * mx
    vy = blur(b * b) - my * my
    cxy = blur(a * b) - mx * my
    s = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))
    return s.mean()


class FilterBank(nn.Module):
    """Fixed multi-scale oriented filter bank: the stand-in for the paper's VGG conv_1..conv_5."""

    def __init__(self, levels: int = 5, sigma: float = 1.0, size: int = 7):
        super().__init__()
        x = torch.arange(size, dtype=torch.float32) - (size - 1) / 2
        yy, xx = torch.meshgrid(x, x, indexing="ij")
        g = torch.exp(-(xx ** 2 + yy ** 2) / (2 * sigma ** 2))
        gx, gy = -xx * g, -yy * g
        filters = []
        for k in range(4):  # oriented first derivatives of a Gaussian, 0°, 45°, 90°, 135°
            t = k * math.pi / 4
            filters.append(math.cos(t) * gx + math.sin(t) * gy)
        log = (xx ** 2 + yy ** 2 - 2 * sigma ** 2) * g  # Laplacian of Gaussian
        filters.append(log - log.mean())
        bank = torch.stack([f / f.norm() for f in filters])  # unit L2 norm: responses ~ contrast
        self.register_buffer("bank", bank[:, None])  # (5, 1, k, k)
        self.levels = levels

    def forward(self, x) -> list:
        b, c, h, w = x.shape
        feats = []
        for i in range(self.levels):
            if i > 0:
                if min(x.shape[2:]) < 2:
                    break
                x = F.avg_pool2d(x, 2)  # VGG block strides 1, 2, 4, 8, 16
            pad = self.bank.shape[-1] // 2
            # the bank on every channel: one grouped convolution, (B, C*5, h, w); it ran ~2.5x
            # faster forward and backward than the (B*C, 1) reshape through one 5-filter conv
            y = F.conv2d(F.pad(x, (pad,) * 4, mode="replicate"), self.bank.repeat(c, 1, 1, 1),
                         groups=c)
            feats.append(y)
        return feats


_VGG16 = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512]
_VGG16_TAPS = (3, 8, 15, 22, 29)  # indices of relu1_2, relu2_2, relu3_3, relu4_3, relu5_3


class VGGFeatures(nn.Module):
    """VGG-16 `features` (torchvision layout: keys `0.weight`, ... or `features.0.weight`, ...)
    with user-supplied weights, frozen; returns the five relu_x taps used as conv_1..conv_5."""

    def __init__(self, weights_path: str | Path):
        super().__init__()
        layers, c = [], 3
        for v in _VGG16:
            if v == "M":
                layers.append(nn.MaxPool2d(2))
            else:
                layers += [nn.Conv2d(c, v, 3, padding=1), nn.ReLU(inplace=False)]
                c = v
        self.features = nn.Sequential(*layers)
        from ..errors import InputError
        from .model import torch_load_reason
        try:
            state = torch.load(Path(weights_path), map_location="cpu", weights_only=True)
        except Exception as e:  # noqa: BLE001  (a user's file: one line naming it)
            raise InputError(f"{weights_path}: cannot read VGG-16 weights ({torch_load_reason(e)})") from None
        if isinstance(state, dict) and "state_dict" in state:
            state = state["state_dict"]
        state = {k[len("features."):] if k.startswith("features.") else k: v
                 for k, v in state.items() if not k.startswith("classifier.")}
        self.features.load_state_dict(state, strict=True)
        for p in self.parameters():
            p.requires_grad_(False)
        self.register_buffer("mean", torch.tensor([0.485, 0.456, 0.406])[None, :, None, None])
        self.register_buffer("std", torch.tensor([0.229, 0.224, 0.225])[None, :, None, None])

    def forward(self, x) -> list:
        x = (x - self.mean) / self.std
        out = []
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in _VGG16_TAPS:
                out.append(x)
            if i >= _VGG16_TAPS[-1]:
                break
        return out


def perceptual(features: nn.Module, a, b):
    """Σ_i mean ‖conv_i(a) − conv_i(b)‖² over the feature layers (§5.2.2)."""
    _check_pair(a, b, "perceptual")
    return sum(F.mse_loss(fa, fb) for fa, fb in zip(features(a), features(b)))


def image_loss(features: nn.Module, out, gt, w: float = PERCEPTUAL_WEIGHT, l1: float = 0.0):
    """L = 1 − SSIM + w Σ ‖conv_i(I_f) − conv_i(I_gt)‖² (§5.2.2) [+ l1 · L1(I_f, I_gt), optional:
    Table 4 of the paper ablates an "L1 loss" that §5.2.2 does not write down; see DSRNET.md]."""
    loss = 1.0 - ssim(out, gt) + w * perceptual(features, out, gt)
    if l1 > 0:
        loss = loss + l1 * (out - gt).abs().mean()
    return loss


def warp_loss(cur, prev_warped, mask=None):
    """L_warp = L1(G(I_n), G(M_r ⊙ I_{n−1})) + L1(I_n, M_r ⊙ I_{n−1}), G 5x5 Gaussian (§5.2.2).

    mask (B,1,H,W), optional: pixels to count (we pass 'p + M_r(p) lies inside the previous frame',
    so zero padding outside the image does not pull the motion; see docs/DSRNET.md)."""
    _check_pair(cur, prev_warped, "warp_loss")
    def blur(x):
        return gaussian_blur(x, WARP_GAUSSIAN_SIZE, 1.0)
    a, b = (cur - prev_warped).abs(), (blur(cur) - blur(prev_warped)).abs()
    if mask is None:
        return b.mean() + a.mean()
    if mask.shape != (cur.shape[0], 1, *cur.shape[2:]):
        raise ValueError(f"warp_loss mask must be {(cur.shape[0], 1, *cur.shape[2:])}, "
                         f"got {tuple(mask.shape)}")
    n = (mask.sum() * cur.shape[1]).clamp(min=1)
    return (b * mask).sum() / n + (a * mask).sum() / n


def build_features(vgg_weights: str = "") -> nn.Module:
    """The conv_i of the perceptual loss: VGG-16 from a user file when given, else FilterBank."""
    if vgg_weights:
        return VGGFeatures(vgg_weights)
    return FilterBank()
