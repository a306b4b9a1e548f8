"""`decompose_terms.sample_bilinear` in one numba pass: the same float64 operations in the same
order, so the same bits (tests/reflection/test_bilinear_nb.py), without numpy's four gathered
(N, C) copies and eight temporaries. Its callers (the image step's residuals, the pose step's
evaluations, the leave-one-out acceptance test) sample ~10^5 points thousands of times per
reflection stage."""
from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True)
def sample_bilinear_nb(img, pos):
    """(N, C) float64 samples of the (H, W, C) image at finite (N, 2) float64 positions, clamped
    to the image, as `bilinear_cells` + `sample_bilinear` compute them."""
    H, W, C = img.shape
    N = pos.shape[0]
    out = np.empty((N, C))
    xm, ym = max(W - 2, 0), max(H - 2, 0)
    for n in range(N):
        x = min(max(pos[n, 0], 0.0), W - 1.0)
        y = min(max(pos[n, 1], 0.0), H - 1.0)
        x0 = min(int(math.floor(x)), xm)
        y0 = min(int(math.floor(y)), ym)
        x1, y1 = min(x0 + 1, W - 1), min(y0 + 1, H - 1)
        ax, ay = x - x0, y - y0
        for c in range(C):
            a = (1 - ax) * np.float64(img[y0, x0, c]) + ax * np.float64(img[y0, x1, c])
            b = (1 - ax) * np.float64(img[y1, x0, c]) + ax * np.float64(img[y1, x1, c])
            out[n, c] = (1 - ay) * a + ay * b
    return out
