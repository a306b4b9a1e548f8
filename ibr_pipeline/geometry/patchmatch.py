"""Multi-scale PatchMatch multi-view stereo in torch (CPU; CUDA with device="cuda").

Why not the plane sweep of `mvs.py`: a fronto-parallel window does not fit a slanted surface seen
at an angle, and winner-takes-all over fixed depths has no spatial coherence, so much of a real
capture stays unmatched. PatchMatch stereo (Bleyer et al. 2011; Galliani et al. 2015 "Gipuma";
Schönberger et al. 2016 "COLMAP"; Xu & Tao 2019 "ACMM") keeps one slanted plane per pixel and
lets good planes spread:

* hypothesis = z-depth d + camera-frame unit normal n facing the camera; the plane n.X = rho
  (rho = d n.K^-1 p) induces H = K_s (R + t n^T / rho) K_r^-1, so the whole window is warped into
  each source (slanted surfaces match);
* init: depth uniform in inverse depth inside the range, random normals (PatchMatch's random
  search: among many pixels some start close to the truth);
* red/black (checkerboard) sweeps (Gipuma): all pixels of one colour are updated at once from
  the other colour, which is what makes the method parallel; neighbours by ACMM's adaptive
  checkerboard sampling: in each of 4 near "V" areas and 4 far strips the lowest-cost neighbour
  lends its plane (re-intersected with this pixel's ray);
* refinement (COLMAP/ACMM): random and perturbed depths/normals around the current best, the
  perturbation halved every sweep (coarse-to-fine search in hypothesis space);
* cost: 1 - bilateral-weighted NCC of the grey window (ACMM), sampled with stride `window_step`
  (Gipuma's sparse window: the same footprint for a third of the samples); the best
  `sources_k_best` sources are averaged (occlusion robustness, Kang et al. 2001);
* multi-scale (ACMM): an image pyramid solved coarse first; each fine pixel starts from the best
  (at the fine level) of its 4 nearest coarse planes, a photometric joint upsampling, so weak
  texture gets the coarse level's larger context;
* geometric consistency (COLMAP/ACMM): once every view has a depth map, extra sweeps add
  geom_weight x min(forward-backward reprojection error, geom_max_px) to each source's cost;
  `patchmatch_views` then keeps the pixels that `filter_min_views` source depth maps confirm.

Scale: translations and depths are divided by sqrt(depth_min x depth_max) inside and tolerances
are relative depths or pixels, so a scene in millimetres gives the depth maps of the same scene in
metres. Conventions are those of `scene.py`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Sequence

import numpy as np

from ..config import Options, param
from ..errors import ConfigError
from ..scene import Camera
from .mvs import geometric_consistency, torch_device

if TYPE_CHECKING:  # torch is imported where it is used (fast CLI start)
    import torch

MAX_COST = 2.0     # 1 - NCC lies in [0, 2]; the cost of a pixel no source sees
FLAT_VAR = 1e-5    # grey-level variance (values in [0, 1]) below which a window counts as flat
_UNSEEN = 1e3      # per-source sentinel: the hypothesis does not project into that source
_EPS = 1e-6        # z clamp in range-relative units (scale-free)


@dataclass(frozen=True)
class PatchMatchOptions(Options):
    """PatchMatch MVS (module docstring); depths are relative to each view's given range."""

    iterations: int = param(2, "red/black propagation + refinement sweeps per level", min=1, max=20)
    levels: int = param(2, "pyramid levels below the working size, solved coarse to fine (ACMM); "
                        "0 = single scale", min=0, max=6)
    window: int = param(7, "odd NCC window side in pixels (at every level)", min=3, max=31)
    window_step: int = param(2, "stride of the NCC window samples (2 = Gipuma/ACMM sparse window, "
                             "1 = every pixel: ~3x slower)", min=1, max=4)
    sources_k_best: int = param(2, "best K source costs averaged (occlusions)", min=1, max=32)
    bilateral_sigma: float = param(0.2, "grey-level scale of the bilateral NCC weights (ACMM); "
                                   "0 = plain NCC", min=0.0, max=10.0)
    perturbation: float = param(0.1, "first refinement step: depth x (1 +- p), normal moved by ~p "
                                "radians; halved every sweep", min=0.0, max=1.0)
    geom_weight: float = param(0.2, "weight of the geometric (forward-backward reprojection) term "
                               "added to each source's 1 - NCC (ACMM/COLMAP)", min=0.0, max=10.0)
    geom_max_px: float = param(3.0, "reprojection error (px) saturating the geometric term",
                               min=0.1, max=100.0)
    geom_iterations: int = param(1, "patchmatch_views: extra red/black sweeps of every view with "
                                 "the geometric term once every view has a depth", min=0, max=20)
    max_cost: float = param(0.6, "aggregated photometric cost (1 - NCC) above this -> invalid "
                            "(depth 0)", min=0.0, max=2.0)
    max_grazing_deg: float = param(80.0, "normals are kept within this angle of the viewing ray "
                                   "(steeper planes give degenerate homographies)",
                                   min=10.0, max=89.0)
    filter_min_views: int = param(1, "final filter of patchmatch_views: source depth maps that "
                                  "must confirm a pixel (0 = no filter)", min=0, max=32)
    filter_rel_depth: float = param(0.02, "final filter: relative depth tolerance", min=0.0, max=1.0)
    filter_reproj_px: float = param(1.0, "final filter: reprojection tolerance in pixels",
                                    min=0.0, max=100.0)
    warp: str = param("affine", "window warp: 'homography' (exact per sample) or 'affine' (its "
                      "first-order expansion about the window centre: ~0.01 px off at a focal "
                      "length of 280 px, 1.3x faster on a CPU)", choices=("affine", "homography"))
    chunk: int = param(1 << 17, "hypotheses (pixel x candidate) evaluated at once; memory ~ chunk "
                       "x window samples x 40 bytes", min=1024, max=1 << 26, affects_output=False)

    def check(self, prefix: str) -> None:
        if self.window % 2 == 0:
            raise ConfigError(prefix + "window", f"must be odd, got {self.window}")
        if self.window_step > self.window // 2:
            raise ConfigError(prefix + "window_step", f"must be <= window // 2 = "
                              f"{self.window // 2}, got {self.window_step}")


@dataclass
class PatchMatchResult:
    """depth (H, W) float32 z-depth, 0 = invalid; normal (H, W, 3) float32 camera-frame unit
    normal (0 where invalid); cost (H, W) float32 aggregated photometric cost (1 - NCC) of every
    pixel's final hypothesis (also where invalid)."""

    depth: np.ndarray
    normal: np.ndarray
    cost: np.ndarray

    @property
    def valid(self) -> np.ndarray:
        return self.depth > 0


# --- pure maths ---------------------------------------------------------------------------------
def window_offsets(window: int, step: int) -> np.ndarray:
    """(n, 2) integer (dx, dy) sample offsets of a window x window patch taken with stride
    `step` (Gipuma's sparse window: window 7, step 2 -> 4 x 4 samples at -3, -1, 1, 3)."""
    a = np.arange(-(window // 2), window // 2 + 1, step, dtype=np.float64)
    a -= np.floor((a[0] + a[-1]) / 2)  # centred (to within a pixel) when step does not divide
    dx, dy = np.meshgrid(a, a)
    return np.stack([dx.ravel(), dy.ravel()], 1)


def plane_warp(A: "torch.Tensor", b: "torch.Tensor", kinv: "torch.Tensor", pix: "torch.Tensor",
               depth: "torch.Tensor", normal: "torch.Tensor", offsets: "torch.Tensor",
               exact: bool = True):
    """Source coordinates of window samples under plane-induced homographies.

    A (3, 3) = F K_s R K_r^-1 and b (3,) = F K_s t for the source-from-reference motion (R, t) and
    any left factor F (identity: pixels; a fold into grid_sample's [-1, 1]); kinv (3, 3) = K_r^-1;
    pix (P, 2) reference pixels; depth (h, P) z-depths and normal (h, P, 3): h hypotheses for
    each pixel; offsets (n, 2) window offsets. Returns (centre (h, P, 3) homogeneous coordinates
    of the pixels themselves; samples (n, h, P, 2) the coordinates of p + offset).
    The plane n.X = rho through X = d K^-1 p gives H = A + b g^T with g = K_r^-T n / rho and
    g.p = 1 / d, so H (p + o) = (A p + b / d) + o_x H_0 + o_y H_1 with the columns
    H_k = A_k + b g_k: no per-sample matrix product. exact=False: the first-order (affine)
    expansion of the homography about the centre, x_c + J o with J = d(x / z)/do: it drops terms
    of order |o|^2 / f (median 0.01 px, at most ~0.07 px for an 11-px window at f = 280 px and a
    13-degree baseline) and skips the per-sample division, the costliest step on a CPU.
    """
    import torch
    centre, origin, d0, d1, homogeneous = plane_warp_terms(A, b, kinv, pix, depth, normal,
                                                           offsets, exact)
    ox, oy = offsets[:, 0, None, None, None], offsets[:, 1, None, None, None]
    X = torch.addcmul(origin, ox, d0).addcmul_(oy, d1)                 # (n, h, P, 3 or 2)
    return centre, (X[..., :2] / X[..., 2:].clamp_min_(_EPS) if homogeneous else X)


def plane_warp_terms(A, b, kinv, pix, depth, normal, offsets, exact: bool = True):
    """The per-hypothesis terms of `plane_warp`: sample o of hypothesis (h, P) lies at
    origin + o_x d0 + o_y d1, homogeneous (divide by the third coordinate) when exact, pixel
    coordinates when affine. Returns (centre, origin, d0, d1, homogeneous); one offset at a time
    (`offset_samples`) needs no (n, h, P, 2) tensor."""
    h, P = depth.shape
    if normal.shape != (h, P, 3) or pix.shape != (P, 2) or offsets.ndim != 2 or offsets.shape[1] != 2:
        raise ValueError(f"plane_warp: pix (P, 2), depth (h, P), normal (h, P, 3), offsets "
                         f"(n, 2) expected, got {tuple(pix.shape)}, {tuple(depth.shape)}, "
                         f"{tuple(normal.shape)}, {tuple(offsets.shape)}")
    ray = pix @ kinv[:, :2].T + kinv[:, 2]                             # K^-1 p~ (P, 3)
    inv_d = (1.0 / depth)[..., None]
    centre = (pix @ A[:, :2].T + A[:, 2]) + b * inv_d                  # (h, P, 3)
    g = (normal @ kinv[:, :2]) * inv_d / (normal * ray).sum(-1, keepdim=True)  # rho = d n.ray
    H0 = A[:, 0] + b * g[..., :1]
    H1 = A[:, 1] + b * g[..., 1:]
    if exact:
        return centre, centre, H0, H1, True
    rz = 1.0 / centre[..., 2:].clamp_min(_EPS)
    xc = centre[..., :2] * rz
    J0 = (H0[..., :2] - xc * H0[..., 2:]) * rz
    J1 = (H1[..., :2] - xc * H1[..., 2:]) * rz
    return centre, xc, J0, J1, False


def offset_samples(terms, ox: float, oy: float):
    """(h, P, 2) source coordinates of the window sample at offset (ox, oy) (`plane_warp_terms`)."""
    import torch
    _, origin, d0, d1, homogeneous = terms
    X = torch.add(origin, d0, alpha=ox).add_(d1, alpha=oy)
    return X[..., :2] / X[..., 2:].clamp_min_(_EPS) if homogeneous else X


def best_k_mean(costs: "torch.Tensor", k: int) -> "torch.Tensor":
    """Mean of the k smallest per-source costs (S, ...) -> (...); entries >= _UNSEEN (source does
    not see the hypothesis) are left out, MAX_COST where no source sees it."""
    import torch
    k = min(k, costs.shape[0])
    best = costs if k == costs.shape[0] else torch.topk(costs, k, dim=0, largest=False).values
    seen = best < _UNSEEN
    n = seen.sum(0)
    mean = torch.where(seen, best, torch.zeros((), device=best.device)).sum(0) / n.clamp_min(1)
    return torch.where(n > 0, mean, torch.full_like(mean, MAX_COST))


def face_camera(normal: "torch.Tensor", view: "torch.Tensor", cos_min: float) -> "torch.Tensor":
    """Unit normals (..., 3) turned towards the camera (n.v < 0 for the unit ray v) and, where
    they are within acos(cos_min) of edge-on, rotated towards -v to exactly that angle (a plane
    seen edge-on has no usable homography)."""
    import torch
    n = normal / normal.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    d = (n * view).sum(-1, keepdim=True)
    n = torch.where(d > 0, -n, n)
    d = -d.abs()
    t = n - d * view                                       # the part across the ray
    t = t / t.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return torch.where(-d < cos_min, -cos_min * view + math.sqrt(1.0 - cos_min ** 2) * t, n)


# ACMM's adaptive checkerboard sampling areas, (dy, dx) of the other colour: 4 "V"-shaped near
# areas (7 pixels) and 4 far strips (11 pixels, every second pixel from 3 to 23 away).
_NEAR_UP = [(-1, 0)] + [(-(i + 2), s * (i + 1)) for i in range(3) for s in (-1, 1)]
_FAR_UP = [(-(3 + 2 * i), 0) for i in range(11)]


def _sampling_areas() -> np.ndarray:
    """(8, 11, 2) offsets (dy, dx); near areas are padded with repeats of their first entry."""
    areas = []
    for base in (_NEAR_UP, _FAR_UP):
        for rot in ((1, 0, 0, 1), (-1, 0, 0, -1), (0, 1, 1, 0), (0, -1, -1, 0)):  # up down left right
            pts = [(rot[0] * dy + rot[1] * dx, rot[2] * dy + rot[3] * dx) for dy, dx in base]
            areas.append(pts + [pts[0]] * (11 - len(pts)))
    return np.asarray(areas, dtype=np.int64)


_AREAS = _sampling_areas()
_PAD = int(np.abs(_AREAS).max())  # 23: the far strips' reach


# --- one reference view and its sources at one resolution -----------------------------------------
class _Matcher:
    """Reference window statistics and per-source projections; `cost` scores hypotheses."""

    def __init__(self, ref_gray, ref_cam, srcs, scale, opts: PatchMatchOptions, dev):
        import torch
        self.torch, self.dev, self.opts = torch, dev, opts
        self.H, self.W = H, W = ref_gray.shape
        f32 = dict(dtype=torch.float32, device=dev)
        Kr_inv = np.linalg.inv(ref_cam.K)
        self.kinv = torch.as_tensor(Kr_inv, **f32)
        u, v = np.meshgrid(np.arange(W), np.arange(H))
        self.pix = torch.as_tensor(np.stack([u.ravel(), v.ravel()], 1), **f32)  # (HW, 2)
        self.ray = self.pix @ self.kinv[:, :2].T + self.kinv[:, 2]           # z = 1 rays (HW, 3)
        self.view = self.ray / self.ray.norm(dim=1, keepdim=True)
        offs = window_offsets(opts.window, opts.window_step)
        self.offsets = torch.as_tensor(offs, **f32)
        self.offset_list = [(float(x), float(y)) for x, y in offs]   # the cost loop's scalars
        # reference windows (edge replicated) and their bilateral weights, centred and normalised
        # once: NCC's reference half does not depend on the hypothesis
        g = torch.as_tensor(ref_gray - 0.5, **f32)
        oi = self.offsets.long()
        iy = torch.arange(H, device=dev)[:, None, None] + oi[:, 1]          # (H, 1, n)
        ix = torch.arange(W, device=dev)[None, :, None] + oi[:, 0]          # (1, W, n)
        inside = ((iy >= 0) & (iy < H) & (ix >= 0) & (ix < W)).reshape(H * W, -1)
        r = g[iy.clamp(0, H - 1), ix.clamp(0, W - 1)].reshape(H * W, -1)   # (HW, n)
        # samples outside the reference image get no weight (their source samples would see
        # something else than the replicated edge)
        w = torch.exp(-(self.offsets ** 2).sum(1) / (2.0 * (opts.window / 2.0) ** 2)) * inside
        if opts.bilateral_sigma > 0:
            w = w * torch.exp(-(r - g.reshape(-1, 1)) ** 2 / (2.0 * opts.bilateral_sigma ** 2))
        w = w / w.sum(1, keepdim=True)
        rc = r - (w * r).sum(1, keepdim=True)
        var = (w * rc * rc).sum(1, keepdim=True)
        self.flat = var[:, 0] < FLAT_VAR
        self.w = w.T.contiguous()                                         # (n, HW)
        self.wr = (w * rc / var.clamp_min(FLAT_VAR).sqrt()).T.contiguous()
        self.sources = []
        for gray, cam, depth in srcs:
            h, w_ = gray.shape
            rel = cam.cam_from_world @ ref_cam.world_from_cam
            R, t = rel[:3, :3], rel[:3, 3] / scale
            A, b = cam.K @ R @ Kr_inv, cam.K @ t
            ax, ay = 2.0 / max(w_ - 1, 1), 2.0 / max(h - 1, 1)
            fold = np.array([[ax, 0, -1], [0, ay, -1], [0, 0, 1]])   # pixels -> grid_sample coords
            src = dict(img=torch.as_tensor(gray - 0.5, **f32)[None, None],
                       A=torch.as_tensor(fold @ A, **f32), b=torch.as_tensor(fold @ b, **f32),
                       lim=(1.0 + 0.5 * ax, 1.0 + 0.5 * ay), depth=None)
            if depth is not None:
                # forward-backward: source pixel x at source depth D -> ref pixel ~ D B x~ + beta
                Rt = R.T
                src.update(depth=torch.as_tensor(depth / scale, **f32), size=(h, w_),
                           Ap=torch.as_tensor(A, **f32), bp=torch.as_tensor(b, **f32),
                           B=torch.as_tensor(ref_cam.K @ Rt @ np.linalg.inv(cam.K), **f32),
                           beta=torch.as_tensor(-ref_cam.K @ Rt @ t, **f32))
            self.sources.append(src)

    def cost(self, idx: "torch.Tensor", depth: "torch.Tensor", normal: "torch.Tensor",
             geom: bool = True) -> "torch.Tensor":
        """Aggregated cost (P, h) of hypotheses depth (P, h), normal (P, h, 3) at pixels idx (P,)."""
        torch = self.torch
        P, h = depth.shape
        rows = max(1, self.opts.chunk // h)
        out = [self._cost(idx[i:i + rows], depth[i:i + rows], normal[i:i + rows], geom)
               for i in range(0, P, rows)]
        return torch.cat(out, 0) if len(out) > 1 else out[0]

    def _cost(self, idx, depth, normal, geom):
        # hypothesis-major layout (h, P) inside: the per-pixel window weights then broadcast
        # over the contiguous pixel axis
        torch, F = self.torch, self.torch.nn.functional
        depth, normal = depth.T.contiguous(), normal.transpose(0, 1).contiguous()
        h, P = depth.shape
        pix = self.pix[idx]
        w, wr = self.w[:, idx], self.wr[:, idx]                          # (n, P)
        exact = self.opts.warp == "homography"
        per_src = []
        for s in self.sources:
            terms = plane_warp_terms(s["A"], s["b"], self.kinv, pix, depth, normal,
                                     self.offsets, exact)
            centre = terms[0]
            z = centre[..., 2]
            zc = z.clamp_min(_EPS)
            ok = (z > _EPS) & ((centre[..., 0] / zc).abs() <= s["lim"][0]) \
                & ((centre[..., 1] / zc).abs() <= s["lim"][1])
            # weighted sums over the window, one sample at a time: the (n, h, P) products of a
            # vectorised form were ~8x slower than accumulating (h, P) planes in place
            mean = torch.zeros((h, P), device=depth.device)
            m2, cov = torch.zeros_like(mean), torch.zeros_like(mean)
            for i, (ox, oy) in enumerate(self.offset_list):
                grid = offset_samples(terms, ox, oy)
                val = F.grid_sample(s["img"], grid[None], mode="bilinear", padding_mode="zeros",
                                    align_corners=True)[0, 0]               # (h, P)
                vw = val * w[i]
                mean += vw
                m2.addcmul_(vw, val)
                cov.addcmul_(val, wr[i])
            var = (m2 - mean * mean).clamp_min(FLAT_VAR)
            c = (1.0 - cov * var.rsqrt()).clamp(0.0, MAX_COST)            # 1 - weighted NCC
            if geom and s["depth"] is not None and self.opts.geom_weight > 0:
                c = c + self.opts.geom_weight * self._reproj_error(s, pix, depth)
            per_src.append(torch.where(ok, c, torch.full_like(c, _UNSEEN)))
        agg = best_k_mean(torch.stack(per_src, 0), self.opts.sources_k_best)
        # a flat reference window matches nothing (cost 1) wherever some source sees it
        flat = self.flat[idx] & (agg < MAX_COST)
        return torch.where(flat, torch.ones((), device=agg.device), agg).T

    def _reproj_error(self, s, pix, depth):
        """min(forward-backward reprojection error in pixels, geom_max_px) (h, P), COLMAP/ACMM:
        lift with the hypothesis, project into the source, lift with the source's depth there
        (nearest pixel), project back."""
        torch = self.torch
        tau = self.opts.geom_max_px
        cp = (pix @ s["Ap"][:, :2].T + s["Ap"][:, 2]) + s["bp"] * (1.0 / depth)[..., None]
        z = cp[..., 2]
        xs = cp[..., :2] / z.clamp_min(_EPS)[..., None]
        h, w = s["size"]
        iu, iv = xs[..., 0].round().long(), xs[..., 1].round().long()
        inside = (z > _EPS) & (iu >= 0) & (iu < w) & (iv >= 0) & (iv < h)
        ds = s["depth"].reshape(-1)[(iv.clamp(0, h - 1) * w + iu.clamp(0, w - 1))]
        back = ds[..., None] * (xs @ s["B"][:, :2].T + s["B"][:, 2]) + s["beta"]
        zb = back[..., 2]
        err = (back[..., :2] / zb.clamp_min(_EPS)[..., None] - pix).norm(dim=-1)
        good = inside & (ds > 0) & (zb > _EPS)
        return torch.where(good, err.clamp_max(tau), torch.full_like(err, tau))


# --- the PatchMatch iterations --------------------------------------------------------------------
@dataclass
class _State:
    """Per-pixel hypotheses (flattened): depth (HW,), normal (HW, 3), cost (HW,)."""

    depth: "torch.Tensor"
    normal: "torch.Tensor"
    cost: "torch.Tensor"


def _random_depth(shape, lo, hi, gen, dev):
    import torch
    u = torch.rand(shape, generator=gen, device=dev)
    return 1.0 / (1.0 / hi + u * (1.0 / lo - 1.0 / hi))  # uniform in inverse depth (disparity)


def _plane_depth(depth_q, normal_q, ray_q, ray_p, lo, hi):
    """Depth at ray_p of the plane through depth_q * ray_q with normal_q; depth_q where the plane
    does not face ray_p; clamped to [lo, hi]."""
    import torch
    num = depth_q * (normal_q * ray_q).sum(-1)
    den = (normal_q * ray_p).sum(-1)
    d = torch.where(den < -1e-6, num / den.clamp_max(-1e-6), depth_q)
    return d.clamp(lo, hi)


def _update(st, idx, cand_d, cand_n, cost):
    """Keep, per pixel, the best of its current hypothesis and the candidates (P, h)."""
    import torch
    best = cost.argmin(1, keepdim=True)
    c = cost.gather(1, best)[:, 0]
    better = c < st.cost[idx]
    sel = idx[better]
    st.cost[sel] = c[better]
    st.depth[sel] = cand_d.gather(1, best)[better, 0]
    st.normal[sel] = torch.take_along_dim(cand_n, best[..., None], 1)[better, 0]


def _sweep(m: _Matcher, st: _State, colours, lo, hi, pert, cos_min, gen, geom):
    """One red/black sweep: per colour, ACMM propagation from the other colour then refinement."""
    torch = m.torch
    H, W, dev = m.H, m.W, m.dev
    Wp = W + 2 * _PAD
    areas = torch.as_tensor(_AREAS[..., 0] * Wp + _AREAS[..., 1], device=dev)  # (8, 11) flat
    for idx in colours:
        P = len(idx)
        # propagation: per area the neighbour with the lowest cost lends its plane
        cpad = torch.nn.functional.pad(st.cost.reshape(1, 1, H, W), (_PAD,) * 4, value=math.inf)
        cpad = cpad.reshape(-1)
        y, x = idx // W, idx % W
        pos = ((y + _PAD) * Wp + x + _PAD)[:, None, None] + areas[None]      # (P, 8, 11)
        pc = cpad[pos]
        k = pc.argmin(2, keepdim=True)
        has = torch.isfinite(pc.gather(2, k)[..., 0])                          # (P, 8)
        q = pos.gather(2, k)[..., 0]
        q = ((q // Wp - _PAD) * W + q % Wp - _PAD).where(has, idx[:, None])  # neighbour pixel
        cand_n = st.normal[q]
        cand_d = _plane_depth(st.depth[q], cand_n, m.ray[q], m.ray[idx][:, None], lo, hi)
        cost = m.cost(idx, cand_d, cand_n, geom).where(has, torch.full((), math.inf, device=dev))
        _update(st, idx, cand_d, cand_n, cost)
        # refinement: random and perturbed depth / normal around the current best (COLMAP/ACMM)
        d0, n0, v = st.depth[idx], st.normal[idx], m.view[idx]
        d_rand = _random_depth((P,), lo, hi, gen, dev)
        n_rand = face_camera(torch.randn((P, 3), generator=gen, device=dev), v, cos_min)
        u = torch.rand((P,), generator=gen, device=dev)
        d_pert = (d0 * (1.0 + pert * (2.0 * u - 1.0))).clamp(lo, hi)
        n_pert = face_camera(n0 + pert * torch.randn((P, 3), generator=gen, device=dev), v, cos_min)
        cand_d = torch.stack([d_rand, d0, d_pert, d_pert], 1)
        cand_n = torch.stack([n_rand, n_pert, n0, n_pert], 1)
        _update(st, idx, cand_d, cand_n, m.cost(idx, cand_d, cand_n, geom))


def _upsample(m: _Matcher, coarse: _State, cm: _Matcher, lo, hi, geom) -> _State:
    """Each fine pixel takes the best, at the fine level, of its 4 nearest coarse planes (the
    coarse plane is the same 3-D plane: camera-frame normals do not depend on the resolution)."""
    torch = m.torch
    H, W, h, w = m.H, m.W, cm.H, cm.W
    yy = torch.arange(H, device=m.dev)
    xx = torch.arange(W, device=m.dev)
    yc, xc = (yy // 2).clamp_max(h - 1), (xx // 2).clamp_max(w - 1)
    yn = (yc + torch.where(yy % 2 == 0, -1, 1)).clamp(0, h - 1)
    xn = (xc + torch.where(xx % 2 == 0, -1, 1)).clamp(0, w - 1)
    cand = torch.stack([(a[:, None] * w + b[None, :]).reshape(-1)
                        for a, b in ((yc, xc), (yn, xc), (yc, xn), (yn, xn))], 1)  # (HW, 4)
    cand_n = coarse.normal[cand]
    idx = torch.arange(H * W, device=m.dev)
    cand_d = _plane_depth(coarse.depth[cand], cand_n, cm.ray[cand], m.ray[:, None], lo, hi)
    cost = m.cost(idx, cand_d, cand_n, geom)
    st = _State(torch.zeros(H * W, device=m.dev), torch.zeros(H * W, 3, device=m.dev),
                torch.full((H * W,), math.inf, device=m.dev))
    _update(st, idx, cand_d, cand_n, cost)
    return st


def _normals_from_depth(depth, ray, H, W, view, cos_min):
    """Camera-frame normals of a depth map (HW,) from central differences of the lifted points."""
    import torch
    X = torch.nn.functional.pad((depth[:, None] * ray).reshape(1, H, W, 3).permute(0, 3, 1, 2),
                                (1, 1, 1, 1), mode="replicate")[0].permute(1, 2, 0)
    n = torch.cross(X[1:-1, 2:] - X[1:-1, :-2], X[2:, 1:-1] - X[:-2, 1:-1], dim=-1).reshape(-1, 3)
    bad = (n.norm(dim=1) < 1e-12) | (depth <= 0)
    return face_camera(torch.where(bad[:, None], -view, n), view, cos_min)


def _solve(ref_gray, ref_cam, srcs, lo, hi, opts, dev, seed, init=None, sweeps=None, first=0,
           geom=True):
    """srcs: [(gray, cam, depth or None)] at any size; lo/hi in world units; init: (depth (H, W),
    normal (H, W, 3) or None) world units at the working size: no pyramid, start from it;
    sweeps (default opts.iterations) per level, the perturbation halved from sweep index `first`.
    Returns the final hypotheses (depth, normal, cost) as numpy at the working size, depth in
    world units (every pixel has one; `_thresholded` invalidates the bad ones)."""
    import cv2
    import torch
    scale = math.sqrt(lo * hi)
    lo_s, hi_s = lo / scale, hi / scale
    cos_min = math.cos(math.radians(opts.max_grazing_deg))
    gen = torch.Generator(device=dev)
    gen.manual_seed(int(seed))
    # pyramid (level 0 = working size); geometry of a level = cameras resized to its images
    pyr = [(ref_gray, [g for g, _, _ in srcs])]
    n_levels = 0 if init is not None else opts.levels
    while len(pyr) <= n_levels and min(pyr[-1][0].shape) >= 8 * opts.window:
        half = lambda g: cv2.resize(g, ((g.shape[1] + 1) // 2, (g.shape[0] + 1) // 2),  # noqa: E731
                                    interpolation=cv2.INTER_AREA)
        pyr.append((half(pyr[-1][0]), [half(g) for g in pyr[-1][1]]))
    st, prev = None, None
    with torch.no_grad():
        for level in range(len(pyr) - 1, -1, -1):
            rg, sgs = pyr[level]
            lsrc = []
            for g, (_, cam, d) in zip(sgs, srcs):
                if d is not None and d.shape != g.shape:
                    d = cv2.resize(d, (g.shape[1], g.shape[0]), interpolation=cv2.INTER_NEAREST)
                lsrc.append((g, cam.resized(g.shape[1], g.shape[0]), d))
            m = _Matcher(rg, ref_cam.resized(rg.shape[1], rg.shape[0]), lsrc, scale, opts, dev)
            HW = m.H * m.W
            idx = torch.arange(HW, device=dev)
            if st is None:
                d = _random_depth((HW,), lo_s, hi_s, gen, dev)
                nrm = face_camera(torch.randn((HW, 3), generator=gen, device=dev), m.view, cos_min)
                if init is not None:
                    T = lambda a: torch.as_tensor(a, dtype=torch.float32, device=dev)  # noqa: E731
                    d0 = T(init[0].reshape(-1) / scale)
                    n0 = (_normals_from_depth(d0, m.ray, m.H, m.W, m.view, cos_min) if init[1] is None
                          else face_camera(T(init[1].reshape(-1, 3)), m.view, cos_min))
                    d = torch.where(d0 > 0, d0.clamp(lo_s, hi_s), d)
                    nrm = torch.where(d0[:, None] > 0, n0, nrm)
                st = _State(d, nrm, m.cost(idx, d[:, None], nrm[:, None], geom)[:, 0])
            else:
                st = _upsample(m, st, prev, lo_s, hi_s, geom)
            red = (idx // m.W + idx % m.W) % 2 == 0
            colours = (idx[red], idx[~red])
            for it in range(first, first + (opts.iterations if sweeps is None else sweeps)):
                _sweep(m, st, colours, lo_s, hi_s, opts.perturbation * 0.5 ** it, cos_min, gen, geom)
            prev = m
    if any(s["depth"] is not None for s in m.sources) and opts.geom_weight > 0:
        with torch.no_grad():  # the result's cost (and validity) is photometric, as in COLMAP
            st.cost = m.cost(idx, st.depth[:, None], st.normal[:, None], geom=False)[:, 0]
    depth = st.depth.reshape(m.H, m.W) * scale
    return (depth.cpu().numpy().astype(np.float32),
            st.normal.reshape(m.H, m.W, 3).cpu().numpy().astype(np.float32),
            st.cost.reshape(m.H, m.W).cpu().numpy().astype(np.float32))


def _thresholded(raw, opts: PatchMatchOptions) -> PatchMatchResult:
    """Result with depth and normal zeroed where the cost exceeds opts.max_cost."""
    depth, normal, cost = raw
    ok = cost <= opts.max_cost
    return PatchMatchResult(np.where(ok, depth, 0).astype(np.float32),
                            np.where(ok[..., None], normal, 0).astype(np.float32), cost)


# --- checks and public API ------------------------------------------------------------------------
def _gray(image, what: str) -> np.ndarray:
    img = np.asarray(image, dtype=np.float32)
    if img.ndim == 3 and img.shape[2] == 3:
        img = img @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
    elif img.ndim != 2:
        raise ValueError(f"{what} must be (H, W, 3) or (H, W), got shape {img.shape}")
    if min(img.shape) < 8 or not np.all(np.isfinite(img)):
        raise ValueError(f"{what} must be at least 8 x 8 and finite, got shape {img.shape}")
    return np.ascontiguousarray(img)


def _range(depth_min, depth_max, what: str) -> tuple[float, float]:
    try:
        lo, hi = float(depth_min), float(depth_max)
    except (TypeError, ValueError):
        raise ValueError(f"{what}: depth_min / depth_max must be scalars, got "
                         f"{np.shape(depth_min)} and {np.shape(depth_max)}") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo < hi):
        raise ValueError(f"{what}: need 0 < depth_min < depth_max (finite), got {lo}, {hi}")
    return lo, hi


def _depth_map(d, shape, what: str) -> np.ndarray:
    """A z-depth map (0 = none) of the given shape (any 2-D shape if None)."""
    arr = np.asarray(d, dtype=np.float32)
    if arr.ndim != 2 or (shape is not None and arr.shape != tuple(shape)):
        raise ValueError(f"{what} must have shape {tuple(shape) if shape else '(h, w)'}, got {arr.shape}")
    if not np.all(np.isfinite(arr)) or np.any(arr < 0):
        raise ValueError(f"{what} must be finite and >= 0 (0 = no depth)")
    return arr


def _checked(opts: PatchMatchOptions) -> PatchMatchOptions:
    if not isinstance(opts, PatchMatchOptions):
        raise ValueError(f"opts must be PatchMatchOptions, got {type(opts).__name__}")
    try:
        opts.validate()
    except ConfigError as e:
        raise ValueError(str(e)) from None
    return opts


def patchmatch(ref_image: np.ndarray, ref_cam: Camera, src_images: Sequence[np.ndarray],
               src_cams: Sequence[Camera], depth_min: float, depth_max: float,
               opts: PatchMatchOptions = PatchMatchOptions(), device: str = "cpu",
               init_depth: np.ndarray | None = None,
               src_depths: Sequence[np.ndarray | None] | None = None,
               seed: int = 0) -> PatchMatchResult:
    """PatchMatch depth and normals of `ref_image` from its source views (module docstring).

    ref_image (H, W, 3) float RGB in [0, 1] (or (H, W) grey) at the working size; src_images
    (h, w, 3) each; cameras are resized to their image's size. depth_min < depth_max: scalars, the
    z-depth range searched. init_depth (H, W), 0 = none: start from it (normals from its
    gradient) at the working size only, no pyramid. src_depths: per source a z-depth map (any
    size, 0 = none) or None: enables the geometric term (opts.geom_weight). seed: the random
    initialisation and refinement (same seed, same device and threads -> same result).
    """
    opts = _checked(opts)
    ref = _gray(ref_image, "ref_image")
    if len(src_images) != len(src_cams) or not src_images:
        raise ValueError(f"need >= 1 source image and as many cameras, got {len(src_images)} "
                         f"images and {len(src_cams)} cameras")
    src_depths = [None] * len(src_images) if src_depths is None else list(src_depths)
    if len(src_depths) != len(src_images):
        raise ValueError(f"{len(src_images)} source images but {len(src_depths)} src_depths")
    for i, c in enumerate([ref_cam, *src_cams]):
        if not isinstance(c, Camera):
            raise ValueError(f"{'ref_cam' if i == 0 else f'src_cams[{i - 1}]'} must be a Camera")
    srcs = [(_gray(s, f"src_images[{i}]"), c,
             None if d is None else _depth_map(d, None, f"src_depths[{i}]"))
            for i, (s, c, d) in enumerate(zip(src_images, src_cams, src_depths))]
    lo, hi = _range(depth_min, depth_max, "patchmatch")
    init = None if init_depth is None else (_depth_map(init_depth, ref.shape, "init_depth"), None)
    raw = _solve(ref, ref_cam, srcs, lo, hi, opts, torch_device(device), seed, init=init)
    return _thresholded(raw, opts)


def patchmatch_views(images: dict[str, np.ndarray], cams: dict[str, Camera],
                     sources: dict[str, list[str]], ranges: dict[str, tuple[float, float]],
                     opts: PatchMatchOptions = PatchMatchOptions(), device: str = "cpu",
                     progress: bool = False, seed: int = 0,
                     map_fn=None) -> dict[str, PatchMatchResult]:
    """Depth maps of every view in `sources` (name -> its source view names).

    1. photometric multi-scale PatchMatch of each view; 2. opts.geom_iterations passes: in each,
    every view runs one sweep at the working size from its own hypotheses with the geometric term
    against the other views' (cost-thresholded) depth maps of the previous pass (ACMM's
    geometric-consistency guided refinement);
    3. forward-backward filter: a pixel stays valid when >= opts.filter_min_views of its sources'
    depth maps agree (relative depth opts.filter_rel_depth, opts.filter_reproj_px pixels).
    images: name -> (H, W, 3) at the working size; ranges: name -> (depth_min, depth_max).
    map_fn(fn, argsets) -> iterator of (index, fn(*argsets[index])) in any order: runs the views
    of one pass (independent of each other: every view reads only the previous pass) — worker
    processes, say; default: one after the other here. Each view's seed is fixed by its position,
    so the maps do not depend on map_fn, only on the torch threads each task runs with.
    """
    opts = _checked(opts)
    for name, srcs in sources.items():
        for what, table in (("images", images), ("cams", cams), ("ranges", ranges)):
            if name not in table:
                raise ValueError(f"view {name!r} is in sources but not in {what}")
        bad = [s for s in srcs if s not in images or s not in cams or s == name]
        if not srcs or bad:
            raise ValueError(f"view {name!r}: sources must be other views in images and cams, "
                             f"got {list(srcs)}")
    dev = torch_device(device)
    used = {*sources, *(s for v in sources.values() for s in v)}
    gray = {n: _gray(images[n], f"images[{n!r}]") for n in used}
    rng = {n: _range(*ranges[n], f"ranges[{n!r}]") for n in sources}
    names = list(sources)
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=len(names) * (1 + opts.geom_iterations), desc="patchmatch", unit="view",
                   leave=False)
    tick = bar.update if bar is not None else (lambda: None)
    run = map_fn or (lambda fn, argsets: ((i, fn(*a)) for i, a in enumerate(argsets)))

    def one_pass(argsets):
        res = [None] * len(argsets)
        for i, r in run(_solve, argsets):  # module-level: worker processes unpickle it
            res[i] = r
            tick()
        return dict(zip(names, res))

    out = one_pass([(gray[n], cams[n], [(gray[s], cams[s], None) for s in sources[n]], *rng[n],
                     opts, dev, seed + i) for i, n in enumerate(names)])
    for g in range(opts.geom_iterations):  # Jacobi: every view sees the previous pass's maps
        prev = {n: _thresholded(r, opts).depth for n, r in out.items()}
        out = one_pass([(gray[n], cams[n], [(gray[s], cams[s], prev.get(s)) for s in sources[n]],
                         *rng[n], opts, dev, seed + (g + 1) * len(names) + i, out[n][:2], 1,
                         opts.iterations + g) for i, n in enumerate(names)])
    if bar is not None:
        bar.close()
    res = {n: _thresholded(out[n], opts) for n in names}
    if opts.filter_min_views == 0:
        return res
    keep = {}
    for n in names:
        have = [s for s in sources[n] if s in res]
        keep[n] = geometric_consistency(cams[n], res[n].depth, [cams[s] for s in have],
                                        [res[s].depth for s in have], rel_tol=opts.filter_rel_depth,
                                        reproj_px=opts.filter_reproj_px,
                                        device=str(dev)) >= opts.filter_min_views
    return {n: PatchMatchResult(np.where(keep[n], r.depth, 0).astype(np.float32),
                                np.where(keep[n][..., None], r.normal, 0).astype(np.float32), r.cost)
            for n, r in res.items()}
