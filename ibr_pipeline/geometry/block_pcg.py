"""Jacobi-preconditioned conjugate gradients with several right-hand sides and fixed variables
(the image step of the reflection decomposition, decompose.Problem.image_step; moved out of
decompose.py to keep that module small)."""
from __future__ import annotations

import numpy as np


def _block_pcg(H, g: np.ndarray, x0: np.ndarray, free: np.ndarray, iterations: int = 150,
               tol: float = 1e-6) -> np.ndarray:
    """Jacobi-preconditioned CG for H x = g with several right-hand sides (columns of g), the
    variables where `free` is False held at their value in x0 (the active set of the box)."""
    F = free.astype(np.float64)
    xb = x0 * (1 - F)
    rhs = F * (g - H @ xb)
    dinv = 1.0 / np.maximum(H.diagonal(), 1e-12)[:, None]
    x = x0 * F

    def mv(v):
        return F * (H @ (F * v))

    r = rhs - mv(x)
    z = dinv * r * F
    p = z.copy()
    rz = (r * z).sum(0)
    n0 = np.sqrt((rhs ** 2).sum(0)) + 1e-30
    for _ in range(iterations):
        if np.all(np.sqrt((r ** 2).sum(0)) < tol * n0):
            break
        q = mv(p)
        pq = (p * q).sum(0)
        alpha = np.where(pq > 0, rz / np.where(pq > 0, pq, 1), 0.0)
        x = x + alpha * p
        r = r - alpha * q
        z = dinv * r * F
        rz_new = (r * z).sum(0)
        beta = np.where(rz > 0, rz_new / np.where(rz > 0, rz, 1), 0.0)
        p = z + beta * p
        rz = rz_new
    return x + xb
