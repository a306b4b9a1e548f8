"""Plane-sweep multi-view stereo in torch (CPU or CUDA): Xu et al. §4.1 (global mesh without depth)
and §4.2.2 (masked per-view refinement).

pycolmap's PatchMatch needs CUDA, so dense depth on CPU is ours. The method is a classic
fronto-parallel plane sweep (Collins 1996; Gallup et al. 2007):

* hypotheses are sampled **uniformly in inverse depth** between `depth_min` and `depth_max`, which
  may be scalars or per-pixel (H, W) maps (a per-pixel search band, e.g. around an initial depth);
* cost = 1 − NCC of the grey-level `window` × `window` patch (zero-mean normalised
  cross-correlation, box-filtered; in [0, 2], 0 = perfect match). NCC, not census: it is invariant
  to the gain/offset changes between views and is what COLMAP's PatchMatch uses;
* occlusion: per pixel and hypothesis the costs of the `k_best` best source views are averaged
  (Kang et al. 2001, "best-K views"), so a view in which the pixel is occluded does not spoil the
  match; a source in which the pixel projects outside the image or behind the camera is left out
  of that average (a pixel no source sees costs 2, the worst);
* winner-takes-all, then `refine_levels` coarse-to-fine passes that re-sweep a band of ±1.5
  hypothesis steps around the winner with `refine_depths` hypotheses, and a parabola fit of the
  cost around the final minimum (sub-hypothesis precision in inverse depth);
* `mask`: only these pixels are computed. The image is cut into `tile` × `tile` tiles and only the
  tiles that touch the mask (dilated by the window radius) are swept, so the work is proportional
  to the masked area (plus a halo), not to the image.

`geometric_consistency` is the forward-backward reprojection test used to filter depth maps before
fusion (COLMAP's geometric filtering, Schönberger et al. 2016), and `select_sources` picks the
neighbour views (triangulation angle and viewing-direction criteria, Hedman et al. 2016 / COLMAP).

Conventions are those of `scene.py`: OpenCV cameras, z-depth in metres, pixel centre (0, 0).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Sequence

import numpy as np

from ..scene import Camera

if TYPE_CHECKING:  # annotations only: torch is imported where it is used (fast CLI start)
    import torch

FLAT_VAR = 1e-6  # grey-level variance (values in [0, 1]) below which a patch counts as flat
_UNSEEN = 1e3  # sentinel cost of a source in which the pixel does not project
MAX_COST = 2.0  # 1 - NCC is in [0, 2]; used for invalid projections and uncomputed pixels


@dataclass
class SweepResult:
    """depth (H, W) float32 z-depth, 0 = invalid; cost (H, W) float32 aggregated 1 − NCC
    (MAX_COST where not computed); valid (H, W) bool."""

    depth: np.ndarray
    cost: np.ndarray
    valid: np.ndarray


# --- helpers --------------------------------------------------------------------------------------
def _gray(image: np.ndarray, what: str) -> np.ndarray:
    img = np.asarray(image, dtype=np.float32)
    if img.ndim == 3 and img.shape[2] == 3:
        img = img @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
    elif img.ndim != 2:
        raise ValueError(f"{what} must be (H, W, 3) or (H, W), got {img.shape}")
    if not np.all(np.isfinite(img)):
        raise ValueError(f"{what} contains NaN or infinite values")
    return img


def _at_size(cam: Camera, width: int, height: int) -> Camera:
    return cam if (cam.width, cam.height) == (width, height) else cam.resized(width, height)


def _range_map(value, shape: tuple[int, int], what: str) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim == 0:
        arr = np.full(shape, float(arr))
    if arr.shape != shape:
        raise ValueError(f"{what} must be a float or an {shape} array, got shape {arr.shape}")
    return arr


def torch_device(device):
    """torch.device(device); ValueError when CUDA is asked for and absent (shared with patchmatch)."""
    import torch
    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError("device 'cuda' requested but torch sees no CUDA device")
    return dev


def _active_tiles(mask: np.ndarray | None, H: int, W: int, tile: int, radius: int):
    """Tile origins (y0, x0) to sweep and the tile size (th, tw). Without a mask (or when the mask
    touches most tiles) one tile covers the whole image."""
    if mask is None:
        return [(0, 0)], (H, W)
    import scipy.ndimage as ndi
    grown = ndi.binary_dilation(mask, iterations=radius) if radius > 0 else mask
    ny, nx = math.ceil(H / tile), math.ceil(W / tile)
    padded = np.zeros((ny * tile, nx * tile), bool)
    padded[:H, :W] = grown
    hit = padded.reshape(ny, tile, nx, tile).any(axis=(1, 3))
    if hit.sum() * tile * tile >= 0.7 * H * W:
        return [(0, 0)], (H, W)
    return [(int(y) * tile, int(x) * tile) for y, x in zip(*np.nonzero(hit))], (tile, tile)


def _extract(arr: np.ndarray, origins, size, radius: int, H: int, W: int) -> np.ndarray:
    """(B, th + 2r, tw + 2r) windows of a 2-D array padded by edge replication."""
    th, tw = size
    ph = max(0, max(y for y, _ in origins) + th - H)
    pw = max(0, max(x for _, x in origins) + tw - W)
    p = np.pad(arr, ((radius, radius + ph), (radius, radius + pw)), mode="edge")
    return np.stack([p[y:y + th + 2 * radius, x:x + tw + 2 * radius] for y, x in origins])


def _box_sum(x: "torch.Tensor", k: int) -> "torch.Tensor":
    """Sums over k × k windows ('valid') of the last two dims from two running sums (an integral
    image, Crow 1984): 6 passes whatever k is (14 for shifted adds at k = 7). The float32 rounding
    is ~1e-7 of a running sum; callers centre grey levels on 0 to keep it small."""
    torch = _torch()
    c = torch.cumsum(x, -1)
    h = c[..., k - 1:].clone()
    h[..., 1:] -= c[..., :c.shape[-1] - k]
    c = torch.cumsum(h, -2)
    out = c[..., k - 1:, :].clone()
    out[..., 1:, :] -= c[..., :c.shape[-2] - k, :]
    return out


def _torch():
    import torch
    return torch


class _Sweeper:
    """The state shared by the passes of one plane sweep at one resolution: tiles, reference
    window statistics, per-source projection of every tile pixel."""

    def __init__(self, ref_gray, ref_cam, src_grays, src_cams, origins, size, radius, window,
                 k_best, dev):
        import torch
        import torch.nn.functional as F
        self.torch, self.F = torch, F
        H, W = ref_gray.shape
        self.H, self.W, self.origins, self.size, self.r, self.window = H, W, origins, size, radius, window
        self.dev = dev
        th, tw = size
        # pixel coordinates of every tile pixel incl. the halo (may lie outside the image: clamped
        # for the reference, whose halo is edge-replicated)
        u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
        tu = _extract(u, origins, size, radius, H, W)
        tv = _extract(v, origins, size, radius, H, W)
        rays = np.stack([tu, tv, np.ones_like(tu)], 0)  # (3, B, Hp, Wp) homogeneous pixels
        self.B, self.Hp, self.Wp = tu.shape
        n = float(window * window)
        self.n = n
        # grey levels centred on 0 (NCC is offset-invariant; smaller running sums in _box_sum)
        ref64 = torch.as_tensor(_extract(ref_gray, origins, size, radius, H, W) - 0.5, dtype=torch.float64)
        Sr = _box_sum(ref64, window)
        var_n2 = n * _box_sum(ref64 * ref64, window) - Sr * Sr  # n² × variance
        self.ref = ref64.to(dev, torch.float32)
        self.Sr = Sr.to(dev, torch.float32)
        self.flat_ref = (var_n2 < n * n * FLAT_VAR).to(dev)
        self.var_r_n2 = var_n2.clamp_min(n * n * FLAT_VAR).to(dev, torch.float32)
        # per source: a ref pixel p at inverse depth q projects to (P + q b) (homogeneous) with
        # P = K_s R_rel K_r^-1 p and b = K_s t_rel; rows 0 and 1 are folded into grid_sample's
        # [-1, 1] coordinates (align_corners): g = (a (P0 + q b0) - (P2 + q b2)) / (P2 + q b2).
        Kr_inv = np.linalg.inv(ref_cam.K)
        self.sources = []
        for g, cam in zip(src_grays, src_cams):
            h, w = g.shape
            rel = cam.cam_from_world @ ref_cam.world_from_cam
            M = cam.K @ rel[:3, :3] @ Kr_inv
            b = cam.K @ rel[:3, 3]
            ax, ay = 2.0 / max(w - 1, 1), 2.0 / max(h - 1, 1)
            fold = np.array([[ax, 0, -1], [0, ay, -1], [0, 0, 1]])
            M, b = fold @ M, fold @ b
            P = torch.as_tensor(np.einsum("ij,jbhw->ibhw", M, rays), dtype=torch.float32, device=dev)
            self.sources.append((torch.as_tensor(g - 0.5, dtype=torch.float32, device=dev)[None, None],
                                 P, [float(x) for x in b], 1.0 + 0.5 * ax, 1.0 + 0.5 * ay))
        self.k_best = min(k_best, len(self.sources))
        self.covered = self.to_image(torch.ones((self.B, th, tw)), 0.0) > 0

    def costs(self, inv: "torch.Tensor") -> "torch.Tensor":
        """Aggregated cost (N, B, th, tw) for inverse-depth hypotheses `inv` (N, B, Hp, Wp)."""
        torch, F, r, n = self.torch, self.F, self.r, self.n
        N = inv.shape[0]
        ys, xs = slice(r, self.Hp - r), slice(r, self.Wp - r)
        ref = self.ref[None]
        per_src, total, seen, worst = [], None, None, None
        running = self.k_best >= len(self.sources) - 1
        for img, P, b, lim_x, lim_y in self.sources:
            z = torch.add(P[2], inv, alpha=b[2])
            gx = torch.add(P[0], inv, alpha=b[0])
            gy = torch.add(P[1], inv, alpha=b[1])
            ok = z[..., ys, xs] > 1e-6
            z.clamp_min_(1e-6)
            gx.div_(z)
            gy.div_(z)
            ok &= gx[..., ys, xs].abs() <= lim_x
            ok &= gy[..., ys, xs].abs() <= lim_y
            grid = torch.stack([gx, gy], -1).reshape(1, -1, self.Wp, 2)
            s = F.grid_sample(img, grid, mode="bilinear", padding_mode="border",
                              align_corners=True).reshape(N, self.B, self.Hp, self.Wp)
            S1 = _box_sum(s, self.window)
            S2 = _box_sum(s * s, self.window)
            S3 = _box_sum(s * ref, self.window)
            # zero-mean NCC from window sums: (n S3 - S1 Sr) / sqrt((n S2 - S1²)(n Sr2 - Sr²)); a
            # flat source patch (variance below FLAT_VAR) correlates with nothing
            num = torch.addcmul(S3 * n, S1, self.Sr, value=-1.0)
            den = torch.addcmul(S2 * n, S1, S1, value=-1.0).clamp_min_(n * n * FLAT_VAR)
            num.mul_(den.mul_(self.var_r_n2).rsqrt_())
            cost = num.neg_().add_(1.0).clamp_(0.0, MAX_COST)
            if running:  # best K >= all but one: mean of the seen costs minus the worst
                c = torch.where(ok, cost, torch.zeros((), device=cost.device))
                if total is None:
                    total, seen, worst = c, ok.to(cost.dtype), c.clone()
                else:
                    total += c
                    seen += ok
                    torch.maximum(worst, c, out=worst)
            else:
                per_src.append(torch.where(ok, cost, torch.full_like(cost, _UNSEEN)))
        if running:
            m = float(len(self.sources))
            drop = (seen == m) & (self.k_best < m)
            agg = torch.where(drop, (total - worst) / max(m - 1, 1), total / seen.clamp_min(1))
            agg = torch.where(seen > 0, agg, torch.full_like(agg, MAX_COST))
        else:
            allc = torch.topk(torch.stack(per_src, 0), self.k_best, dim=0, largest=False).values
            ok = allc < _UNSEEN
            cnt = ok.sum(0)
            agg = torch.where(ok, allc, torch.zeros_like(allc)).sum(0) / cnt.clamp_min(1)
            agg = torch.where(cnt > 0, agg, torch.full_like(agg, MAX_COST))
        # a flat reference patch matches nothing (cost 1) wherever some source sees it
        return torch.where(self.flat_ref & (agg < MAX_COST), torch.ones((), device=agg.device), agg)

    def sweep(self, inv_near: "torch.Tensor", inv_far: "torch.Tensor", num: int, batch: int,
              progress: bool = False, desc: str = "plane sweep"):
        """Winner-takes-all over `num` hypotheses uniform in inverse depth between the (B, Hp, Wp)
        maps; returns (inverse depth, cost, inverse-depth step) on the tile interiors."""
        torch, r = self.torch, self.r
        steps = torch.arange(num, device=self.dev, dtype=torch.float32) / max(num - 1, 1)
        th, tw = self.size
        vol = torch.empty((num, self.B, th, tw), device=self.dev)
        chunks = range(0, num, batch)
        if progress:
            from tqdm import tqdm
            chunks = tqdm(chunks, desc=desc, unit="batch", leave=False)
        for i0 in chunks:
            t = steps[i0:i0 + batch][:, None, None, None]
            vol[i0:i0 + batch] = self.costs(inv_far[None] + (inv_near - inv_far)[None] * t)
        best = vol.argmin(0)
        c0 = vol.gather(0, best[None])[0]
        # parabola through the costs at best-1, best, best+1 (in hypothesis index space)
        lo = vol.gather(0, (best - 1).clamp_min(0)[None])[0]
        hi = vol.gather(0, (best + 1).clamp_max(num - 1)[None])[0]
        denom = lo - 2 * c0 + hi
        off = torch.where((best > 0) & (best < num - 1) & (denom > 1e-6),
                          0.5 * (lo - hi) / denom.clamp_min(1e-6), torch.zeros_like(c0)).clamp(-0.5, 0.5)
        near_i = inv_near[:, r:self.Hp - r, r:self.Wp - r]
        far_i = inv_far[:, r:self.Hp - r, r:self.Wp - r]
        step = (near_i - far_i) / max(num - 1, 1)
        inv_best = far_i + (best.float() + off) * step
        return inv_best, c0, step

    def to_image(self, tiles: "torch.Tensor", fill: float) -> np.ndarray:
        """Scatter tile interiors (B, th, tw) back into an (H, W) image."""
        th, tw = self.size
        out = np.full((self.H, self.W), fill, np.float32)
        arr = tiles.detach().cpu().numpy()
        for (y, x), t in zip(self.origins, arr):
            h, w = min(th, self.H - y), min(tw, self.W - x)
            out[y:y + h, x:x + w] = t[:h, :w]
        return out


def _sweep_level(ref_gray, ref_cam, src_grays, src_cams, inv_near, inv_far, mask, num, opt):
    """One resolution: `num` hypotheses between the (H, W) inverse-depth maps, then
    opt['refine_levels'] passes of ±1.5 steps. Returns (inv, cost, step, computed) images."""
    import torch
    H, W = ref_gray.shape
    r, dev = opt["window"] // 2, opt["dev"]
    origins, size = _active_tiles(mask, H, W, opt["tile"], r)
    sw = _Sweeper(ref_gray, ref_cam, src_grays, src_cams, origins, size, r, opt["window"],
                  opt["k_best"], dev)
    tt = lambda a: torch.as_tensor(_extract(a, origins, size, r, H, W), dtype=torch.float32, device=dev)  # noqa: E731
    near0, far0 = tt(inv_near), tt(inv_far)
    inv, cost, step = sw.sweep(near0, far0, num, opt["batch"], opt["progress"])
    for level in range(opt["refine_levels"]):
        # re-sweep ±1.5 steps around the winner, inside the original range
        lo_i, hi_i = far0[:, r:sw.Hp - r, r:sw.Wp - r], near0[:, r:sw.Hp - r, r:sw.Wp - r]
        near = torch.minimum(inv + 1.5 * step, hi_i)
        far = torch.maximum(inv - 1.5 * step, lo_i)
        # the halo of each tile takes the neighbouring tiles' bands (same result as unmasked)
        near_img = np.where(sw.covered, sw.to_image(near, 0.0), inv_near)
        far_img = np.where(sw.covered, sw.to_image(far, 0.0), inv_far)
        inv, cost, step = sw.sweep(tt(near_img), tt(far_img), opt["refine_depths"], opt["batch"],
                                   opt["progress"], f"refine {level + 1}")
    return sw.to_image(inv, 0.0), sw.to_image(cost, MAX_COST), sw.to_image(step, 0.0), sw.covered


def _half(a: np.ndarray, how: str) -> np.ndarray:
    """2 × 2 block reduction (odd sizes: the last row/column is repeated): max, min or any."""
    H, W = a.shape
    p = np.pad(a, ((0, H % 2), (0, W % 2)), mode="edge")
    b = p.reshape(p.shape[0] // 2, 2, p.shape[1] // 2, 2)
    return b.max(axis=(1, 3)) if how in ("max", "any") else b.min(axis=(1, 3))


def _solve(ref_gray, ref_cam, src_grays, src_cams, inv_near, inv_far, mask, levels, opt):
    """Coarse-to-fine (pyramid) plane sweep: the full `num_depths` sweep runs `levels` octaves
    down; every finer level sweeps `refine_depths` hypotheses inside the band spanned by the
    coarser winners of the 3 × 3 neighbourhood ± 1.5 coarse steps (so that both sides of a depth
    edge stay in the band), then `refine_levels` passes at the finest level only.
    Returns (inv, cost, step, computed) images at the input resolution."""
    import cv2
    import scipy.ndimage as ndi
    H, W = ref_gray.shape
    if levels <= 0 or min(H, W) < 4 * opt["window"]:
        return _sweep_level(ref_gray, ref_cam, src_grays, src_cams, inv_near, inv_far, mask,
                            opt["num_depths"], opt)
    h2, w2 = (H + 1) // 2, (W + 1) // 2
    down = lambda g: cv2.resize(g, (w2, h2), interpolation=cv2.INTER_AREA)  # noqa: E731
    inv_c, _, step_c, done = _solve(
        down(ref_gray), _at_size(ref_cam, w2, h2), [down(g) for g in src_grays],
        [_at_size(c, (g.shape[1] + 1) // 2, (g.shape[0] + 1) // 2) for c, g in zip(src_cams, src_grays)],
        _half(inv_near, "max"), _half(inv_far, "min"), None if mask is None else _half(mask, "any"),
        levels - 1, dict(opt, refine_levels=0))
    hi = ndi.maximum_filter(np.where(done, inv_c + 1.5 * step_c, -np.inf), size=3)
    lo = ndi.minimum_filter(np.where(done, inv_c - 1.5 * step_c, np.inf), size=3)
    up = lambda a: np.repeat(np.repeat(a, 2, 0), 2, 1)[:H, :W]  # noqa: E731
    near, far = np.minimum(up(hi), inv_near), np.maximum(up(lo), inv_far)
    bad = ~(np.isfinite(near) & np.isfinite(far) & (near > far))
    near, far = np.where(bad, inv_near, near), np.where(bad, inv_far, far)
    return _sweep_level(ref_gray, ref_cam, src_grays, src_cams, near, far, mask, opt["refine_depths"], opt)


# --- public API ----------------------------------------------------------------------------------
def plane_sweep(ref_image: np.ndarray, ref_cam: Camera, src_images: Sequence[np.ndarray],
                src_cams: Sequence[Camera], depth_min, depth_max, num_depths: int = 48,
                window: int = 7, mask: np.ndarray | None = None, device: str = "cpu",
                batch: int = 8, k_best: int = 3, refine_levels: int = 1, refine_depths: int = 16,
                max_cost: float = 0.5, tile: int = 32, progress: bool = False,
                coarse_levels: int = 0) -> SweepResult:
    """Fronto-parallel plane-sweep depth of `ref_image` from neighbouring views (module docstring).

    ref_image (H, W, 3) float32 in [0, 1] (or (H, W) grey); src_images: list of (h, w, 3); cameras
    are resized to their image's size when they differ. depth_min/depth_max: floats or (H, W) maps
    (> 0, min < max). mask (H, W) bool: compute only these pixels (others get depth 0).
    batch: hypotheses evaluated at once (memory ~ batch x 12 x tile pixels floats per source).
    k_best: costs of the best K sources averaged per hypothesis (occlusion robustness).
    max_cost: pixels whose best aggregated 1 − NCC exceeds this are invalid (depth 0).
    coarse_levels: run the full `num_depths` sweep this many octaves down and only
    `refine_depths` hypotheses per pixel at each finer level (pyramid; 0 = single resolution).
    """
    import torch

    ref_gray = _gray(ref_image, "ref_image")
    H, W = ref_gray.shape
    if len(src_images) != len(src_cams) or len(src_images) == 0:
        raise ValueError(f"need >= 1 source image and as many cameras, got {len(src_images)} images "
                         f"and {len(src_cams)} cameras")
    if window < 3 or window % 2 == 0:
        raise ValueError(f"window must be odd and >= 3, got {window}")
    if num_depths < 2 or refine_depths < 2 or batch < 1 or k_best < 1 or tile < 8 or coarse_levels < 0:
        raise ValueError("num_depths/refine_depths >= 2, batch >= 1, k_best >= 1, tile >= 8, "
                         "coarse_levels >= 0 required")
    src_grays = [_gray(s, f"src_images[{i}]") for i, s in enumerate(src_images)]
    ref_cam = _at_size(ref_cam, W, H)
    src_cams = [_at_size(c, g.shape[1], g.shape[0]) for c, g in zip(src_cams, src_grays)]
    dmin = _range_map(depth_min, (H, W), "depth_min")
    dmax = _range_map(depth_max, (H, W), "depth_max")
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != (H, W):
            raise ValueError(f"mask must be {(H, W)}, got {mask.shape}")
    usable = np.isfinite(dmin) & np.isfinite(dmax) & (dmin > 0) & (dmax > dmin)
    ranged = usable.copy()
    if mask is not None:
        usable &= mask
    if not usable.any():
        z = np.zeros((H, W), np.float32)
        return SweepResult(z, np.full((H, W), MAX_COST, np.float32), np.zeros((H, W), bool))
    # unusable pixels get a harmless range so that they can sit in a window's halo
    fill_min, fill_max = float(np.median(dmin[usable])), float(np.median(dmax[usable]))
    dmin = np.where(ranged, dmin, fill_min)
    dmax = np.where(ranged, dmax, fill_max)
    opt = dict(window=window, dev=torch_device(device), tile=tile, k_best=k_best, batch=batch,
               progress=progress, refine_levels=refine_levels, refine_depths=refine_depths,
               num_depths=num_depths)
    with torch.no_grad():
        inv, cost_img, _, _ = _solve(ref_gray, ref_cam, src_grays, src_cams, 1.0 / dmin, 1.0 / dmax,
                                     mask, coarse_levels, opt)
    depth = np.where(inv > 0, 1.0 / np.maximum(inv, 1e-9), 0.0)
    valid = usable & (cost_img <= max_cost) & np.isfinite(depth) & (depth > 0)
    cost_img[~usable] = MAX_COST
    return SweepResult(np.where(valid, depth, 0).astype(np.float32), cost_img.astype(np.float32), valid)


def geometric_consistency(ref_cam: Camera, ref_depth: np.ndarray, src_cams: Sequence[Camera],
                          src_depths: Sequence[np.ndarray], rel_tol: float = 0.01,
                          reproj_px: float = 1.0, device: str = "cpu") -> np.ndarray:
    """(H, W) int: how many source depth maps agree with `ref_depth` at each pixel.

    Forward-backward check (COLMAP geometric filtering): lift the ref pixel with its depth, project
    into the source, read the source depth there (nearest pixel), lift that and project back; the
    source agrees when the round trip lands within `reproj_px` pixels of the start and its depth is
    within `rel_tol` (relative) of the ref depth. Cameras are resized to their depth map's size.
    """
    import torch

    ref_depth = np.asarray(ref_depth, dtype=np.float32)
    if ref_depth.ndim != 2:
        raise ValueError(f"ref_depth must be (H, W), got {ref_depth.shape}")
    if len(src_cams) != len(src_depths):
        raise ValueError(f"{len(src_cams)} source cameras but {len(src_depths)} depth maps")
    H, W = ref_depth.shape
    dev = torch_device(device)
    ref_cam = _at_size(ref_cam, W, H)
    f64 = torch.float64
    u, v = torch.meshgrid(torch.arange(W, dtype=f64, device=dev), torch.arange(H, dtype=f64, device=dev),
                          indexing="xy")
    d = torch.as_tensor(ref_depth, dtype=f64, device=dev)
    has = d > 0
    pix = torch.stack([u * d, v * d, d], -1).reshape(-1, 3)
    T = lambda a: torch.as_tensor(np.asarray(a), dtype=f64, device=dev)  # noqa: E731
    X_ref = pix @ T(np.linalg.inv(ref_cam.K)).T  # ref camera coordinates
    count = torch.zeros(H * W, dtype=torch.int32, device=dev)
    for cam, sd in zip(src_cams, src_depths):
        sd = np.asarray(sd, dtype=np.float32)
        if sd.ndim != 2:
            raise ValueError(f"source depth must be (h, w), got {sd.shape}")
        h, w = sd.shape
        cam = _at_size(cam, w, h)
        rel = T(cam.cam_from_world @ ref_cam.world_from_cam)
        Xs = X_ref @ rel[:3, :3].T + rel[:3, 3]
        ps = Xs @ T(cam.K).T
        zs = ps[:, 2]
        us, vs = ps[:, 0] / zs.clamp_min(1e-9), ps[:, 1] / zs.clamp_min(1e-9)
        iu, iv = torch.round(us).long(), torch.round(vs).long()
        inside = (zs > 1e-9) & (iu >= 0) & (iu < w) & (iv >= 0) & (iv < h)
        sdt = torch.as_tensor(sd, dtype=f64, device=dev)
        ds = torch.zeros_like(zs)
        ds[inside] = sdt[iv[inside], iu[inside]]
        ok = inside & (ds > 0)
        # back: source pixel (us, vs) at the source's depth -> ref
        Xs2 = torch.stack([us * ds, vs * ds, ds], -1) @ T(np.linalg.inv(cam.K)).T
        inv_rel = torch.linalg.inv(rel)
        Xr2 = Xs2 @ inv_rel[:3, :3].T + inv_rel[:3, 3]
        pr = Xr2 @ T(ref_cam.K).T
        zr = pr[:, 2]
        ur, vr = pr[:, 0] / zr.clamp_min(1e-9), pr[:, 1] / zr.clamp_min(1e-9)
        err = torch.hypot(ur - u.reshape(-1), vr - v.reshape(-1))
        dref = d.reshape(-1)
        agree = ok & (zr > 0) & (err <= reproj_px) & ((zr - dref).abs() <= rel_tol * dref)
        count += agree.int()
    count[~has.reshape(-1)] = 0
    return count.reshape(H, W).cpu().numpy().astype(np.int64)


def select_sources(ref_cam: Camera, cams: dict[str, Camera], k: int = 4,
                   scene_depth: float | None = None, min_angle_deg: float = 2.0,
                   max_view_angle_deg: float = 60.0, min_overlap: float = 0.3,
                   exclude: Sequence[str] = ()) -> list[str]:
    """The `k` best neighbour views of `ref_cam` for stereo, best first.

    Criteria: the source's optical axis is within `max_view_angle_deg` of the reference's; at least
    `min_overlap` of a grid of reference pixels lifted to `scene_depth` (default: the median distance
    to the other cameras' centres, at least 1) projects inside the source image; the triangulation
    angle at the reference's look-at point X (at `scene_depth`) is >= `min_angle_deg` (baseline).
    Score (COLMAP/Hedman style): a Gaussian preferring a triangulation angle of ~10° (σ 5° below,
    15° above), times the cosine of the viewing-direction angle, times the overlap.
    """
    if k < 1:
        raise ValueError(f"k must be >= 1, got {k}")
    C = ref_cam.center
    others = {n: c for n, c in cams.items() if n not in exclude
              and not np.allclose(c.cam_from_world, ref_cam.cam_from_world)}
    if not others:
        return []
    if scene_depth is None:
        dists = [np.linalg.norm(c.center - C) for c in others.values()]
        scene_depth = max(1.0, float(np.median(dists)))
    X = C + scene_depth * ref_cam.viewing_direction
    # a 7 x 5 grid of reference pixels lifted to scene_depth: the overlap with each source
    gu, gv = np.meshgrid(np.linspace(0, ref_cam.width - 1, 7), np.linspace(0, ref_cam.height - 1, 5))
    grid = ref_cam.unproject(np.c_[gu.ravel(), gv.ravel()], np.full(gu.size, scene_depth))
    scored = []
    for name, cam in others.items():
        cos_v = float(np.dot(cam.viewing_direction, ref_cam.viewing_direction))
        if cos_v < math.cos(math.radians(max_view_angle_deg)):
            continue
        uv, z = cam.project(grid)
        overlap = float(np.mean((z > 0) & (uv[:, 0] >= -0.5) & (uv[:, 0] <= cam.width - 0.5)
                                & (uv[:, 1] >= -0.5) & (uv[:, 1] <= cam.height - 0.5)))
        if overlap < min_overlap:
            continue
        a, b = C - X, cam.center - X
        cosang = np.dot(a, b) / max(np.linalg.norm(a) * np.linalg.norm(b), 1e-12)
        ang = math.degrees(math.acos(float(np.clip(cosang, -1, 1))))
        if ang < min_angle_deg:
            continue
        sigma = 5.0 if ang < 10.0 else 15.0
        scored.append((math.exp(-((ang - 10.0) ** 2) / (2 * sigma ** 2)) * cos_v * overlap, name))
    scored.sort(key=lambda s: -s[0])
    return [n for _, n in scored[:k]]
