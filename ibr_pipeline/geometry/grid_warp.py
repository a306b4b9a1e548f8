"""2D non-rigid grid warp F_k' (Xu et al. §4.3.1, Eqs. 4-5), solved by Gauss-Newton.

F(u) = u + sum_l theta_l(u) f_l (Eq. 4): offsets f_l on the (gx+1) x (gy+1) control vertices of a
grid that uniformly covers the neighbour image (paper: 40 x 30 cells, 41 x 31 vertices), bilinear
weights theta. The offsets minimise (Eq. 5)

    sum_u || I_k'(F(w(u))) - I_k(u) ||^2 + w_r sum_l ||f_l||^2
        + w_a sum_t || v1 - (v2 + alpha [[0, 1], [-1, 0]] (v3 - v2)) ||^2

with w_r = 1.2, w_a = 0.5, the ARAP term over the two triangles of every cell (Igarashi et al.
2005; alpha = the cell aspect ratio). The rest grid satisfies the ARAP term exactly, so it is a
linear function of the offsets. Intensities are linear values in [0, 1].
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np
from numba import njit


def grid_vertices(width: int, height: int, gx: int = 40, gy: int = 30) -> tuple[np.ndarray, float, float]:
    """Rest positions (gy+1, gx+1, 2) of the control vertices covering pixel centres 0..W-1,
    0..H-1; and the cell size (sx, sy)."""
    sx, sy = (width - 1) / gx, (height - 1) / gy
    xs, ys = np.meshgrid(np.arange(gx + 1) * sx, np.arange(gy + 1) * sy)
    return np.stack([xs, ys], -1), sx, sy


def bilinear_weights(p: np.ndarray, width: int, height: int, gx: int, gy: int):
    """Eq. 4's theta: for (N, 2) positions, the 4 control-vertex indices (N, 4) (flat, row-major
    over (gy+1, gx+1)) and weights (N, 4) of the cell containing each position (clamped)."""
    p = np.asarray(p, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2:
        raise ValueError(f"positions must be (N, 2), got {p.shape}")
    sx, sy = (width - 1) / gx, (height - 1) / gy
    fx = np.clip(p[:, 0] / sx, 0, gx - 1e-9)
    fy = np.clip(p[:, 1] / sy, 0, gy - 1e-9)
    i, j = np.floor(fx).astype(np.int64), np.floor(fy).astype(np.int64)
    ax, ay = fx - i, fy - j
    n = gx + 1
    idx = np.stack([j * n + i, j * n + i + 1, (j + 1) * n + i, (j + 1) * n + i + 1], 1)
    w = np.stack([(1 - ax) * (1 - ay), ax * (1 - ay), (1 - ax) * ay, ax * ay], 1)
    return idx, w


def apply_warp(p: np.ndarray, offsets: np.ndarray, width: int, height: int) -> np.ndarray:
    """F(p) of Eq. 4 for (..., 2) positions with offsets (gy+1, gx+1, 2)."""
    offsets = np.asarray(offsets, dtype=np.float64)
    if offsets.ndim != 3 or offsets.shape[2] != 2:
        raise ValueError(f"offsets must be (gy+1, gx+1, 2), got {offsets.shape}")
    gy, gx = offsets.shape[0] - 1, offsets.shape[1] - 1
    shape = np.shape(p)
    flat = np.asarray(p, dtype=np.float64).reshape(-1, 2)
    idx, w = bilinear_weights(flat, width, height, gx, gy)
    f = offsets.reshape(-1, 2)
    return (flat + np.einsum("nk,nkc->nc", w, f[idx])).reshape(shape)


def arap_matrix(gx: int, gy: int, sx: float, sy: float):
    """Sparse (4 gx gy, 2 L) matrix A with A f = the ARAP residuals of Eq. 5 (two triangles per
    cell; the rest grid has zero residual). Unknown order: (x0, y0, x1, y1, ...) per vertex.
    Built once per grid shape and aspect ratio (`_arap_terms`): every grid warp of a
    decomposition has the same grid, so the matrix is shared, not rebuilt; callers must not
    modify it."""
    return _arap_terms(int(gx), int(gy), float(sx / sy))[0]


def arap_normal(gx: int, gy: int, sx: float, sy: float):
    """A^T A (csr, 2L x 2L) of `arap_matrix`, shared the same way."""
    return _arap_terms(int(gx), int(gy), float(sx / sy))[1]


@lru_cache(maxsize=8)
def _arap_terms(gx: int, gy: int, alpha: float):
    import scipy.sparse as sp

    n = gx + 1
    j, i = np.meshgrid(np.arange(gy), np.arange(gx), indexing="ij")
    v00, v10 = (j * n + i).ravel(), (j * n + i + 1).ravel()
    v01, v11 = ((j + 1) * n + i).ravel(), ((j + 1) * n + i + 1).ravel()
    # per cell two triangles (v1, v2, v3): (v10, v00, v01) and (v01, v11, v10), as the reference
    tri = np.stack([np.stack([v10, v00, v01], 1), np.stack([v01, v11, v10], 1)], 1)  # (cells, 2, 3)
    Rm = np.array([[0.0, 1.0], [-1.0, 0.0]])
    eye = np.eye(2)
    coef = np.stack([eye, alpha * Rm - eye, -alpha * Rm])  # (3 vertices, c, d)
    cells = len(v00)
    # entry (cell, triangle, vertex, c, d): row 4 cell + 2 triangle + c, column 2 vertex + d
    rows = (4 * np.arange(cells)).reshape(-1, 1, 1, 1, 1) + 2 * np.arange(2).reshape(1, 2, 1, 1, 1) \
        + np.arange(2).reshape(1, 1, 1, 2, 1)
    cols = 2 * tri[:, :, :, None, None] + np.arange(2).reshape(1, 1, 1, 1, 2)
    rows, cols, vals = np.broadcast_arrays(rows, cols, coef[None, None])
    keep = vals != 0.0
    A = sp.csr_matrix((vals[keep], (rows[keep], cols[keep])), shape=(4 * cells, 2 * n * (gy + 1)))
    return A, (A.T @ A).tocsr()


def arap_matrix_reference(gx: int, gy: int, sx: float, sy: float):
    """`arap_matrix` built entry by entry, in loops over the cells: the reference."""
    import scipy.sparse as sp

    alpha = sx / sy  # Eq. 5: grid aspect ratio
    n = gx + 1
    rows, cols, vals = [], [], []
    r = 0
    Rm = np.array([[0.0, 1.0], [-1.0, 0.0]])
    for j in range(gy):
        for i in range(gx):
            v00, v10, v01, v11 = j * n + i, j * n + i + 1, (j + 1) * n + i, (j + 1) * n + i + 1
            # t1: v1 = v10, v2 = v00, v3 = v01 (right angle at v00); t2: v01, v11, v10
            for v1, v2, v3 in ((v10, v00, v01), (v01, v11, v10)):
                # residual = f1 - f2 - alpha R (f3 - f2) = f1 + (alpha R - I) f2 - alpha R f3
                for c in range(2):
                    for d in range(2):
                        coef1 = 1.0 if c == d else 0.0
                        coef2 = alpha * Rm[c, d] - coef1
                        coef3 = -alpha * Rm[c, d]
                        for v, coef in ((v1, coef1), (v2, coef2), (v3, coef3)):
                            if coef != 0.0:
                                rows.append(r + c)
                                cols.append(2 * v + d)
                                vals.append(coef)
                r += 2
    L = (gx + 1) * (gy + 1)
    return sp.csr_matrix((vals, (rows, cols)), shape=(r, 2 * L))


def _sample(img: np.ndarray, p: np.ndarray) -> np.ndarray:
    import cv2

    n = len(p)
    cols = 1024  # remap maps must stay below SHRT_MAX rows: lay the points out as a 2D map
    m = np.zeros((-(-n // cols) * cols, 2), np.float32)
    m[:n] = p
    m = m.reshape(-1, cols, 2)
    out = cv2.remap(img.astype(np.float32), m[..., 0], m[..., 1], cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(-1, img.shape[2] if img.ndim == 3 else 1)[:n]


def gauss_newton_terms_reference(w: np.ndarray, idx: np.ndarray, gxs: np.ndarray,
                                 gys: np.ndarray, res: np.ndarray, L: int):
    """J^T J (sparse, 2L x 2L) and J^T res (2L,) of Eq. 5's data term, with the Jacobian J formed
    (rows: pixel x channel; d res / d f_l = grad I_k'(q) theta_l): the reference."""
    import scipy.sparse as sp
    N, C = res.shape
    rows = np.repeat(np.arange(N * C), 8)
    colx = (2 * idx)[:, None, :].repeat(C, 1)  # (N, C, 4)
    cols = np.stack([colx, colx + 1], -1).reshape(-1)  # (N, C, 4, 2)
    vals = (w[:, None, :, None] * np.stack([gxs, gys], -1)[:, :, None, :]).reshape(-1)
    J = sp.csr_matrix((vals, (rows, cols)), shape=(N * C, 2 * L))
    return (J.T @ J).tocsr(), J.T @ res.reshape(-1)


@lru_cache(maxsize=8)
def _cell_pattern(gx: int, gy: int):
    """The sparsity of Eq. 5's Gauss-Newton matrix: every unknown coupled to those of the cells
    it is a corner of (J^T J, A^T A and the identity all lie in it). Returns its CSC structure
    (indptr, indices; rows sorted), the sorted keys column * 2L + row of its entries, each
    cell's first vertex (cells,) and the data position of each entry of each cell's 8 x 8 block
    (cells, 64), unknowns ordered as in `_gn_cells`."""
    n, N = gx + 1, 2 * (gx + 1) * (gy + 1)
    j, i = np.meshgrid(np.arange(gy), np.arange(gx), indexing="ij")
    first = (j * n + i).ravel()
    vid = np.stack([first, first + 1, first + n, first + n + 1], 1)  # bilinear_weights' order
    r = (2 * vid[:, :, None] + np.arange(2)).reshape(-1, 8)
    rows, cols = np.broadcast_arrays(r[:, :, None], r[:, None, :])
    entry = (cols * N + rows).reshape(len(first), 64)
    keys = np.unique(entry)
    indptr = np.searchsorted(keys // N, np.arange(N + 1)).astype(np.int32)
    return indptr, (keys % N).astype(np.int32), keys, first, np.searchsorted(keys, entry)


def _pattern_data(M, keys: np.ndarray, N: int) -> np.ndarray:
    """The entries of sparse M (N, N) as data over `_cell_pattern`'s structure (M within it)."""
    M = M.tocoo()
    k = M.col.astype(np.int64) * N + M.row
    pos = np.searchsorted(keys, k)
    if np.any(pos >= len(keys)) or np.any(keys[np.minimum(pos, len(keys) - 1)] != k):
        raise ValueError("matrix has entries outside the grid cells' pattern")
    return np.bincount(pos, weights=M.data, minlength=len(keys))


@lru_cache(maxsize=8)
def _regulariser_data(gx: int, gy: int, alpha: float, w_r: float, w_a: float) -> np.ndarray:
    """w_r I + w_a A^T A (Eq. 5's regulariser and ARAP term) as data over `_cell_pattern`."""
    import scipy.sparse as sp
    N = 2 * (gx + 1) * (gy + 1)
    M = w_r * sp.identity(N, format="csr") + w_a * _arap_terms(gx, gy, alpha)[1]
    return _pattern_data(M, _cell_pattern(gx, gy)[2], N)


def gauss_newton_system(w: np.ndarray, idx: np.ndarray, gxs: np.ndarray, gys: np.ndarray,
                        res: np.ndarray, gx: int, gy: int, sx: float, sy: float, w_r: float,
                        w_a: float):
    """Eq. 5's Gauss-Newton matrix J^T J + w_r I + w_a A^T A (CSC, 2L x 2L) and J^T res (2L,),
    without forming J: a pixel's rows are theta (x) g_c over the channels c, so its share of
    J^T J is (theta theta^T) (x) (sum_c g_c g_c^T), a 4 x 4 by 2 x 2 Kronecker product; a numba
    kernel sums those 8 x 8 blocks per grid cell (and J^T res), and they are added straight into
    the grid's fixed pattern (`_cell_pattern`): assembling the matrix by sparse additions and
    format conversions was ~5 % of a 120-view reflection stage. idx, w: `bilinear_weights` of
    the N positions; gxs, gys, res: (N, C)."""
    import scipy.sparse as sp
    N, C = res.shape
    L = (gx + 1) * (gy + 1)
    if idx.shape != (N, 4) or w.shape != (N, 4) or gxs.shape != (N, C) or gys.shape != (N, C):
        raise ValueError(f"need idx, w (N, 4), gxs, gys, res (N, C); got {idx.shape}, "
                         f"{w.shape}, {gxs.shape}, {gys.shape}, {res.shape}")
    blocks, Jtr = _gn_cells(np.ascontiguousarray(w, np.float64),
                            np.ascontiguousarray(idx, np.int64),
                            np.ascontiguousarray(gxs, np.float64),
                            np.ascontiguousarray(gys, np.float64),
                            np.ascontiguousarray(res, np.float64), L)
    indptr, indices, keys, first, pos = _cell_pattern(int(gx), int(gy))
    data = _regulariser_data(int(gx), int(gy), float(sx / sy), float(w_r), float(w_a)) \
        + np.bincount(pos.ravel(), weights=blocks[first].reshape(-1), minlength=len(keys))
    return sp.csc_matrix((data, indices, indptr), shape=(2 * L, 2 * L)), Jtr


@njit(cache=True)
def _gn_cells(w, idx, gxs, gys, res, L):
    """Per grid cell (keyed by its first vertex): the 8 x 8 block of J^T J, in the unknown order
    (vertex k of the cell, axis a) -> 2k + a (zero for cells without pixels); and J^T res (2L,)."""
    N, C = res.shape
    blocks = np.zeros((L, 8, 8))
    Jtr = np.zeros(2 * L)
    for n in range(N):
        g00 = g01 = g11 = b0 = b1 = 0.0
        for c in range(C):
            gx, gy, rr = gxs[n, c], gys[n, c], res[n, c]
            g00 += gx * gx
            g01 += gx * gy
            g11 += gy * gy
            b0 += gx * rr
            b1 += gy * rr
        cell = idx[n, 0]
        for k in range(4):
            wk = w[n, k]
            Jtr[2 * idx[n, k]] += wk * b0
            Jtr[2 * idx[n, k] + 1] += wk * b1
            for m in range(4):
                ww = wk * w[n, m]
                blocks[cell, 2 * k, 2 * m] += ww * g00
                blocks[cell, 2 * k, 2 * m + 1] += ww * g01
                blocks[cell, 2 * k + 1, 2 * m] += ww * g01
                blocks[cell, 2 * k + 1, 2 * m + 1] += ww * g11
    return blocks, Jtr


def solve_grid_warp(ref: np.ndarray, nb: np.ndarray, flow: np.ndarray, valid: np.ndarray, *,
                    gx: int = 40, gy: int = 30, w_r: float = 1.2, w_a: float = 0.5,
                    iterations: int = 5, reference: bool = False) -> tuple[np.ndarray, list[float]]:
    """Gauss-Newton solution of Eq. 5.

    ref: I_k (H, W, C); nb: I_k' (H', W', C); flow: w_k'(u, M0) (H, W, 2) positions in the
    neighbour image; valid: (H, W) pixels that take part. Returns the offsets (gy+1, gx+1, 2) and
    the energy before each iteration and after the last (len iterations + 1). `reference`:
    the normal equations from the formed Jacobian (gauss_newton_terms_reference), the ARAP
    matrix from its loops and SuperLU's default ordering.
    """
    import scipy.sparse as sp
    from scipy.sparse.linalg import spsolve

    ref = np.asarray(ref, np.float64)
    nb = np.asarray(nb, np.float64)
    if ref.ndim == 2:
        ref = ref[..., None]
    if nb.ndim == 2:
        nb = nb[..., None]
    H, W = ref.shape[:2]
    if flow.shape != (H, W, 2) or np.asarray(valid).shape != (H, W) or nb.shape[2] != ref.shape[2]:
        raise ValueError(f"ref (H, W, C) {ref.shape}, nb {nb.shape}, flow {flow.shape} and "
                         f"valid {np.asarray(valid).shape} do not match")
    Hn, Wn, C = nb.shape
    L = (gx + 1) * (gy + 1)
    f = np.zeros((L, 2))
    _, sx, sy = grid_vertices(Wn, Hn, gx, gy)
    if reference:
        A = arap_matrix_reference(gx, gy, sx, sy)
        AtA = (A.T @ A).tocsr()
    else:
        AtA = arap_normal(gx, gy, sx, sy)
    sel = np.asarray(valid, bool) & np.all(np.isfinite(flow), axis=2)
    p = flow[sel]
    target = ref[sel]
    N = len(p)
    energies: list[float] = []
    if N == 0:
        return f.reshape(gy + 1, gx + 1, 2), [0.0]
    import cv2
    gxi = np.stack([cv2.Sobel(nb[..., c].astype(np.float32), cv2.CV_32F, 1, 0, ksize=3) / 8
                    for c in range(C)], -1)
    gyi = np.stack([cv2.Sobel(nb[..., c].astype(np.float32), cv2.CV_32F, 0, 1, ksize=3) / 8
                    for c in range(C)], -1)
    idx, w = bilinear_weights(p, Wn, Hn, gx, gy)

    def energy(fv, res):
        return float((res ** 2).sum() + w_r * (fv ** 2).sum() + w_a * fv.reshape(-1) @ (AtA @ fv.reshape(-1)))

    for it in range(iterations + 1):
        q = p + np.einsum("nk,nkc->nc", w, f[idx])
        res = _sample(nb, q) - target  # (N, C)
        energies.append(energy(f, res))
        if it == iterations:
            break
        gxs, gys = _sample(gxi, q), _sample(gyi, q)  # (N, C)
        fv = f.reshape(-1)
        if reference:
            JtJ, Jtr = gauss_newton_terms_reference(w, idx, gxs, gys, res, L)
            step = spsolve((JtJ + w_r * sp.identity(2 * L) + w_a * AtA).tocsc(),
                           -(Jtr + w_r * fv + w_a * (AtA @ fv)))
        else:
            lhs, Jtr = gauss_newton_system(w, idx, gxs, gys, res, gx, gy, sx, sy, w_r, w_a)
            # lhs is symmetric positive definite: a minimum-degree ordering of A^T + A gives
            # SuperLU less fill than its default column ordering (the same step up to rounding)
            step = spsolve(lhs, -(Jtr + w_r * fv + w_a * (AtA @ fv)), permc_spec="MMD_AT_PLUS_A")
        f = (fv + step).reshape(L, 2)
    return f.reshape(gy + 1, gx + 1, 2), energies
