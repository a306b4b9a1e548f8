"""`textures.value_noise` in one numba pass: the same float64 operations in the same order and the
same 32-bit hash, so the same bits (tests/synthetic/test_noise_nb.py), without numpy's ~30
temporaries per call; the procedural textures evaluate it at every hit of every traced ray."""
from __future__ import annotations

import math

import numpy as np
from numba import njit

_M32 = 0xFFFFFFFF


@njit(cache=True)
def _hash(ix, iy, seed_term):
    # numba widens uint32 products to 64 bits: masking after each product is the uint32 wrap
    h = (((ix & _M32) * 0x8DA6B343) & _M32) ^ (((iy & _M32) * 0xD8163841) & _M32) ^ seed_term
    for _ in range(2):
        h = (((h ^ (h >> 16)) & _M32) * 0x45D9F3B) & _M32
    h = h ^ (h >> 16)
    return np.float64(h) * (1.0 / 4294967296.0)


@njit(cache=True)
def value_noise_nb(p, freq, seed_term):
    """(N,) value noise at (N, 2) float64 points; seed_term = (seed * 0x9E3779B1) mod 2^32."""
    n = p.shape[0]
    out = np.empty(n)
    for k in range(n):
        qx, qy = p[k, 0] * freq, p[k, 1] * freq
        fx0, fy0 = math.floor(qx), math.floor(qy)
        fx, fy = qx - fx0, qy - fy0
        u = fx * fx * (3 - 2 * fx)
        v = fy * fy * (3 - 2 * fy)
        ix, iy = np.uint64(np.int64(fx0)), np.uint64(np.int64(fy0))
        a = _hash(ix, iy, seed_term)
        b = _hash(ix + np.uint64(1), iy, seed_term)
        c = _hash(ix, iy + np.uint64(1), seed_term)
        d = _hash(ix + np.uint64(1), iy + np.uint64(1), seed_term)
        out[k] = (a * (1 - u) + b * u) * (1 - v) + (c * (1 - u) + d * u) * v
    return out
