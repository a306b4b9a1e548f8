"""Jacobi-preconditioned conjugate gradients with several right-hand sides and fixed variables
(the image step of the reflection decomposition, decompose.Problem.image_step).

Two implementations of one algorithm: `block_pcg_reference` (scipy sparse
mat-vecs and numpy reductions, ~10 passes over memory per iteration) and `block_pcg` (numba
kernels: the mat-vec reads each stored entry once for the three colour channels, fused with the
dot products and the updates). Applying H = A^T A + ... through A row by row, without forming
A^T A, was measured slower (its scattered writes miss the cache): the image step forms H once.
tests/reflection/test_block_pcg.py checks that they agree; `ibr bench speed` times both.
"""
from __future__ import annotations

import numpy as np
from numba import njit


def _check(H, g: np.ndarray, x0: np.ndarray, free: np.ndarray) -> None:
    P = H.shape[0]
    if H.shape != (P, P) or g.ndim != 2 or g.shape[0] != P or x0.shape != g.shape \
            or free.shape != g.shape:
        raise ValueError(f"need H (P, P), g, x0, free (P, C); got {H.shape}, {g.shape}, "
                         f"{x0.shape}, {free.shape}")


def block_pcg_reference(H, g: np.ndarray, x0: np.ndarray, free: np.ndarray,
                        iterations: int = 150, tol: float = 1e-6,
                        info: dict | None = None) -> np.ndarray:
    """Jacobi-preconditioned CG for H x = g with several right-hand sides (columns of g), the
    variables where `free` is False held at their value in x0 (the active set of the box).
    Each column stops when its residual is below `tol` x its right-hand side's norm; `info`
    receives the iterations run ("iterations")."""
    _check(H, g, x0, free)
    F = free.astype(np.float64)
    xb = x0 * (1 - F)
    rhs = F * (g - H @ xb)
    dinv = 1.0 / np.maximum(H.diagonal().astype(np.float64), 1e-12)[:, None]
    x = x0 * F

    def mv(v):
        return F * (H @ (F * v))

    r = rhs - mv(x)
    z = dinv * r * F
    p = z.copy()
    rz = (r * z).sum(0)
    n0 = np.sqrt((rhs ** 2).sum(0)) + 1e-30
    done = 0
    for _ in range(iterations):
        if np.all(np.sqrt((r ** 2).sum(0)) < tol * n0):
            break
        done += 1
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
    if info is not None:
        info["iterations"] = done
    return x + xb


def block_pcg(H, g: np.ndarray, x0: np.ndarray, free: np.ndarray, iterations: int = 150,
              tol: float = 1e-6, info: dict | None = None) -> np.ndarray:
    """`block_pcg_reference` in numba kernels (the same iterates up to rounding). H's entries
    are read in H's precision (float32 or float64), everything else is float64."""
    import scipy.sparse as sp
    _check(H, g, x0, free)
    Hc = sp.csr_matrix(H)
    if not Hc.has_sorted_indices:
        Hc = Hc.sorted_indices()
    data = np.ascontiguousarray(Hc.data, np.float32 if Hc.dtype == np.float32 else np.float64)
    x, done = _pcg_kernel(_i32(Hc.indptr), _i32(Hc.indices), data,
                          _f64(Hc.diagonal()), _f64(g), _f64(x0),
                          np.ascontiguousarray(free, np.bool_), int(iterations), float(tol))
    if info is not None:
        info["iterations"] = int(done)
    return x


def _i32(a):
    return np.ascontiguousarray(a, np.int32)


def _f64(a):
    return np.ascontiguousarray(a, np.float64)


@njit(cache=True)
def _csr_mv(indptr, indices, data, v, out):
    """out = M @ v for a CSR matrix M and every column of v (each entry read once)."""
    n, C = out.shape
    if C == 3:  # colour images: scalar accumulators the compiler keeps in registers
        for i in range(n):
            s0 = s1 = s2 = 0.0
            for k in range(indptr[i], indptr[i + 1]):
                j = indices[k]
                a = data[k]
                s0 += a * v[j, 0]
                s1 += a * v[j, 1]
                s2 += a * v[j, 2]
            out[i, 0], out[i, 1], out[i, 2] = s0, s1, s2
        return
    acc = np.zeros(C)
    for i in range(n):
        acc[:] = 0.0
        for k in range(indptr[i], indptr[i + 1]):
            j = indices[k]
            a = data[k]
            for c in range(C):
                acc[c] += a * v[j, c]
        for c in range(C):
            out[i, c] = acc[c]


@njit(cache=True)
def _masked_mv(indptr, indices, data, F, v, out):
    """out = F * (H @ v); returns the column sums of v * out."""
    _csr_mv(indptr, indices, data, v, out)
    P, C = v.shape
    dots = np.zeros(C)
    for i in range(P):
        for c in range(C):
            q = F[i, c] * out[i, c]
            out[i, c] = q
            dots[c] += v[i, c] * q
    return dots


@njit(cache=True)
def _pcg_kernel(Hp, Hi, Hd, diag, g, x0, free, iterations, tol):
    P, C = g.shape
    F = np.empty((P, C))
    for i in range(P):
        for c in range(C):
            F[i, c] = 1.0 if free[i, c] else 0.0
    xb = x0 * (1.0 - F)
    hx = np.empty((P, C))
    _masked_mv(Hp, Hi, Hd, np.ones((P, C)), xb, hx)  # H @ xb
    dinv = np.empty(P)
    for i in range(P):
        dinv[i] = 1.0 / max(diag[i], 1e-12)
    rhs = F * (g - hx)
    x = x0 * F
    r = np.empty((P, C))
    _masked_mv(Hp, Hi, Hd, F, x, hx)
    z = np.empty((P, C))
    rz = np.zeros(C)
    n0 = np.zeros(C)
    rr = np.zeros(C)
    for i in range(P):
        for c in range(C):
            ri = rhs[i, c] - hx[i, c]
            r[i, c] = ri
            zi = dinv[i] * ri * F[i, c]
            z[i, c] = zi
            rz[c] += ri * zi
            rr[c] += ri * ri
            n0[c] += rhs[i, c] * rhs[i, c]
    for c in range(C):
        n0[c] = np.sqrt(n0[c]) + 1e-30
    p = z.copy()
    q = np.empty((P, C))
    alpha = np.zeros(C)
    beta = np.zeros(C)
    its = 0
    for _ in range(iterations):
        done = True
        for c in range(C):
            if not np.sqrt(rr[c]) < tol * n0[c]:
                done = False
        if done:
            break
        its += 1
        pq = _masked_mv(Hp, Hi, Hd, F, p, q)  # p is 0 where F is: F * p = p
        for c in range(C):
            alpha[c] = rz[c] / pq[c] if pq[c] > 0 else 0.0
        rz_new = np.zeros(C)
        rr[:] = 0.0
        for i in range(P):
            for c in range(C):
                x[i, c] += alpha[c] * p[i, c]
                ri = r[i, c] - alpha[c] * q[i, c]
                r[i, c] = ri
                zi = dinv[i] * ri * F[i, c]
                z[i, c] = zi
                rz_new[c] += ri * zi
                rr[c] += ri * ri
        for c in range(C):
            beta[c] = rz_new[c] / rz[c] if rz[c] > 0 else 0.0
            rz[c] = rz_new[c]
        for i in range(P):
            for c in range(C):
                p[i, c] = z[i, c] + beta[c] * p[i, c]
    return x + xb, its
