"""DSRNet (Xu et al. 2021 §5.2.1, Fig. 10): supersampling of the view-warping output.

Inputs (low resolution h x w): the current frame I_n (colour) and D_n (z-depth), the previous frame
I_{n-1}, D_{n-1}, and the base motion M_d (from the depths and poses, `warp.depth_motion`).
Output: I_n^f at (scale*h, scale*w).

Modules (Fig. 10):
* feature extraction: two towers of 3x3 convolutions, one for (I_n, D_n) and one for
  (I_{n-1}, D_{n-1}); as in RSSNet (Xiao et al. 2020) the tower output is concatenated with its input.
* MVR, Eq. 16: M_r = M_d + MVR(I_n, I_{n-1}, M_d ⊙ I_{n-1}, M_d); first layer 5x5, the rest 3x3
  (Fig. 10 caption); output limited to [-5, 5] px (§5.2.1) by `limit * tanh`.
* re-weighting: three trainable convolutions on (I_n, M_r ⊙ I_{n-1}) give a per-pixel weight of the
  warped previous features (RSSNet: tanh scaled to [0, 10]).
* reconstruction: a U-Net on the fused features, pixel shuffle to the target resolution.

Deviations (recorded in docs/DSRNET.md): the network predicts a residual on top of the bicubic
upsampling of I_n (`residual=True`, as VDSR does), which makes the small CPU network useful after
minutes of training; LeakyReLU(0.1) and He initialisation (no dead units in short training).
"""
from __future__ import annotations

import contextlib
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import torch
import torch.nn as nn
import torch.nn.functional as F

from ..workspace import atomic_path
from .warp import backward_warp

MVR_LIMIT_PX = 5.0  # §5.2.1: "the output of MVR is limited to [-5, 5] pixels"
REWEIGHT_MAX = 10.0  # RSSNet (Xiao et al. 2020 §4.3): weights in [0, 10]


@dataclass(frozen=True)
class DSRNetConfig:
    scale: int = 2  # supersampling factor (×2: half-resolution render -> full resolution)
    feature_channels: tuple[int, ...] = (16, 16, 8)  # tower convs; the last is the feature count
    mvr_channels: tuple[int, ...] = (16, 16)  # first conv 5x5, then 3x3; a final 3x3 conv -> 2
    reweight_channels: tuple[int, ...] = (16, 16)  # three convs: these two widths, then 1
    unet_channels: tuple[int, ...] = (24, 32, 48)  # U-Net widths per level (full, 1/2, 1/4 ...)
    use_mvr: bool = True  # False: M_r = M_d (Table 3 "W/O MVR")
    mvr_limit: float = MVR_LIMIT_PX
    residual: bool = True  # predict a residual over the bicubic upsampling of I_n (VDSR-style)

    def to_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @staticmethod
    def from_dict(d: dict) -> "DSRNetConfig":
        known = {f for f in DSRNetConfig.__dataclass_fields__}
        kw = {k: tuple(v) if isinstance(v, list) else v for k, v in d.items() if k in known}
        return DSRNetConfig(**kw)


# Channel presets. "cpu": trains on 2 CPU cores within the demo budget (docs/DSRNET.md).
# "paper": the widths of RSSNet (Xiao et al. 2020, Fig. 4), which DSRNet follows (§5.2.1:
# "the architecture of the U-Net and feature extraction towers are standard, which follow those of
# RSSNet"); Fig. 10's own numbers exist only in the figure image.
PRESETS: dict[str, DSRNetConfig] = {
    "cpu": DSRNetConfig(),
    "paper": DSRNetConfig(feature_channels=(32, 32, 8), mvr_channels=(32, 32),
                          reweight_channels=(32, 32), unet_channels=(64, 64, 128)),
}


def _convs(cin: int, widths, first_kernel: int = 3, last_relu: bool = True) -> nn.Sequential:
    layers = []
    for i, c in enumerate(widths):
        k = first_kernel if i == 0 else 3
        layers.append(nn.Conv2d(cin, c, k, padding=k // 2))
        if last_relu or i < len(widths) - 1:
            layers.append(nn.LeakyReLU(0.1, inplace=True))
        cin = c
    return nn.Sequential(*layers)


class FeatureTower(nn.Module):
    """3x3 conv tower; its output is concatenated with its input (RSSNet feature extraction)."""

    def __init__(self, cin: int, widths):
        super().__init__()
        self.body = _convs(cin, widths)
        self.out_channels = cin + widths[-1]

    def forward(self, x):
        return torch.cat([x, self.body(x)], dim=1)


class MVR(nn.Module):
    """Motion-vector rectification (Eq. 16): a bounded correction of M_d."""

    def __init__(self, widths, limit: float):
        super().__init__()
        # inputs: I_n (3), I_{n-1} (3), M_d ⊙ I_{n-1} (3), M_d (2)
        self.body = _convs(11, widths, first_kernel=5)  # Fig. 10: first MVR layer 5x5
        self.out = nn.Conv2d(widths[-1], 2, 3, padding=1)
        self.limit = limit

    def forward(self, cur, prev, prev_warped, flow):
        # M_d enters relative to the image size: a raw 90 px motion would saturate the first layer
        x = torch.cat([cur, prev, prev_warped, flow / max(flow.shape[2:])], dim=1)
        return self.limit * torch.tanh(self.out(self.body(x)))  # within [-5, 5] px (§5.2.1)


class Reweight(nn.Module):
    """Three trainable convolutions on (I_n, M_r ⊙ I_{n-1}) -> weight in [0, 10] (RSSNet)."""

    def __init__(self, widths):
        super().__init__()
        self.body = _convs(6, tuple(widths) + (1,), last_relu=False)

    def forward(self, cur, prev_warped):
        return REWEIGHT_MAX * 0.5 * (torch.tanh(self.body(torch.cat([cur, prev_warped], 1))) + 1)


class UNet(nn.Module):
    """Reconstruction U-Net; the last conv feeds a pixel shuffle to scale x the input size."""

    def __init__(self, cin: int, widths, scale: int):
        super().__init__()
        self.enc = nn.ModuleList()
        c = cin
        for w in widths:
            self.enc.append(_convs(c, (w, w)))
            c = w
        self.dec = nn.ModuleList()
        for w_skip in reversed(widths[:-1]):
            self.dec.append(_convs(c + w_skip, (w_skip, w_skip)))
            c = w_skip
        self.out = nn.Conv2d(c, 3 * scale * scale, 3, padding=1)
        self.shuffle = nn.PixelShuffle(scale)
        self.levels = len(widths)

    def forward(self, x):
        skips = []
        for i, enc in enumerate(self.enc):
            if i > 0:
                x = F.max_pool2d(x, 2)
            x = enc(x)
            skips.append(x)
        for dec, skip in zip(self.dec, reversed(skips[:-1])):
            x = F.interpolate(x, size=skip.shape[2:], mode="bilinear", align_corners=False)
            x = dec(torch.cat([x, skip], dim=1))
        return self.shuffle(self.out(x))


def normalise_depth(depth, ref):
    """Depth divided by the mean valid depth of `ref` per sample (scale-free: SfM units work).

    A sample whose `ref` has no valid depth (a crop that is all hole) falls back to the mean of
    `depth` itself, then to 1: dividing by ~0 there fed values of ~1e6 to the network and made
    single training steps explode on real renders."""
    def mean_valid(x):
        valid = (x > 0).to(x.dtype)
        n = valid.sum(dim=(1, 2, 3), keepdim=True)
        return (x * valid).sum(dim=(1, 2, 3), keepdim=True) / n.clamp(min=1), n > 0

    m_ref, ok_ref = mean_valid(ref)
    m_own, ok_own = mean_valid(depth)
    mean = torch.where(ok_ref, m_ref, torch.where(ok_own, m_own, torch.ones_like(m_ref)))
    return depth / mean.clamp(min=1e-6)


class DSRNet(nn.Module):
    def __init__(self, config: DSRNetConfig = DSRNetConfig()):
        super().__init__()
        if config.scale < 1 or len(config.unet_channels) < 1 or len(config.feature_channels) < 1:
            raise ValueError(f"invalid DSRNet config {config}")
        self.config = config
        fc = config.feature_channels
        self.tower_cur = FeatureTower(4, fc)
        self.tower_prev = FeatureTower(4, fc)
        self.mvr = MVR(config.mvr_channels, config.mvr_limit) if config.use_mvr else None
        self.reweight = Reweight(config.reweight_channels)
        self.unet = UNet(self.tower_cur.out_channels + self.tower_prev.out_channels,
                         config.unet_channels, config.scale)
        self.multiple = 2 ** (len(config.unet_channels) - 1)
        # He initialisation (ReLU nets): PyTorch's default conv init shrinks the signal ~2.5x per
        # layer, which left the 13-layer path with vanishing activations and no learning.
        for mod in self.modules():
            if isinstance(mod, nn.Conv2d):
                nn.init.kaiming_normal_(mod.weight, a=0.1, nonlinearity="leaky_relu")
                nn.init.zeros_(mod.bias)
        heads = [self.unet.out] + ([self.mvr.out] if self.mvr is not None else [])
        for head in heads:  # start at I_f = bicubic(I_n) (with `residual`) and M_r = M_d
            nn.init.zeros_(head.weight)

    def forward(self, cur, depth, prev, depth_prev, flow_d) -> dict:
        """cur/prev (B,3,h,w) linear colour; depth/depth_prev (B,1,h,w) z-depth, 0 = hole;
        flow_d (B,2,h,w) = M_d in pixels. Returns {"image" (B,3,s*h,s*w), "flow" M_r,
        "prev_warped" M_r ⊙ I_{n-1}, "inside" (B,1,h,w), "weight" (B,1,h,w)}."""
        b, _, h, w = cur.shape
        for name, t, c in (("cur", cur, 3), ("depth", depth, 1), ("prev", prev, 3),
                           ("depth_prev", depth_prev, 1), ("flow_d", flow_d, 2)):
            if t.ndim != 4 or t.shape[0] != b or t.shape[1] != c or t.shape[2:] != (h, w):
                raise ValueError(f"DSRNet input {name} must be ({b}, {c}, {h}, {w}), "
                                 f"got {tuple(t.shape)}")
        dn, dp = normalise_depth(depth, depth), normalise_depth(depth_prev, depth)
        flow = flow_d
        if self.mvr is not None:
            warped_d, _ = backward_warp(prev, flow_d)
            flow = flow_d + self.mvr(cur, prev, warped_d, flow_d)  # Eq. 16
        prev_warped, inside = backward_warp(prev, flow)
        f_cur = self.tower_cur(torch.cat([cur, dn], 1))
        f_prev, _ = backward_warp(self.tower_prev(torch.cat([prev, dp], 1)), flow)
        weight = self.reweight(cur, prev_warped) * inside
        fused = torch.cat([f_cur, weight * f_prev], 1)
        # pad to a multiple of the U-Net's total downsampling, crop afterwards
        ph, pw = (-h) % self.multiple, (-w) % self.multiple
        if ph or pw:
            fused = F.pad(fused, (0, pw, 0, ph), mode="replicate")
        s = self.config.scale
        out = self.unet(fused)[:, :, :s * h, :s * w]
        if self.config.residual:
            out = out + F.interpolate(cur, scale_factor=s, mode="bicubic", align_corners=False)
        return {"image": out, "flow": flow, "prev_warped": prev_warped, "inside": inside,
                "weight": weight}


def build_model(config: DSRNetConfig) -> DSRNet:
    return DSRNet(config)


def preset(name: str, **overrides) -> DSRNetConfig:
    if name not in PRESETS:
        raise ValueError(f"unknown DSRNet preset {name!r} (known: {', '.join(PRESETS)})")
    return replace(PRESETS[name], **{k: v for k, v in overrides.items() if v is not None})


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


__all__ = ["DSRNet", "DSRNetConfig", "PRESETS", "preset", "build_model", "count_parameters",
           "normalise_depth"]


# --- the model file and where the model runs ---------------------------------------------------
MODEL_FORMAT = "ibr_pipeline.dsrnet/1"


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ValueError("device 'cuda' requested but torch sees no CUDA device")
    return torch.device(name)


def _busy_jiffies() -> tuple[int, int, int] | None:
    """(busy, total) clock ticks of all cores since boot and the number of cores they cover, from
    /proc/stat (Linux); None elsewhere."""
    try:
        with open("/proc/stat") as f:
            lines = f.read().splitlines()
        fields = [int(x) for x in lines[0].split()[1:]]
    except (OSError, ValueError, IndexError):
        return None
    if len(fields) < 4:
        return None
    ncpu = sum(1 for ln in lines[1:] if ln.startswith("cpu") and ln[3:4].isdigit()) or 1
    idle = fields[3] + (fields[4] if len(fields) > 4 else 0)   # idle + iowait
    return sum(fields[:8]) - idle, sum(fields[:8]), ncpu


def busy_cores(window_s: float = 0.25) -> float | None:
    """Cores kept busy by other processes now: the machine's busy time over `window_s` minus this
    process's own, in cores; None where /proc/stat is missing. A measurement of the present, where
    the 1-minute load average still counts the pipeline's own workers of the stage before."""
    import os

    a, own_a = _busy_jiffies(), os.times()
    if a is None:
        return None
    time.sleep(window_s)
    b, own_b = _busy_jiffies(), os.times()
    if b is None or b[1] <= a[1]:
        return None
    own = (own_b.user + own_b.system) - (own_a.user + own_a.system)   # seconds
    share = (b[0] - a[0]) / (b[1] - a[1])          # of all the cores /proc/stat counts
    return max(0.0, share * b[2] - own / window_s)


def cpu_threads(requested: int = 0) -> int:
    """CPU threads for torch. 0 = auto: the cores other processes leave idle (at least 1):
    OpenMP threads spin-wait, and a 2-thread step was measured 7x slower than a 1-thread step on
    a 2-core machine another job kept busy (docs/DSRNET.md). Where /proc/stat is missing, the
    1-minute load average decides: 1 thread when it is at least the number of cores."""
    import os

    if requested > 0:
        return requested
    cores = os.cpu_count() or 1
    busy = busy_cores()
    if busy is not None:
        return max(1, min(cores, cores - int(round(busy))))
    try:
        loaded = os.getloadavg()[0] >= cores
    except OSError:
        loaded = False
    return 1 if loaded else cores


@contextlib.contextmanager
def torch_threads(n: int):
    old = torch.get_num_threads()
    torch.set_num_threads(max(1, n))
    try:
        yield
    finally:
        torch.set_num_threads(old)


def save_model(path: Path, model: DSRNet, extra: dict | None = None) -> None:
    state = {"format": MODEL_FORMAT, "config": model.config.to_dict(),
             "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()}}
    state.update(extra or {})
    # torch.save(obj, PATH) names the zip archive's records after the file (here the random
    # temporary name of the atomic write), so identical weights gave different bytes on every run;
    # given an open file it names them "archive/..." always.
    with atomic_path(Path(path)) as tmp, open(tmp, "wb") as fh:
        torch.save(state, fh)


def torch_load_reason(e: Exception) -> str:
    """The first sentence of why torch.load(weights_only=True) refused a file. Its messages run to
    several paragraphs and advise weights_only=False, which would run the file's code: never here."""
    first = (str(e).strip().splitlines() or [""])[0].split(". ")[0].rstrip(".")
    return f"{type(e).__name__}: {first}" if first else type(e).__name__


def load_model(path: Path, device="cpu") -> DSRNet:
    from ..errors import InputError
    try:
        state = torch.load(Path(path), map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise InputError(f"{path}: no trained DSRNet (run `ibr supersample` first)") from None
    except Exception as e:  # noqa: BLE001  (corrupt/foreign file: one line for the user)
        raise InputError(f"{path}: cannot read DSRNet weights ({torch_load_reason(e)}); retrain "
                         "with `ibr supersample --force`") from None
    if not isinstance(state, dict) or state.get("format") != MODEL_FORMAT:
        raise InputError(f"{path}: not a DSRNet model file ({MODEL_FORMAT})")
    model = DSRNet(DSRNetConfig.from_dict(state["config"]))
    model.load_state_dict(state["state_dict"])
    return model.to(device).eval()
