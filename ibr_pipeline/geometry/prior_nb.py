"""The reflected-scene colour prior's per-view lookup as one fused numba loop.

`reflection_prior.seen_colours_np` is the reference: project the reflected points into a view,
test that the view sees them directly (nearest-pixel depth within tol x depth, not on a
reflector pixel), and sample the image bilinearly where it does. In numpy that is a dozen
full-length temporaries per view (projection, rounding, NaN guards, four gathers per channel);
reflector detection does it for up to `prior_views` views per captured view per candidate plane,
and it was the largest part of the stage. One pass per point does the same arithmetic without
them. Tested against the reference (tests/reflection/test_prior_nb.py).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

# |pixel coordinate| beyond this is outside any image (and safe to round to an integer)
_FAR = 1e9


@njit(cache=True)
def _seen_colours(R, t, K, X, depth, exclude, img, tol, out):
    H, W = depth.shape
    C = img.shape[2]
    n = 0
    for i in range(X.shape[0]):
        for c in range(C):
            out[i, c] = np.nan
        x, y, z = X[i, 0], X[i, 1], X[i, 2]
        c0 = x * R[0, 0] + y * R[0, 1] + z * R[0, 2] + t[0]
        c1 = x * R[1, 0] + y * R[1, 1] + z * R[1, 2] + t[1]
        c2 = x * R[2, 0] + y * R[2, 1] + z * R[2, 2] + t[2]
        if not (c2 > 0.0) or not math.isfinite(c2):
            continue
        u = (c0 * K[0, 0] + c1 * K[0, 1] + c2 * K[0, 2]) / c2
        v = (c0 * K[1, 0] + c1 * K[1, 1] + c2 * K[1, 2]) / c2
        if not (abs(u) < _FAR and abs(v) < _FAR):  # also false for NaN
            continue
        xi = int(np.rint(u))
        yi = int(np.rint(v))
        if xi < 0 or xi >= W or yi < 0 or yi >= H:
            continue
        d = np.float64(depth[yi, xi])
        if not (d > 0.0) or not (abs(d - c2) < tol * min(d, c2)) or exclude[yi, xi]:
            continue
        xx = min(max(u, 0.0), W - 1.0)
        yy = min(max(v, 0.0), H - 1.0)
        x0 = min(int(math.floor(xx)), max(W - 2, 0))
        y0 = min(int(math.floor(yy)), max(H - 2, 0))
        ax, ay = xx - x0, yy - y0
        x1, y1 = min(x0 + 1, W - 1), min(y0 + 1, H - 1)
        for c in range(C):
            out[i, c] = ((1.0 - ay) * ((1.0 - ax) * np.float64(img[y0, x0, c])
                                       + ax * np.float64(img[y0, x1, c]))
                         + ay * ((1.0 - ax) * np.float64(img[y1, x0, c])
                                 + ax * np.float64(img[y1, x1, c])))
        n += 1
    return n


def seen_colours(camera, points: np.ndarray, depth: np.ndarray, exclude: np.ndarray,
                 image: np.ndarray, tol: float) -> tuple[np.ndarray, int]:
    """points (N, 3) world, depth (H, W) z-depth (0 = none), exclude (H, W) bool, image (H, W, C)
    of `camera`'s size. Returns (N, C) float64 bilinear colours where the view sees the point
    directly, NaN elsewhere, and how many it sees."""
    X = np.ascontiguousarray(points, np.float64)
    if X.ndim != 2 or X.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {X.shape}")
    H, W = camera.height, camera.width
    if np.shape(depth) != (H, W) or np.shape(exclude) != (H, W) or np.ndim(image) != 3 \
            or np.shape(image)[:2] != (H, W):
        raise ValueError(f"depth, exclude (H, W) and image (H, W, C) must be {H}x{W}: got "
                         f"{np.shape(depth)}, {np.shape(exclude)}, {np.shape(image)}")
    out = np.empty((len(X), np.shape(image)[2]), np.float64)
    n = _seen_colours(np.ascontiguousarray(camera.R, np.float64),
                      np.ascontiguousarray(camera.t, np.float64),
                      np.ascontiguousarray(camera.K, np.float64), X,
                      np.ascontiguousarray(depth), np.ascontiguousarray(exclude, np.bool_),
                      np.ascontiguousarray(image), float(tol), out)
    return out, int(n)
