"""The renderer's per-frame post-processing (§5.1.4 holes, Eq. 3) as fused numba loops.

`blend.fill_holes` / `blend.compose` are the numpy references. On a 640×480 frame each of their
steps is a full pass over a 4.9 MB (H, W, 4) float32 array (weighting, the pull levels, the
full-resolution upsampling of the fill, the seam blend, clipping, Eq. 3) and together they were
a third of a frame's time on the CPU (docs/BENCHMARKS.md, "where a 640×480 frame's time goes").
Here the same arithmetic runs in one pass per step: the push pyramid stays OpenCV's INTER_AREA
resize, the pull and the seam blend are fused, and the fill is upsampled (OpenCV's INTER_LINEAR
convention, computed in place) only at the pixels that take some of it. Tested against the
references (tests/render/test_post_nb.py).
"""
from __future__ import annotations

import functools

import numpy as np
from numba import njit


@njit(cache=True)
def _normalise(acc, bacc, front, color4, covered, depth):
    """color4 = acc / acc.w with channel 3 = bacc / acc.w (0 where acc.w = 0); covered = acc.w > 0;
    depth = front where covered and front < 1e29, else 0. Returns the (x0, y0, x1, y1) bounds
    (inclusive) of color4[..., 3] > 1e-4, x1 < x0 when there is none."""
    H, W = covered.shape
    x0, y0, x1, y1 = W, H, -1, -1
    one = np.float32(1.0)
    for y in range(H):
        for x in range(W):
            w = acc[y, x, 3]
            c = w > 0
            covered[y, x] = c
            inv = one / (w if c else one)
            for ch in range(3):
                color4[y, x, ch] = acc[y, x, ch] * inv
            b = bacc[y, x] * inv
            color4[y, x, 3] = b
            depth[y, x] = front[y, x] if (c and front[y, x] < 1e29) else 0.0
            if b > 1e-4:
                x0, y0 = min(x0, x), min(y0, y)
                x1, y1 = max(x1, x), max(y1, y)
    return x0, y0, x1, y1


def normalise(acc: np.ndarray, bacc: np.ndarray, front: np.ndarray):
    """The normalised blend of the surface layer's accumulators (ibr.py's pass 3 read-back):
    (color4 (H, W, 4), covered (H, W) bool, depth (H, W), box (x, y, w, h) of beta > 1e-4 or None)."""
    acc = np.ascontiguousarray(acc, np.float32)
    H, W = acc.shape[:2]
    if acc.shape != (H, W, 4) or np.shape(bacc) != (H, W) or np.shape(front) != (H, W):
        raise ValueError(f"need acc (H, W, 4), bacc and front (H, W); got {acc.shape}, "
                         f"{np.shape(bacc)}, {np.shape(front)}")
    color4 = np.empty((H, W, 4), np.float32)
    covered = np.empty((H, W), np.bool_)
    depth = np.empty((H, W), np.float32)
    x0, y0, x1, y1 = _normalise(acc, np.ascontiguousarray(bacc, np.float32),
                                np.ascontiguousarray(front, np.float32), color4, covered, depth)
    box = None if x1 < x0 else (int(x0), int(y0), int(x1 - x0 + 1), int(y1 - y0 + 1))
    return color4, covered, depth, box


@njit(cache=True)
def _weighted(color, weight, out):
    for y in range(weight.shape[0]):
        for x in range(weight.shape[1]):
            for c in range(color.shape[2]):
                out[y, x, c] = color[y, x, c] * weight[y, x]


@njit(cache=True)
def _divide(cw, ww, out):
    for y in range(ww.shape[0]):
        for x in range(ww.shape[1]):
            d = max(ww[y, x], np.float32(1e-12))
            for c in range(cw.shape[2]):
                out[y, x, c] = cw[y, x, c] / d


@njit(cache=True)
def _pull(cw, ww, up, out):
    """One pull level of blend._pyramid_fill: well-covered cells keep their own colour."""
    for y in range(ww.shape[0]):
        for x in range(ww.shape[1]):
            a = min(ww[y, x] * np.float32(4.0), np.float32(1.0))
            d = max(ww[y, x], np.float32(1e-12))
            for c in range(cw.shape[2]):
                out[y, x, c] = a * (cw[y, x, c] / d) + (np.float32(1.0) - a) * up[y, x, c]


def _linear_taps(n_dst: int, n_src: int):
    """OpenCV INTER_LINEAR source index and weight per destination index (clamped borders)."""
    scale = n_src / n_dst
    f = (np.arange(n_dst) + 0.5) * scale - 0.5
    i = np.floor(f).astype(np.int64)
    a = (f - i).astype(np.float32)
    low, high = i < 0, i >= n_src - 1
    a[low | high] = 0.0
    i = np.clip(i, 0, n_src - 1)
    return i, np.minimum(i + 1, n_src - 1), a


@njit(cache=True)
def _seam(color, fill, dist, inv_decay, ix0, ix1, ax, iy0, iy1, ay, out):
    """out = a·color + (1 − a)·upsampled fill, a = min(dist / decay, 1) (blend.fill_holes)."""
    H, W, C = color.shape
    one = np.float32(1.0)
    for y in range(H):
        r0, r1, fy = iy0[y], iy1[y], ay[y]
        for x in range(W):
            a = min(dist[y, x] * inv_decay, one)
            if a >= one:
                for c in range(C):
                    out[y, x, c] = color[y, x, c]
                continue
            c0, c1, fx = ix0[x], ix1[x], ax[x]
            for c in range(C):
                top = fill[r0, c0, c] + (fill[r0, c1, c] - fill[r0, c0, c]) * fx
                bot = fill[r1, c0, c] + (fill[r1, c1, c] - fill[r1, c0, c]) * fx
                f = top + (bot - top) * fy
                out[y, x, c] = a * color[y, x, c] + (one - a) * f


def _half_fill(color: np.ndarray, weight: np.ndarray, levels: int) -> np.ndarray:
    """blend._pyramid_fill without its last step (the upsampling to full resolution)."""
    import cv2

    from .blend import push_pyramid

    cw = np.empty_like(color)
    _weighted(color, weight, cw)
    pyr = push_pyramid(cw, weight, levels)
    cw, ww = pyr[-1]
    out = np.empty_like(cw)
    _divide(cw, ww, out)
    for cw, ww in reversed(pyr[:-1]):
        up = cv2.resize(out, (ww.shape[1], ww.shape[0]), interpolation=cv2.INTER_LINEAR)
        out = np.empty_like(cw)
        _pull(cw, ww, up.reshape(cw.shape), out)
    return out


def fill_holes(color: np.ndarray, covered: np.ndarray, decay_px: float) -> np.ndarray:
    """`blend.fill_holes` (same arguments, same result up to float rounding), fused."""
    import cv2

    color = np.ascontiguousarray(color, np.float32)
    covered = np.asarray(covered, bool)
    if color.ndim != 3 or covered.shape != color.shape[:2]:
        raise ValueError(f"covered {covered.shape} does not match color {color.shape}")
    if covered.all() or not covered.any():
        return color
    H, W = covered.shape
    cov8 = covered.astype(np.uint8)
    fill = _half_fill(color, cov8.astype(np.float32), 12)
    dist = cv2.distanceTransform(cov8, cv2.DIST_L2, 3)
    ix0, ix1, ax = _linear_taps(W, fill.shape[1])
    iy0, iy1, ay = _linear_taps(H, fill.shape[0])
    out = np.empty_like(color)
    _seam(color, np.ascontiguousarray(fill), dist, np.float32(1.0 / max(decay_px, 1e-9)),
          ix0, ix1, ax, iy0, iy1, ay, out)
    return out


SRGB_LUT_SEGMENTS = 4096


@functools.cache
def srgb_lut() -> np.ndarray:
    """sRGB decoding sampled at SRGB_LUT_SEGMENTS + 1 points of [0, 1]: linear interpolation in
    it is within 1e-6 of io.images.srgb_to_linear, at a table read instead of a pow per value."""
    from ..io.images import srgb_to_linear
    return np.ascontiguousarray(srgb_to_linear(np.linspace(0.0, 1.0, SRGB_LUT_SEGMENTS + 1)),
                                np.float32)


_NO_LUT = np.zeros(0, np.float32)


@njit(cache=True)
def _decoded(v, lut):
    """v itself (empty lut) or its sRGB decoding through `lut`, v clipped to [0, 1]."""
    n = lut.shape[0] - 1
    if n < 1:
        return v
    f = min(max(v, np.float32(0.0)), np.float32(1.0)) * np.float32(n)
    i = min(int(f), n - 1)
    return lut[i] + (lut[i + 1] - lut[i]) * (f - np.float32(i))


@njit(cache=True)
def _finish(color4, i1, bx, by, out, beta, lut):
    """beta = clip(color4.a, 0, 1); out = max(dec(color4.rgb) + beta·dec(I1) (inside the box), 0),
    dec = the sRGB decoding through `lut` (identity when it is empty)."""
    H, W = beta.shape
    bh, bw = i1.shape[0], i1.shape[1]
    for y in range(H):
        for x in range(W):
            b = min(max(color4[y, x, 3], np.float32(0.0)), np.float32(1.0))
            beta[y, x] = b
            inside = 0 <= y - by < bh and 0 <= x - bx < bw
            for c in range(3):
                v = _decoded(color4[y, x, c], lut)
                if inside:
                    v = v + b * _decoded(i1[y - by, x - bx, c], lut)
                out[y, x, c] = max(v, np.float32(0.0))


def finish(color4: np.ndarray, i1: np.ndarray | None = None, box=None, srgb: bool = False):
    """Eq. 3 on the filled surface layer: (colour (H, W, 3) clipped at 0, beta (H, W) in [0, 1]);
    `i1` (h, w, 3) is the reflection layer inside `box` (x, y, w, h), 0 elsewhere. With `srgb`
    both layers were blended as sRGB values and are decoded to linear first (Eq. 3 adds light)."""
    color4 = np.ascontiguousarray(color4, np.float32)
    H, W = color4.shape[:2]
    if i1 is None:
        i1, box = np.zeros((0, 0, 3), np.float32), (0, 0, 0, 0)
    x, y, bw, bh = box
    if np.shape(i1) != (bh, bw, 3) or x < 0 or y < 0 or x + bw > W or y + bh > H:
        raise ValueError(f"I1 {np.shape(i1)} does not fit box {box} in a {W}x{H} frame")
    out = np.empty((H, W, 3), np.float32)
    beta = np.empty((H, W), np.float32)
    _finish(color4, np.ascontiguousarray(i1, np.float32), int(x), int(y), out, beta,
            srgb_lut() if srgb else _NO_LUT)
    return out, beta
