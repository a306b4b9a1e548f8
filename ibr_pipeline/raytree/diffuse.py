"""Diffuse flow (Lochmann et al. 2014, §3.4 "Diffuse flow", Fig. 4 a-d).

  forward flow   f_d^-1(l_old) = project(M_new, W_d(l_old)) - l_old
  backward flow  f_d(l_new): splat every old location to round(l_new) with a depth test (Fig. 4b),
                 replace each pixel's flow by the one closest to the camera in its 3x3
                 neighbourhood (closes magnification holes, dilates edges, Fig. 4c), then one
                 fixed-point-iteration step (Bowles et al. 2012) x1 = l_new - f_d^-1(x0) that
                 discards pixels where the iteration does not converge (Fig. 4d).
The result is, per new pixel, a continuous old-image location x1 = l_new + f_d(l_new) and a mask.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from . import ops

_BIG = torch.iinfo(torch.int64).max


@dataclass
class Flow:
    src: torch.Tensor      # (Hn, Wn, 2) old-image location read by each new pixel (l + f_d(l))
    ok: torch.Tensor       # (Hn, Wn) bool, flow defined (converged)
    splat_hit: torch.Tensor  # (Hn, Wn) bool, a point was splatted here (Fig. 4b)
    filled: torch.Tensor   # (Hn, Wn) bool, defined after the 3x3 fill (Fig. 4c)
    pix: torch.Tensor | None = None      # (K,) flat indices of the ok new pixels (any order)
    taps: ops.Taps | None = None         # old-image bilinear taps of src at those pixels
    sampler: ops.Sampler | None = None   # the root sampler the taps belong to
    values: torch.Tensor | None = None   # (K, C) the `extra` buffer read at the taps


def splat_keys(uv: torch.Tensor, z: torch.Tensor, valid: torch.Tensor, new_size: tuple[int, int]):
    """Point splatting with depth test (§3.4 `splat`): (Hn*Wn,) int64 keys z_q * P + old index,
    the smallest key per new pixel wins (closest to the camera); _BIG where nothing landed."""
    H, W = valid.shape
    Wn, Hn = new_size
    n_old = H * W
    t = torch.round(uv.reshape(-1, 2)).long()
    zf = z.reshape(-1)
    tx, ty = t[:, 0], t[:, 1]
    ok = valid.reshape(-1) & (zf > 1e-6) & (tx >= 0) & (tx < Wn) & (ty >= 0) & (ty < Hn)
    # no compaction: points that do not land go to a spare slot at the end of the buffer
    target = torch.where(ok, ty * Wn + tx, torch.full_like(tx, Hn * Wn))
    zq = torch.round(zf.clamp(0, 1e4) * 1e5).long()  # 10 um depth quantum for the depth test
    key = zq * n_old + torch.arange(n_old, device=uv.device)
    buf = torch.full((Hn * Wn + 1,), _BIG, dtype=torch.int64, device=uv.device)
    buf.scatter_reduce_(0, target, key, reduce="amin")
    buf = buf[:-1]
    return buf


def closest_3x3(keys: torch.Tensor, new_size: tuple[int, int]) -> torch.Tensor:
    """§3.4: "the flow at each pixel is replaced by the flow of the pixel that is closest to the
    camera in a 3x3 neighborhood" (min key over the 9 neighbours, as two separable 3-tap mins)."""
    Wn, Hn = new_size
    # padded with _BIG by hand: F.pad's float `value` turns int64 max into int64 min, which made
    # every border pixel "closest" to a garbage key (found by the numba backend's tests)
    k = torch.full((Hn + 2, Wn + 2), _BIG, dtype=torch.int64, device=keys.device)
    k[1:-1, 1:-1] = keys.view(Hn, Wn)
    r = torch.minimum(torch.minimum(k[:, :-2], k[:, 1:-1]), k[:, 2:])      # (Hn + 2, Wn)
    return torch.minimum(torch.minimum(r[:-2], r[1:-1]), r[2:]).reshape(-1)


def diffuse_flow(pos: torch.Tensor, valid: torch.Tensor, depth: torch.Tensor, P_new: torch.Tensor,
                 new_size: tuple[int, int], fpi_eps: float = 0.5, rel_tol: float = 0.05,
                 fallback: bool = True, sampler: ops.Sampler | None = None,
                 extra: torch.Tensor | None = None) -> Flow:
    """Backward diffuse flow for positions `pos` (H, W, 3) seen at old z-depth `depth` (H, W).

    fpi_eps: convergence threshold of the fixed-point step in new-image pixels (bilinear
    residual; 2 x fpi_eps where the old neighbourhood is not smooth and the nearest tap is used).
    fallback: where the 3x3-filled candidate fails the test, also try the directly splatted
    point (our addition: keeps background pixels next to a foreground edge instead of leaving a
    hole for push-pull); evaluated only on the pixels that failed.
    The result also lists the converged pixels and their bilinear taps, so the caller samples
    every root buffer at the sub-pixel fixed-point location without recomputing them; `extra`
    (1, C, H, W) (the sampler's chw layout, e.g. the root radiance) is read in the same bilinear
    pass as the fixed-point residual and returned as Flow.values (K, C)."""
    ops.check(pos, (None, None, 3), "positions")
    ops.check(valid, tuple(pos.shape[:2]), "valid")
    ops.check(depth, tuple(pos.shape[:2]), "depth")
    ops.check(P_new, (3, 4), "P_new")
    H, W = valid.shape
    Wn, Hn = new_size
    n_old = H * W
    dev = pos.device
    uv, z = ops.project(P_new, pos)            # l_new = project(M_new, W_d)  (§3.4)
    direct = splat_keys(uv, z, valid, new_size)
    filled = closest_3x3(direct, new_size)
    sampler = sampler or ops.Sampler(valid, depth, rel_tol)
    uv_flat = uv.reshape(-1, 2)
    uv_chw = sampler.chw(uv)
    if extra is not None:
        uv_chw = torch.cat([uv_chw, extra], 1)
    eps2 = fpi_eps * fpi_eps

    def xy(flat_idx, width):
        """(N, 2) float (x, y) of flat pixel indices (float32 is exact below 2^24 pixels)."""
        f = flat_idx.to(pos.dtype)
        y = torch.floor(f / width)
        return torch.stack([f - y * width, y], -1)

    def fpi(keys, pix):
        """One fixed-point step (Bowles et al. 2012) for the new pixels `pix` from the old pixels
        encoded in keys[pix]: x1 = l_new - f^-1(x0) = x0 + (l_new - uv(x0)); converged when the
        bilinear re-projection of x1 lands within fpi_eps of l_new."""
        idx = keys[pix] % n_old
        p = xy(pix, Wn)
        x1 = xy(idx, W) + (p - uv_flat[idx])
        t = sampler.taps(x1)
        vals, smooth, defined = sampler.sample(uv_chw, x1, t)
        res2 = ((vals[:, :2] - p) ** 2).sum(-1)
        conv = defined & (res2 < torch.where(smooth, eps2, 4 * eps2)) & \
            (x1[:, 0] > -0.5) & (x1[:, 0] < W - 0.5) & (x1[:, 1] > -0.5) & (x1[:, 1] < H - 0.5)
        sel = torch.nonzero(conv).squeeze(-1)   # keep the converged ones (and their taps)
        return pix[sel], x1[sel], t[sel], vals[sel, 2:]

    src = torch.zeros(Hn * Wn, 2, device=dev, dtype=pos.dtype)
    ok = torch.zeros(Hn * Wn, dtype=torch.bool, device=dev)
    cand = torch.nonzero(filled != _BIG).squeeze(-1)
    pix, x1, taps, vals = fpi(filled, cand)
    src[pix] = x1
    ok[pix] = True
    if fallback:
        fb = torch.nonzero(~ok & (direct != _BIG)).squeeze(-1)
        if len(fb):
            fb, xb, tb, vb = fpi(direct, fb)
            src[fb] = xb
            ok[fb] = True
            pix, taps, vals = torch.cat([pix, fb]), ops.Taps.cat([taps, tb]), torch.cat([vals, vb])
    return Flow(src=src.view(Hn, Wn, 2), ok=ok.view(Hn, Wn), splat_hit=(direct != _BIG).view(Hn, Wn),
                filled=(filled != _BIG).view(Hn, Wn), pix=pix, taps=taps, sampler=sampler,
                values=vals if extra is not None else None)


def projection_matrix(K, cam_from_world, device) -> torch.Tensor:
    """3x4 pixel projection P = K [R | t] of a camera (the new M_new of §3.4)."""
    import numpy as np
    P = np.asarray(K, np.float64) @ np.asarray(cam_from_world, np.float64)[:3]
    return torch.as_tensor(P, dtype=torch.float32, device=device)
