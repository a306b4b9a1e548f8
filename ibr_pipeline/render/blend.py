"""Reference (numpy) implementations of the blending mathematics of Xu et al. 2021, §5.1.3–5.1.4.

The GL renderer (`render/ibr.py` + `render/shaders`) computes the same quantities per fragment;
tests compare its output with these functions. Texture-space weights (feathering, edge decay) are
also *computed* here once per view and uploaded as the texture alpha, as the paper does.
"""
from __future__ import annotations

import functools

import numpy as np

COST_MARGIN = 0.17     # §5.1.3: keep points whose IBR cost is within 0.17 of the smallest
DEPTH_TOL_M = 0.03     # §5.1.3: a pixel contributes when within 3 cm of the front-most depth
DELTA = 0.033          # Eq. 15: w_k = exp(−d_k/δ), δ = 0.033
# §5.1.4 feathering: weight falling smoothly to 0 at the image border. Xu et al. use 20 px; 5 px
# here, because a wide feather hands the border of every view to views farther from the novel
# one: held-out PSNR +0.19 to +0.24 dB on three real captures (docs/RENDERING.md)
FEATHER_PX = 5
EDGE_DECAY_PX = 5      # §5.1.4: weight decay within ±5 px of depth edges
WEIGHT_FLOOR = 1e-3    # ours: decayed texture weights never reach exactly 0 (see texture_alpha)
VIEW_WEIGHT_FLOOR = 1e-12  # ours: a far view keeps a tiny weight instead of underflowing to 0
HOLE_DECAY_PX = 2      # ours: warped pixels within 2 px of a hole are blended with the fill


def ibr_cost(t_k: np.ndarray, t_n: np.ndarray, x: np.ndarray) -> np.ndarray:
    """§5.1.3 (Hedman et al. 2016): c = ∠(t_k − x, t_n − x)·π/180 + max(0, 1 − ‖t_n − x‖/‖t_k − x‖).

    t_k, t_n: (3,) optical centres; x: (..., 3) points. The angle in degrees × π/180 is radians.
    """
    x = np.asarray(x, dtype=np.float64)
    if x.shape[-1:] != (3,) or np.shape(t_k) != (3,) or np.shape(t_n) != (3,):
        raise ValueError(f"need t_k (3,), t_n (3,), x (..., 3); got {np.shape(t_k)}, "
                         f"{np.shape(t_n)}, {x.shape}")
    a, b = np.asarray(t_k) - x, np.asarray(t_n) - x
    na, nb = np.linalg.norm(a, axis=-1), np.linalg.norm(b, axis=-1)
    cos = np.sum(a * b, axis=-1) / np.maximum(na * nb, 1e-12)
    ang = np.arccos(np.clip(cos, -1.0, 1.0))
    return ang + np.maximum(0.0, 1.0 - nb / np.maximum(na, 1e-12))


def view_weights(dist_k: np.ndarray, delta: float = DELTA) -> np.ndarray:
    """Eq. 15: w_k = exp(−d_k/δ), rescaled by exp(d_min/δ) (which cancels in the normalised blend)
    so that float32 does not underflow; floored at VIEW_WEIGHT_FLOOR."""
    d = np.asarray(dist_k, dtype=np.float64)
    if d.ndim != 1:
        raise ValueError(f"dist_k must be (K,), got {d.shape}")
    if d.size == 0:
        return d
    return np.maximum(np.exp(-(d - d.min()) / delta), VIEW_WEIGHT_FLOOR)


def _ramp(dist: np.ndarray, width: float) -> np.ndarray:
    """Smooth 0→1 ramp (smoothstep) over [0, width]."""
    s = np.clip(dist / max(width, 1e-9), 0.0, 1.0)
    return s * s * (3.0 - 2.0 * s)


def feather_weight(height: int, width: int, feather_px: float = FEATHER_PX) -> np.ndarray:
    """§5.1.4 feathering: weight rising smoothly from 0 at the image border to 1 at feather_px.
    Read-only: one array per size, shared by every view of that size (a model loads hundreds)."""
    if height <= 0 or width <= 0:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    return _feather(int(height), int(width), float(feather_px))


@functools.lru_cache(maxsize=8)
def _feather(height: int, width: int, feather_px: float) -> np.ndarray:
    v = np.minimum(np.arange(height), np.arange(height)[::-1]) + 0.5
    u = np.minimum(np.arange(width), np.arange(width)[::-1]) + 0.5
    w = _ramp(np.minimum(v[:, None], u[None, :]), feather_px).astype(np.float32)
    w.setflags(write=False)
    return w


def edge_decay(edges: np.ndarray, decay_px: float = EDGE_DECAY_PX) -> np.ndarray:
    """§5.1.4 weight decay near depth edges: 0 on an edge pixel, rising to 1 at decay_px.

    `edges` (H, W) bool/uint8 depth-edge map (Eq. 1 edges of `view_depth`). The distance to the
    nearest edge pixel (Euclidean distance transform) is used for "±5 px along edge gradients".
    """
    import cv2

    e = np.asarray(edges)
    if e.ndim != 2:
        raise ValueError(f"edges must be (H, W), got {e.shape}")
    if not e.any() or decay_px <= 0:  # no decay: edge pixels keep their full weight too
        return np.ones(e.shape, np.float32)
    dist = cv2.distanceTransform((e == 0).astype(np.uint8), cv2.DIST_L2, 5)
    return _ramp(dist, decay_px).astype(np.float32)


def texture_alpha(edges: np.ndarray, feather_px: float = FEATHER_PX,
                  decay_px: float = EDGE_DECAY_PX, floor: float = WEIGHT_FLOOR) -> np.ndarray:
    """The per-view weight stored in the texture alpha (§5.1.4): feathering × edge decay.

    Floored at `floor` (ours): where every view's weight has decayed (a pixel that only border or
    edge pixels see), the blend still takes their colour instead of leaving a hole.
    """
    h, w = np.asarray(edges).shape[:2]
    return np.maximum(feather_weight(h, w, feather_px) * edge_decay(edges, decay_px),
                      floor).astype(np.float32)


def fuzzy_depth_test(depth: np.ndarray, cost: np.ndarray, cost_margin: float = COST_MARGIN,
                     depth_tol: float = DEPTH_TOL_M) -> tuple[np.ndarray, np.ndarray]:
    """§5.1.3 fuzzy depth test over K warped views.

    depth, cost: (K, H, W), depth 0 (or non-finite) where view k does not cover the pixel.
    Returns the front-most depth map (H, W) (0 = nobody covers it) — the smallest depth among the
    points whose IBR cost is within `cost_margin` of the smallest cost — and the (K, H, W) mask
    of points within `depth_tol` of it, i.e. the ones that contribute to the blend.
    """
    depth = np.asarray(depth, dtype=np.float64)
    cost = np.asarray(cost, dtype=np.float64)
    if depth.shape != cost.shape or depth.ndim != 3:
        raise ValueError(f"depth and cost must both be (K, H, W), got {depth.shape}, {cost.shape}")
    valid = np.isfinite(depth) & (depth > 0) & np.isfinite(cost)
    c = np.where(valid, cost, np.inf)
    cmin = c.min(axis=0) if len(c) else np.full(depth.shape[1:], np.inf)
    keep = valid & (c <= cmin + cost_margin)
    front = np.where(keep, depth, np.inf).min(axis=0) if len(c) else cmin
    front = np.where(np.isfinite(front), front, 0.0)
    contrib = valid & (np.abs(depth - front) < depth_tol) & (front > 0)
    return front.astype(np.float32), contrib


def blend(colors: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normalised weighted blend: colors (K, H, W, C), weights (K, H, W) (0 = no contribution).

    Returns (H, W, C) colour (0 where the weight sum is 0) and the (H, W) weight sum."""
    colors = np.asarray(colors, dtype=np.float64)
    weights = np.asarray(weights, dtype=np.float64)
    if colors.ndim != 4 or weights.shape != colors.shape[:3]:
        raise ValueError(f"colors must be (K, H, W, C) and weights (K, H, W); got {colors.shape}, "
                         f"{weights.shape}")
    wsum = weights.sum(axis=0)
    acc = np.einsum("khw,khwc->hwc", weights, colors)
    out = np.where(wsum[..., None] > 0, acc / np.maximum(wsum, 1e-30)[..., None], 0.0)
    return out.astype(np.float32), wsum.astype(np.float32)


def push_pyramid(cw: np.ndarray, ww: np.ndarray, levels: int) -> list:
    """The push half of push-pull: weighted colour `cw` (H, W, C) and weight `ww` (H, W) box-filtered
    to half size per level, [(cw, ww), ...] from level 1 down, stopping where every cell has weight."""
    import cv2

    pyr = []
    for _ in range(levels):
        if min(ww.shape) < 2:
            break
        size = ((ww.shape[1] + 1) // 2, (ww.shape[0] + 1) // 2)
        cw = cv2.resize(cw, size, interpolation=cv2.INTER_AREA).reshape(size[1], size[0], -1)
        ww = cv2.resize(ww, size, interpolation=cv2.INTER_AREA)
        pyr.append((cw, ww))
        if ww.min() > 0:
            break
    return pyr


def _pyramid_fill(color: np.ndarray, weight: np.ndarray, levels: int) -> np.ndarray:
    """Push-pull from level 1 down: the smooth fill at half resolution (covered cells keep their
    colour there), returned upsampled to full resolution."""
    import cv2

    h, w = weight.shape
    pyr = push_pyramid(color * weight[..., None], weight, levels)
    cw, ww = pyr[-1]
    out = cw / np.maximum(ww, 1e-12)[..., None]
    for cw, ww in reversed(pyr[:-1]):  # pull: fill each level from the coarser one
        up = cv2.resize(out, (ww.shape[1], ww.shape[0]), interpolation=cv2.INTER_LINEAR)
        up = up.reshape(ww.shape[0], ww.shape[1], -1)
        a = np.minimum(ww * 4.0, 1.0)[..., None]  # well-covered cells keep their own colour
        out = a * (cw / np.maximum(ww, 1e-12)[..., None]) + (1 - a) * up
    return cv2.resize(out, (w, h), interpolation=cv2.INTER_LINEAR).reshape(h, w, -1)


def push_pull(color: np.ndarray, weight: np.ndarray, levels: int = 12) -> np.ndarray:
    """Push-pull interpolation (Gortler et al. 1996; used by Lochmann et al. 2014 for holes).

    color (H, W, C) and coverage weight (H, W) in [0, 1]; returns (H, W, C): covered pixels
    (weight 1) keep their colour, uncovered ones (weight 0) are filled from a weighted pyramid."""
    color = np.asarray(color, dtype=np.float32)
    w = np.clip(np.asarray(weight, dtype=np.float32), 0.0, 1.0)
    if color.ndim != 3 or w.shape != color.shape[:2]:
        raise ValueError(f"color must be (H, W, C) and weight (H, W); got {color.shape}, {w.shape}")
    if w.min() > 0:
        return color
    fill = _pyramid_fill(color, w, levels)
    return (w[..., None] * color + (1 - w[..., None]) * fill).astype(np.float32)


def fill_holes(color: np.ndarray, covered: np.ndarray,
               decay_px: float = HOLE_DECAY_PX) -> np.ndarray:
    """§5.1.4 holes (our alternative to tile-based voxel rendering, see docs/RENDERING.md):
    uncovered pixels take a push-pull fill; the warped result's weight decays to that fill within
    `decay_px` of a hole's border (the paper's "weight decay at the hole boundary"), so the seam
    between the warped and the filled parts is smooth."""
    import cv2

    color = np.asarray(color, dtype=np.float32)
    covered = np.asarray(covered, bool)
    if color.ndim != 3 or covered.shape != color.shape[:2]:
        raise ValueError(f"covered {covered.shape} does not match color {color.shape}")
    if covered.all() or not covered.any():
        return color
    fill = _pyramid_fill(color, covered.astype(np.float32), 12)
    dist = cv2.distanceTransform(covered.astype(np.uint8), cv2.DIST_L2, 3)
    a = np.minimum(dist * np.float32(1.0 / max(decay_px, 1e-9)), np.float32(1.0))  # 0 in holes
    return cv2.blendLinear(np.ascontiguousarray(color), np.ascontiguousarray(fill, np.float32),
                           a, 1.0 - a)


def compose(i0: np.ndarray, beta: np.ndarray, i1: np.ndarray) -> np.ndarray:
    """Xu et al. Eq. 3: I = I0 + beta · I1 (in the linear values we store)."""
    i0, i1 = np.asarray(i0), np.asarray(i1)
    beta = np.asarray(beta)
    if i0.shape != i1.shape or beta.shape != i0.shape[:2]:
        raise ValueError(f"need I0, I1 (H, W, 3) and beta (H, W); got {i0.shape}, {i1.shape}, "
                         f"{beta.shape}")
    return (i0 + beta[..., None] * i1).astype(np.float32)
