"""Small vectorised torch helpers shared by the ray-tree modules (CPU or CUDA, float32).

Conventions (scene.py): OpenCV camera axes, pixel centre of the top-left pixel at (0, 0),
images are (H, W, C) tensors, pixel locations are (..., 2) tensors (x, y) = (u, v).
"""
from __future__ import annotations


import torch


def check(t: torch.Tensor, shape: tuple, name: str) -> None:
    """Raise ValueError unless `t` has `shape` (None = any size in that axis)."""
    if t.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, t.shape)):
        raise ValueError(f"{name} must have shape {shape} (None = any), got {tuple(t.shape)}")


def normalize(v: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """v / |v| over the last axis (3-vectors: fused multiply-adds on the 3 planes and one
    rsqrt, ~1.5x faster on CPU than v.norm(dim=-1))."""
    if v.shape[-1] != 3 or v.is_complex():
        return v / v.norm(dim=-1, keepdim=True).clamp_min(eps)
    x, y, z = v.unbind(-1)
    s = (x * x).addcmul_(y, y).addcmul_(z, z).clamp_min_(eps * eps).rsqrt_()
    return v * s.unsqueeze(-1)


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
    (normalised convolution: invalid pixels neither contribute nor get diluted), replicate
    border. The C + 1 channels are filtered as shifted weighted sums of slices (ksize
    multiply-adds per axis: ~10x faster on CPU than a 1-channel conv2d, same on CUDA)."""
    k = gaussian_kernel(ksize, sigma, img.device, img.dtype).tolist()
    m = mask.to(img.dtype)
    x = torch.cat([(img * m[..., None]).permute(2, 0, 1), m[None]], 0)  # (C+1, H, W)
    pad = ksize // 2
    H, W = mask.shape
    F = torch.nn.functional
    xp = F.pad(x[None], (pad, pad, 0, 0), mode="replicate")[0]
    x = xp[..., 0:W] * k[0]
    for j in range(1, ksize):
        x.add_(xp[..., j:j + W], alpha=k[j])
    xp = F.pad(x[None], (0, 0, pad, pad), mode="replicate")[0]
    x = xp[:, 0:H] * k[0]
    for j in range(1, ksize):
        x.add_(xp[:, j:j + H], alpha=k[j])
    return (x[:-1] / x[-1:].clamp_min(1e-8)).permute(1, 2, 0)


def bbox(mask: torch.Tensor, margin: int = 0) -> tuple[int, int, int, int] | None:
    """(y0, y1, x0, x1) slice bounds of the true pixels of (H, W) mask grown by `margin`
    (clipped to the image), or None when the mask is empty."""
    rows = torch.nonzero(mask.any(1))
    if len(rows) == 0:
        return None
    cols = torch.nonzero(mask.any(0))
    H, W = mask.shape
    return (max(int(rows[0]) - margin, 0), min(int(rows[-1]) + 1 + margin, H),
            max(int(cols[0]) - margin, 0), min(int(cols[-1]) + 1 + margin, W))


class Taps:
    """Bilinear taps of N continuous locations q (N, 2): top-left index i0 (N,), fractional
    offsets fx, fy (N,), `smooth` (N,) (4 valid taps without a depth / label discontinuity,
    inside the image) and `nearest` (N,) (the nearest valid tap, -1 if none / outside).
    The 4 tap indices `idx` (N, 4) (order 00, 10, 01, 11) and weights `w` (N, 4) are derived
    on demand."""
    __slots__ = ("q", "i0", "fx", "fy", "smooth", "nearest", "offs")
    _rows = ("q", "i0", "fx", "fy", "smooth", "nearest")

    def __init__(self, q, i0, fx, fy, smooth, nearest, offs):
        self.q, self.i0, self.fx, self.fy, self.smooth, self.nearest, self.offs = \
            q, i0, fx, fy, smooth, nearest, offs

    @property
    def idx(self) -> torch.Tensor:
        return self.i0[..., None] + self.offs

    @property
    def w(self) -> torch.Tensor:
        fx, fy = self.fx, self.fy
        gx, gy = 1 - fx, 1 - fy
        return torch.stack([gx * gy, fx * gy, gx * fy, fx * fy], -1)

    def __getitem__(self, sel) -> "Taps":
        return Taps(*(getattr(self, k)[sel] for k in self._rows), self.offs)

    @staticmethod
    def cat(parts: list["Taps"]) -> "Taps":
        return Taps(*(torch.cat([getattr(p, k) for p in parts]) for k in Taps._rows), parts[0].offs)

    def __iter__(self):  # backwards compatible unpacking: idx, w, tap validity (None), smooth, nearest
        return iter((self.idx, self.w, None, self.smooth, self.nearest))



def cell(qx, qy, W: int, H: int):
    """Bilinear cell of locations (qx, qy) in a W x H grid: flat index of its top-left tap (M,),
    fractions fx, fy (M,) and `inside` (M,) (within half a pixel of the grid)."""
    xc, yc = qx.clamp(0, W - 1), qy.clamp(0, H - 1)
    x0 = xc.floor().clamp_(max=max(W - 2, 0))
    y0 = yc.floor().clamp_(max=max(H - 2, 0))
    inside = (qx >= -0.5) & (qx <= W - 0.5) & (qy >= -0.5) & (qy <= H - 0.5)
    return (y0 * W + x0).long(), xc - x0, yc - y0, inside

class Sampler:
    """Bilinear sampling of (H, W, C) images at continuous pixel locations, aware of validity
    and depth discontinuities: a location is `smooth` when its 4 taps are valid and their
    `key` depths agree within `rel_tol`; elsewhere the nearest valid tap is returned.

    The smoothness of every 2x2 quad is precomputed once (one pass over the image), so a
    lookup costs one gather instead of four validity / depth gathers and a min / max."""

    def __init__(self, valid: torch.Tensor, key: torch.Tensor, rel_tol: float = 0.05,
                 label: torch.Tensor | None = None, slack: torch.Tensor | None = None):
        """label (H, W) int, optional: a quad whose 4 labels differ (e.g. a diffuse wall next to
        a flush mirror: same depth, different ray-tree nodes) is not smooth either, so colour
        and node bits are then read from the same (nearest) pixel, never blended across."""
        check(valid, (None, None), "valid")
        check(key, tuple(valid.shape), "key")
        self.H, self.W = valid.shape
        self.valid = valid.reshape(-1)
        self.rel_tol = rel_tol
        # quad_ok[y, x]: pixels (x..x+1, y..y+1) all valid, key spread <= rel_tol * min key
        v = torch.nn.functional.pad(valid[None, None].to(torch.uint8), (0, 1, 0, 1), mode="replicate")[0, 0] > 0
        k = torch.nn.functional.pad(key[None, None].to(torch.float32), (0, 1, 0, 1), mode="replicate")[0, 0]
        if self.W == 1:
            v, k = v[:, :1].expand(-1, 2), k[:, :1].expand(-1, 2)
        if self.H == 1:
            v, k = v[:1].expand(2, -1), k[:1].expand(2, -1)
        a, b, c, d = k[:-1, :-1], k[:-1, 1:], k[1:, :-1], k[1:, 1:]
        kmin = torch.minimum(torch.minimum(a, b), torch.minimum(c, d))
        kmax = torch.maximum(torch.maximum(a, b), torch.maximum(c, d))
        ok = v[:-1, :-1] & v[:-1, 1:] & v[1:, :-1] & v[1:, 1:]
        if label is not None:
            check(label, tuple(valid.shape), "label")
            lb = torch.nn.functional.pad(label[None, None].to(torch.float32), (0, 1, 0, 1),
                                         mode="replicate")[0, 0]
            if self.W == 1:
                lb = lb[:, :1].expand(-1, 2)
            if self.H == 1:
                lb = lb[:1].expand(2, -1)
            a0 = lb[:-1, :-1]
            ok = ok & (lb[:-1, 1:] == a0) & (lb[1:, :-1] == a0) & (lb[1:, 1:] == a0)
        tol = rel_tol * kmin.abs().clamp_min(1e-6)
        if slack is not None:   # (H, W) extra relative tolerance per quad (top-left pixel)
            check(slack, tuple(valid.shape), "slack")
            tol = tol[:self.H, :self.W] + slack * kmax.abs()[:self.H, :self.W]
            kmax, kmin = kmax[:self.H, :self.W], kmin[:self.H, :self.W]
            ok = ok[:self.H, :self.W]
        self.quad_ok = (ok & (kmax - kmin <= tol))[:self.H, :self.W].reshape(-1)
        dev = valid.device
        dx = 1 if self.W > 1 else 0
        dy = self.W if self.H > 1 else 0
        self.offs = torch.tensor([0, dx, dy, dy + dx], device=dev)

    def taps(self, q: torch.Tensor) -> Taps:
        i0, fx, fy, inside = cell(q[..., 0], q[..., 1], self.W, self.H)
        smooth = self.quad_ok[i0] & inside
        # nearest tap: the heaviest one; where not smooth, the heaviest *valid* one (or -1)
        nearest = i0 + (fx >= 0.5).long() * self.offs[1] + (fy >= 0.5).long() * self.offs[2]
        t = Taps(q, i0, fx, fy, smooth, nearest, self.offs)
        rough = torch.nonzero(~smooth).squeeze(-1)
        if len(rough):
            tr = t[rough]
            ir, wr = tr.idx, tr.w
            tv = self.valid[ir]
            best = torch.where(tv, wr, torch.full_like(wr, -1.0)).argmax(-1, keepdim=True)
            nr = ir.gather(-1, best)[..., 0]
            nearest[rough] = torch.where(tv.any(-1) & inside[rough], nr, torch.full_like(nr, -1))
        return t

    def chw(self, img: torch.Tensor) -> torch.Tensor:
        """(H, W, C) -> the (1, C, H, W) layout `sample` reads fastest (cache it when reused)."""
        return img.reshape(self.H, self.W, -1).permute(2, 0, 1)[None].contiguous()

    def sample(self, img: torch.Tensor, q: torch.Tensor | None = None, taps: Taps | None = None):
        """(values (N, C), smooth (N,), defined (N,)): bilinear where smooth (F.grid_sample at
        the continuous location), else the nearest valid tap. img: (H, W, C), (H*W, C) or the
        (1, C, H, W) layout of `chw`."""
        t = self.taps(q) if taps is None else taps
        x = img if img.ndim == 4 else self.chw(img)
        C = x.shape[1]
        q = t.q
        gx = q[:, 0] * (2.0 / (self.W - 1)) - 1 if self.W > 1 else torch.zeros_like(q[:, 0])
        gy = q[:, 1] * (2.0 / (self.H - 1)) - 1 if self.H > 1 else torch.zeros_like(q[:, 1])
        grid = torch.stack([gx, gy], -1).view(1, 1, -1, 2)
        out = torch.nn.functional.grid_sample(x, grid, mode="bilinear", padding_mode="border",
                                              align_corners=True)[0, :, 0].T.contiguous()
        rough = torch.nonzero(~t.smooth).squeeze(-1)
        if len(rough):
            flat = x[0].reshape(C, -1)
            out[rough] = flat[:, t.nearest[rough].clamp_min(0)].T
        return out, t.smooth, t.nearest >= 0


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
