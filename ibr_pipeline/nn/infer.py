"""DSRNet inference: `SuperSampler` (API in docs/PIPELINE.md), used by `ibr render --supersample`.

    sampler = SuperSampler.load(ws)            # nn/dsrnet.pt of a workspace
    sampler.reset()                            # start of a new sequence (no previous frame)
    color_hr = sampler(color_lr, depth_lr, camera_lr)

The sampler keeps the previous frame (colour, depth, camera) itself; the base motion M_d (Eq. 16)
is computed from the current depth and the two cameras (`warp.depth_motion`). The first frame of
a sequence uses itself as the previous frame (M_d = 0).
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from .. import layout as L
from ..scene import Camera
from .warp import depth_motion

MODEL_KEY = L.MODEL


def upsample(color: np.ndarray, scale: int, mode: str = "bilinear") -> np.ndarray:
    """Bilinear/bicubic upsampling of (h, w, 3) by `scale` (the baselines), clipped to [0, 1]."""
    import cv2

    interp = {"bilinear": cv2.INTER_LINEAR, "bicubic": cv2.INTER_CUBIC}[mode]
    h, w = color.shape[:2]
    out = cv2.resize(np.asarray(color, np.float32), (w * scale, h * scale), interpolation=interp)
    return np.clip(out, 0.0, 1.0)


def run_network(model, cur, depth, prev, depth_prev, flow, self_ensemble: bool = False):
    """DSRNet's output image (N, 3, sH, sW) for input tensors (N, C, h, w) (no clamping).

    self_ensemble (our addition; the paper does not use it): the mean of the network on the input
    and on its mirror image (every input flipped left-right, the motion's u negated, as the
    training's flip augmentation does), the latter flipped back: one extra forward pass."""
    import torch

    if not self_ensemble:
        return model(cur, depth, prev, depth_prev, flow)["image"]
    mirror = lambda t: torch.flip(t, dims=[3])  # noqa: E731
    sign = torch.tensor([-1.0, 1.0], dtype=flow.dtype, device=flow.device).view(1, 2, 1, 1)
    both = [torch.cat([t, mirror(t)]) for t in (cur, depth, prev, depth_prev)]
    y = model(*both, torch.cat([flow, mirror(flow) * sign]))["image"]
    n = cur.shape[0]
    return 0.5 * (y[:n] + mirror(y[n:]))


class SuperSampler:
    def __init__(self, model, device="cpu", self_ensemble: bool = False):
        import torch
        # channels_last: ~25 % faster convolutions on CPU (measured, docs/DSRNET.md)
        self.model = model.eval().to(memory_format=torch.channels_last)
        self.device = device
        self.self_ensemble = bool(self_ensemble)  # see `run_network`
        self.scale = model.config.scale
        self.last_ms = 0.0
        from .model import cpu_threads
        self.threads = cpu_threads()   # measured once: a frame loop must not pause to measure
        self.reset()

    @staticmethod
    def load(ws, device: str = "auto", self_ensemble: bool = False) -> "SuperSampler":
        """Load a workspace's trained DSRNet (nn/dsrnet.pt); `ws` may also be a .pt path."""
        from .model import load_model, resolve_device

        path = Path(ws) if isinstance(ws, (str, Path)) else ws.path(MODEL_KEY)
        if path.is_dir():
            path = path / MODEL_KEY
        dev = resolve_device(device)
        return SuperSampler(load_model(path, dev), dev, self_ensemble)

    def reset(self) -> None:
        self._prev = None

    def __call__(self, color_lr: np.ndarray, depth_lr: np.ndarray, camera_lr: Camera) -> np.ndarray:
        """(h, w, 3) linear colour + (h, w) z-depth (0 = hole) of a `camera_lr` render ->
        (scale*h, scale*w, 3) float32 in [0, 1]."""
        import torch

        color = np.asarray(color_lr, np.float32)
        depth = np.asarray(depth_lr, np.float32)
        h, w = camera_lr.height, camera_lr.width
        if color.shape != (h, w, 3) or depth.shape != (h, w):
            raise ValueError(f"render must be colour ({h}, {w}, 3) and depth "
                             f"({h}, {w}) for a {w}x{h} camera, got {color.shape}, {depth.shape}")
        if not (np.all(np.isfinite(color)) and np.all(np.isfinite(depth))):
            raise ValueError("render contains NaN or infinite values")
        t0 = time.perf_counter()
        prev = self._prev
        if prev is None or prev[0].shape != color.shape:
            prev = (color, depth, camera_lr)
        flow, _ = depth_motion(depth, camera_lr, prev[2], prev[1])
        t = lambda a: torch.from_numpy(np.ascontiguousarray(  # noqa: E731
            a.transpose(2, 0, 1) if a.ndim == 3 else a[None]))[None].to(self.device).contiguous(
                memory_format=torch.channels_last)
        from .model import torch_threads
        with torch.no_grad(), torch_threads(self.threads):
            out = run_network(self.model, t(color), t(depth), t(prev[0]), t(prev[1]), t(flow),
                              self.self_ensemble)
        result = out.clamp(0, 1)[0].permute(1, 2, 0).float().cpu().numpy()
        self._prev = (color, depth, camera_lr)
        self.last_ms = (time.perf_counter() - t0) * 1000.0
        return result


def prefer_dsrnet(direct_ms: float, dsrnet_ms: float, direct_psnr: float, dsrnet_psnr: float,
                  max_loss_db: float = 0.5) -> tuple[bool, str]:
    """Whether `ibr render --supersample auto` should use DSRNet (Xu et al. §5.2: render at low
    resolution, upsample) rather than render at full resolution, from the two measured on the
    same views: when it is at least as good, or faster while losing at most `max_loss_db`.
    Returns (use it, why)."""
    figures = (f"DSRNet {dsrnet_ms:.1f} ms / {dsrnet_psnr:.2f} dB, full resolution "
               f"{direct_ms:.1f} ms / {direct_psnr:.2f} dB")
    if dsrnet_psnr >= direct_psnr:
        return True, f"{figures}: DSRNet is at least as good"
    if dsrnet_ms < direct_ms and dsrnet_psnr >= direct_psnr - max_loss_db:
        return True, f"{figures}: DSRNet is faster and within {max_loss_db:g} dB"
    why = (["slower"] if dsrnet_ms >= direct_ms else []) + [f"{direct_psnr - dsrnet_psnr:.2f} dB worse"]
    return False, f"{figures}: rendering at full resolution (DSRNet is {' and '.join(why)} here)"
