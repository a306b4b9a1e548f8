"""Small vectorised torch helpers shared by the ray-tree modules (CPU or CUDA, float32).

Conventions (scene.py): OpenCV camera axes, pixel centre of the top-left pixel at (0, 0),
images are (H, W, C) tensors, pixel locations are (..., 2) tensors (x, y) = (u, v).
"""
from __future__ import annotations

import math

import torch


def check(t: torch.Tensor, shape: tuple, name: str) -> None:
    """Raise ValueError unless `t` has `shape` (None = any size in that axis)."""
    if t.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, t.shape)):
        raise ValueError(f"{name} must have shape {shape} (None = any), got {tuple(t.shape)}")


def normalize(v: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    return v / v.norm(dim=-1, keepdim=True).clamp_min(eps)


def reflect(d: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
    """GLSL reflect(I, N) = I - 2 dot(N, I) N (n unit)."""
    return d - 2.0 * (d * n).sum(-1, keepdim=True) * n


def refract(d: torch.Tensor, n: torch.Tensor, eta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """GLSL refract(I, N, eta) for unit I and N (N facing against I): returns (T, tir mask);
    k = 1 - eta^2 (1 - dot(N,I)^2); T = eta I - (eta dot(N,I) + sqrt(k)) N, 0 where k < 0."""
    cos = (d * n).sum(-1, keepdim=True)
    eta = eta.reshape(eta.shape + (1,)) if eta.ndim == d.ndim - 1 else eta
    k = 1.0 - eta * eta * (1.0 - cos * cos)
    tir = k[..., 0] < 0
    out = eta * d - (eta * cos + torch.sqrt(k.clamp_min(0))) * n
    return torch.where(tir[..., None], torch.zeros_like(out), out), tir


def angle(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Angle between vectors (radians), atan2(|a x b|, a.b): accurate near 0."""
    return torch.atan2(torch.linalg.cross(a, b, dim=-1).norm(dim=-1), (a * b).sum(-1))


def project(P: torch.Tensor, X: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel locations (..., 2) and z-depth (...) of world points X (..., 3) under the 3x4
    pixel projection P = K [R | t] ("project" with M_new, §3.4)."""
    h = X @ P[:, :3].T + P[:, 3]
    z = h[..., 2]
    zs = torch.where(z.abs() > 1e-9, z, torch.full_like(z, 1e-9))
    return h[..., :2] / zs.unsqueeze(-1), z


def unproject(K: torch.Tensor, cam_from_world: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
    """(H, W, 3) world positions of every pixel from z-depth (H, W) ("unproject" with M_old,
    §3.3 "Diffuse position")."""
    H, W = depth.shape
    v, u = torch.meshgrid(torch.arange(H, device=depth.device, dtype=depth.dtype),
                          torch.arange(W, device=depth.device, dtype=depth.dtype), indexing="ij")
    x = (u - K[0, 2]) / K[0, 0]
    y = (v - K[1, 2]) / K[1, 1]
    cam = torch.stack([x * depth, y * depth, depth], -1)
    R, t = cam_from_world[:3, :3], cam_from_world[:3, 3]
    return (cam - t) @ R  # R^T (x - t)


def gaussian_kernel(ksize: int, sigma: float, device, dtype=torch.float32) -> torch.Tensor:
    if sigma <= 0:  # OpenCV's default sigma for a ksize kernel (cv2.getGaussianKernel)
        sigma = 0.3 * ((ksize - 1) * 0.5 - 1) + 0.8
    x = torch.arange(ksize, device=device, dtype=dtype) - (ksize - 1) / 2
    k = torch.exp(-x * x / (2 * sigma * sigma))
    return k / k.sum()


def blur_masked(img: torch.Tensor, mask: torch.Tensor, ksize: int = 7, sigma: float = 0.0) -> torch.Tensor:
    """Separable Gaussian blur of (H, W, C) over the pixels where mask (H, W) is true
    (normalised convolution: invalid pixels neither contribute nor get diluted)."""
    k = gaussian_kernel(ksize, sigma, img.device, img.dtype)
    m = mask.to(img.dtype)[None, None]
    x = torch.cat([img.permute(2, 0, 1)[None] * m, m], 1)  # (1, C+1, H, W)
    C = x.shape[1]
    pad = ksize // 2
    x = torch.nn.functional.conv2d(torch.nn.functional.pad(x, (pad, pad, 0, 0), mode="replicate"),
                                   k.view(1, 1, 1, -1).expand(C, 1, 1, ksize), groups=C)
    x = torch.nn.functional.conv2d(torch.nn.functional.pad(x, (0, 0, pad, pad), mode="replicate"),
                                   k.view(1, 1, -1, 1).expand(C, 1, ksize, 1), groups=C)
    return (x[0, :-1] / x[0, -1:].clamp_min(1e-8)).permute(1, 2, 0)


class Sampler:
    """Bilinear sampling of (H, W, C) images at continuous pixel locations, aware of validity
    and depth discontinuities: a location is `smooth` when its 4 taps are valid and their
    `key` depths agree within `rel_tol`; elsewhere the nearest valid tap is returned."""

    def __init__(self, valid: torch.Tensor, key: torch.Tensor, rel_tol: float = 0.05):
        check(valid, (None, None), "valid")
        check(key, tuple(valid.shape), "key")
        self.H, self.W = valid.shape
        self.valid = valid.reshape(-1)
        self.key = key.reshape(-1)
        self.rel_tol = rel_tol

    def taps(self, q: torch.Tensor):
        """Tap indices (N, 4), weights (N, 4), tap validity (N, 4), smooth (N,), nearest (N,)."""
        x = q[..., 0].clamp(0, self.W - 1)
        y = q[..., 1].clamp(0, self.H - 1)
        x0 = x.floor().clamp(max=self.W - 2 if self.W > 1 else 0)
        y0 = y.floor().clamp(max=self.H - 2 if self.H > 1 else 0)
        fx, fy = x - x0, y - y0
        x0, y0 = x0.long(), y0.long()
        x1 = (x0 + 1).clamp(max=self.W - 1)
        y1 = (y0 + 1).clamp(max=self.H - 1)
        idx = torch.stack([y0 * self.W + x0, y0 * self.W + x1, y1 * self.W + x0, y1 * self.W + x1], -1)
        w = torch.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], -1)
        tv = self.valid[idx]
        kk = self.key[idx]
        kmax = torch.where(tv, kk, torch.full_like(kk, -math.inf)).amax(-1)
        kmin = torch.where(tv, kk, torch.full_like(kk, math.inf)).amin(-1)
        inside = (q[..., 0] >= -0.5) & (q[..., 0] <= self.W - 0.5) & (q[..., 1] >= -0.5) & \
                 (q[..., 1] <= self.H - 0.5)
        smooth = tv.all(-1) & (kmax - kmin <= self.rel_tol * kmin.abs().clamp_min(1e-6)) & inside
        # nearest valid tap (by weight); none valid -> -1
        wn = torch.where(tv, w, torch.full_like(w, -1.0))
        best = wn.argmax(-1, keepdim=True)
        nearest = idx.gather(-1, best)[..., 0]
        nearest = torch.where(tv.any(-1) & inside, nearest, torch.full_like(nearest, -1))
        return idx, w, tv, smooth, nearest

    def sample(self, img: torch.Tensor, q: torch.Tensor, taps=None):
        """(values (N, C), smooth (N,), defined (N,)): bilinear where smooth, else nearest."""
        idx, w, tv, smooth, nearest = self.taps(q) if taps is None else taps
        flat = img.reshape(self.H * self.W, -1)
        bil = (flat[idx] * w[..., None]).sum(-2)
        near = flat[nearest.clamp_min(0)]
        return torch.where(smooth[..., None], bil, near), smooth, nearest >= 0


def fresnel_dielectric(cos_i: torch.Tensor, eta: torch.Tensor) -> torch.Tensor:
    """Unpolarised Fresnel reflectance, eta = n_from / n_to (same formulae as
    synthetic.materials.fresnel_dielectric)."""
    rs, rp = _rs_rp(cos_i, eta)
    return 0.5 * (rs + rp)


def fresnel_pane(cos_i: torch.Tensor, ior: torch.Tensor) -> torch.Tensor:
    """Thin-sheet reflectance 2R/(1+R) per polarisation (synthetic.materials.fresnel_pane)."""
    rs, rp = _rs_rp(cos_i, 1.0 / ior)
    return 0.5 * (2 * rs / (1 + rs) + 2 * rp / (1 + rp))


def _rs_rp(cos_i: torch.Tensor, eta: torch.Tensor):
    cos_i = cos_i.abs().clamp(0, 1)
    sin_t2 = eta * eta * (1 - cos_i * cos_i)
    tir = sin_t2 >= 1
    cos_t = (1 - sin_t2).clamp_min(0).sqrt()
    rs = (eta * cos_i - cos_t) / (eta * cos_i + cos_t).clamp_min(1e-12)
    rp = (eta * cos_t - cos_i) / (eta * cos_t + cos_i).clamp_min(1e-12)
    one = torch.ones_like(cos_i)
    return torch.where(tir, one, rs * rs), torch.where(tir, one, rp * rp)


def sync(device) -> None:
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()
