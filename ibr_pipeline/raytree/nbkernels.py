"""numba-compiled fused kernels of the ray-tree warper: the CPU backend (Lochmann et al. 2014).

Each kernel is one pass over the pixels doing what the eager torch code (decode.py, diffuse.py,
specular.py, fill.py: the reference and the CUDA path) does in tens of elementwise passes; the
mathematics is the same, per pixel, with the same rules (tested against the torch code in
tests/raytree/test_raytree_numba.py). Arithmetic is in float64 registers, buffers are float32.

Conventions as in ops.py: pixel centre of the top-left pixel at (0, 0), images (H, W, C) or
flattened (H*W, C), a location (x, y); bilinear taps in the order 00, 10, 01, 11 at flat offsets
0, dx, dy, dx + dy (dx = 1, dy = W; 0 for a 1-pixel-wide / -high image).
"""
from __future__ import annotations

import math

import os

import numba
import numpy as np
from numba import njit, prange

if "NUMBA_THREADING_LAYER" not in os.environ:
    # the installed TBB is too old for numba (it warns and falls back): try OpenMP first
    numba.config.THREADING_LAYER_PRIORITY = ["omp", "workqueue", "tbb"]


BIG = np.iinfo(np.int64).max          # empty splat slot (diffuse._BIG)
F_NONE, F_DIELECTRIC, F_PANE = 0, 1, 2  # encoding.FRESNEL_*


# ---------------------------------------------------------------- per-location helpers
@njit(cache=True)
def _cell(qx, qy, W, H):
    """ops.cell: flat top-left tap, fractions and `inside` (within half a pixel of the grid)."""
    if not (qx == qx and qy == qy):   # NaN: outside
        qx, qy = -1e4, -1e4
    xc = min(max(qx, 0.0), W - 1.0)
    yc = min(max(qy, 0.0), H - 1.0)
    x0 = min(math.floor(xc), max(W - 2, 0))
    y0 = min(math.floor(yc), max(H - 2, 0))
    inside = qx >= -0.5 and qx <= W - 0.5 and qy >= -0.5 and qy <= H - 0.5
    return y0 * W + x0, xc - x0, yc - y0, inside


@njit(cache=True)
def _nearest(i0, fx, fy, smooth, inside, valid, dx, dy):
    """ops.Sampler.taps: the heaviest tap; where the quad is not smooth the heaviest *valid* one
    (first of equal weights), -1 if none or outside."""
    if smooth:
        return i0 + (dx if fx >= 0.5 else 0) + (dy if fy >= 0.5 else 0)
    if not inside:
        return -1
    gx, gy = 1.0 - fx, 1.0 - fy
    best, bw = -1, -2.0
    for t in range(4):
        idx = i0 + (dx if t & 1 else 0) + (dy if t & 2 else 0)
        w = (fx if t & 1 else gx) * (fy if t & 2 else gy)
        if valid[idx] and w > bw:
            best, bw = idx, w
    return best


@njit(cache=True)
def _bilin(img, c, i0, fx, fy, dx, dy):
    """Bilinear value of channel c of (P, C) img in the quad at i0 (= F.grid_sample there)."""
    gx, gy = 1.0 - fx, 1.0 - fy
    return (gx * gy * img[i0, c] + fx * gy * img[i0 + dx, c] + gx * fy * img[i0 + dy, c]
            + fx * fy * img[i0 + dx + dy, c])


@njit(cache=True)
def _norm3(x, y, z):
    """ops.normalize: v / |v| with |v|^2 clamped at 1e-24 (the zero vector stays zero)."""
    s = 1.0 / math.sqrt(max(x * x + y * y + z * z, 1e-24))
    return x * s, y * s, z * s


@njit(cache=True)
def _rs_rp(cos_i, eta):
    cos_i = min(abs(cos_i), 1.0)
    sin_t2 = eta * eta * (1.0 - cos_i * cos_i)
    if sin_t2 >= 1.0:
        return 1.0, 1.0
    cos_t = math.sqrt(max(1.0 - sin_t2, 0.0))
    rs = (eta * cos_i - cos_t) / max(eta * cos_i + cos_t, 1e-12)
    rp = (eta * cos_t - cos_i) / max(eta * cos_t + cos_i, 1e-12)
    return rs * rs, rp * rp


@njit(cache=True)
def _fresnel(code, cos_i, ior):
    """warp.fresnel_weight: dielectric Fresnel, thin-pane reflectance or 1 (no Fresnel model)."""
    if ior <= 0:
        ior = 1.0
    if code == F_DIELECTRIC:
        rs, rp = _rs_rp(cos_i, 1.0 / ior)
        return 0.5 * (rs + rp)
    if code == F_PANE:
        rs, rp = _rs_rp(cos_i, 1.0 / ior)
        return 0.5 * (2 * rs / (1 + rs) + 2 * rp / (1 + rp))
    return 1.0


@njit(cache=True)
def _eta(ior, code):
    """decode.eta_of: n_air / n_material; 1 for a thin pane or where no IOR is given."""
    if code == F_PANE or ior <= 0:
        return 1.0
    return 1.0 / max(ior, 1e-6)


# ---------------------------------------------------------------- decoding (§3.3)
@njit(cache=True, parallel=True)
def unproject(depth, K, T, out):
    """§3.3 "Diffuse position": W_d = unproject(M_old, (x, y, z)) into out (H, W, 3)."""
    H, W = depth.shape
    for y in prange(H):
        cy = (y - K[1, 2]) / K[1, 1]
        for x in range(W):
            d = depth[y, x]
            c0 = (x - K[0, 2]) / K[0, 0] * d - T[0, 3]
            c1 = cy * d - T[1, 3]
            c2 = d - T[2, 3]
            for k in range(3):   # R^T (x_cam - t)
                out[y, x, k] = T[0, k] * c0 + T[1, k] * c1 + T[2, k] * c2


@njit(cache=True, parallel=True)
def unpack_valid(bits, depth):
    """Per-node validity (n, H, W) from the bit mask (§3.2); the root also needs depth > 0."""
    n, H, W = depth.shape
    out = np.empty((n, H, W), np.bool_)
    for y in prange(H):
        for x in range(W):
            b = bits[y, x]
            out[0, y, x] = (b & 1) != 0 and depth[0, y, x] > 0
            for i in range(1, n):
                out[i, y, x] = ((b >> i) & 1) != 0
    return out


@njit(cache=True, parallel=True)
def root_labels(valid, fres):
    """Node bits of every old pixel (H*W,) and the sampler label bits * 4 + Fresnel code (H, W)."""
    n, H, W = valid.shape
    bits = np.zeros(H * W, np.int32)
    label = np.empty((H, W), np.int32)
    for y in prange(H):
        for x in range(W):
            b = 0
            for i in range(n):
                if valid[i, y, x]:
                    b |= 1 << i
            bits[y * W + x] = b
            label[y, x] = b * 4 + fres[y, x]
    return bits, label


@njit(cache=True)
def normals_box(Wd, valid, eye, y0, y1, x0, x1, kern, out, rel=0.0):
    """§3.3 "Normals" on the crop (y0:y1, x0:x1) as its own image (= decode.reconstruct_normals
    of the crop, forward differences): n = (W(l+(0,1)) - W(l)) x (W(l+(1,0)) - W(l)) (backward
    difference where the forward one is unavailable), oriented towards `eye`, then the masked
    separable Gaussian `kern` (Fig. 3; replicate border, normalised over the valid normals) and
    normalised; written to out[y0:y1, x0:x1]. rel > 0 (our extension, = decode.edge_blur): the
    2-D edge-stopping blur instead (taps with |z_j - z_i| <= rel z_i, z the distance to `eye`;
    no weight outside the crop; no tap passing: the window's defined normals)."""
    h, w = y1 - y0, x1 - x0
    A = _raw_normals(Wd, valid, eye, y0, x0, h, w, rel)
    if rel > 0:   # the edge-stopping blur (our extension)
        _edge_blur(Wd, eye, y0, x0, h, w, kern, rel, A, out)
    else:
        _blur_sep(y0, x0, h, w, kern, A, out)


@njit(cache=True, parallel=True)
def _raw_normals(Wd, valid, eye, y0, x0, h, w, rel):
    A = np.zeros((h, w, 4))
    for i in prange(h):
        _raw_normals_row(Wd, valid, eye, y0 + i, x0, i == 0, i == h - 1, w, A[i], rel)
    return A


@njit(cache=True, parallel=True)
def _blur_sep(y0, x0, h, w, kern, A, out):
    """§3.3's separable masked Gaussian of the raw normals A (replicate border), normalised."""
    r = len(kern) // 2
    B = np.zeros((h, w, 4))
    for i in prange(h):   # horizontal pass, replicate border
        for j in range(w):
            for t in range(len(kern)):
                jj = min(max(j + t - r, 0), w - 1)
                for c in range(4):
                    B[i, j, c] += kern[t] * A[i, jj, c]
    for i in prange(h):   # vertical pass, normalise by the weight, then to unit length
        for j in range(w):
            s0 = s1 = s2 = s3 = 0.0
            for t in range(len(kern)):
                ii = min(max(i + t - r, 0), h - 1)
                s0 += kern[t] * B[ii, j, 0]
                s1 += kern[t] * B[ii, j, 1]
                s2 += kern[t] * B[ii, j, 2]
                s3 += kern[t] * B[ii, j, 3]
            m = max(s3, 1e-8)
            nx, ny, nz = _norm3(s0 / m, s1 / m, s2 / m)
            out[y0 + i, x0 + j, 0], out[y0 + i, x0 + j, 1], out[y0 + i, x0 + j, 2] = nx, ny, nz


@njit(cache=True, parallel=True)
def _edge_blur(Wd, eye, y0, x0, h, w, kern, rel, A, out):
    """normals_box's edge-stopping blur (rel > 0) of the raw normals A (h, w, 4) (= decode.
    edge_blur). Where every defined tap of the window passes the depth test (window min / max of
    z, separable), the value is the separable zero-padded Gaussian sum (the same sum); only
    windows straddling a depth edge run the 2-D tap loop."""
    r = len(kern) // 2
    K = len(kern)
    Z = np.empty((h, w))
    lo = np.empty((h, w))
    hi = np.empty((h, w))
    B = np.zeros((h, w, 3))
    for i in prange(h):   # distance to the camera; horizontal min / max and blur, zero outside
        for j in range(w):
            Z[i, j] = _dist(Wd, eye, y0 + i, x0 + j)
        for j in range(w):
            mn, mx = np.inf, -np.inf
            for t in range(K):
                jj = j + t - r
                if jj < 0 or jj >= w or A[i, jj, 3] == 0:
                    continue
                zj = _dist(Wd, eye, y0 + i, x0 + jj)
                mn, mx = min(mn, zj), max(mx, zj)
                for c in range(3):
                    B[i, j, c] += kern[t] * A[i, jj, c]
            lo[i, j], hi[i, j] = mn, mx
    for i in prange(h):
        for j in range(w):
            z = Z[i, j]
            s0 = s1 = s2 = 0.0
            mn, mx = np.inf, -np.inf
            for t in range(K):
                ii = i + t - r
                if ii < 0 or ii >= h:
                    continue
                s0 += kern[t] * B[ii, j, 0]
                s1 += kern[t] * B[ii, j, 1]
                s2 += kern[t] * B[ii, j, 2]
                mn, mx = min(mn, lo[ii, j]), max(mx, hi[ii, j])
            if mx - z > rel * z or z - mn > rel * z:   # a tap across a depth edge: 2-D loop
                e0 = e1 = e2 = sw = 0.0
                for a in range(K):
                    ii = i + a - r
                    if ii < 0 or ii >= h:
                        continue
                    for b in range(K):
                        jj = j + b - r
                        if jj < 0 or jj >= w or A[ii, jj, 3] == 0 or abs(Z[ii, jj] - z) > rel * z:
                            continue
                        g = kern[a] * kern[b]
                        e0 += g * A[ii, jj, 0]
                        e1 += g * A[ii, jj, 1]
                        e2 += g * A[ii, jj, 2]
                        sw += g
                if sw > 0:   # else: no tap passes, the window's defined normals (s)
                    s0, s1, s2 = e0, e1, e2
            nx, ny, nz = _norm3(s0, s1, s2)
            out[y0 + i, x0 + j, 0], out[y0 + i, x0 + j, 1], out[y0 + i, x0 + j, 2] = nx, ny, nz


@njit(cache=True)
def _dist(Wd, eye, y, x):
    a0, a1, a2 = Wd[y, x, 0] - eye[0], Wd[y, x, 1] - eye[1], Wd[y, x, 2] - eye[2]
    return math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)


@njit(cache=True)
def _raw_normals_row(Wd, valid, eye, y, x0, first_row, last_row, w, A, rel):
    """Unblurred normals of crop row y (normals_box) into A (w, 4): n, 1 where defined.
    rel > 0 (our extension, = decode.reconstruct_normals): per axis the backward difference
    replaces a forward one that crosses a depth edge (|z_next - z| > rel z) when it does not."""
    for j in range(w):
        x = x0 + j
        if not valid[y, x]:
            continue
        fy = not last_row and valid[y + 1, x]
        by = not first_row and valid[y - 1, x]
        fx = j < w - 1 and valid[y, x + 1]
        bx = j > 0 and valid[y, x - 1]
        if rel > 0:
            z = _dist(Wd, eye, y, x)
            if fy and by and abs(_dist(Wd, eye, y + 1, x) - z) > rel * z and abs(_dist(Wd, eye, y - 1, x) - z) <= rel * z:
                fy = False
            if fx and bx and abs(_dist(Wd, eye, y, x + 1) - z) > rel * z and abs(_dist(Wd, eye, y, x - 1) - z) <= rel * z:
                fx = False
        # W(l + (0, 1)) - W(l): one row down (backward difference at the crop's last row or
        # where the lower neighbour is invalid)
        if fy:
            a0, a1, a2 = Wd[y + 1, x, 0] - Wd[y, x, 0], Wd[y + 1, x, 1] - Wd[y, x, 1], Wd[y + 1, x, 2] - Wd[y, x, 2]
        elif by:
            a0, a1, a2 = Wd[y, x, 0] - Wd[y - 1, x, 0], Wd[y, x, 1] - Wd[y - 1, x, 1], Wd[y, x, 2] - Wd[y - 1, x, 2]
        else:
            continue
        # W(l + (1, 0)) - W(l): one column right
        if fx:
            b0, b1, b2 = Wd[y, x + 1, 0] - Wd[y, x, 0], Wd[y, x + 1, 1] - Wd[y, x, 1], Wd[y, x + 1, 2] - Wd[y, x, 2]
        elif bx:
            b0, b1, b2 = Wd[y, x, 0] - Wd[y, x - 1, 0], Wd[y, x, 1] - Wd[y, x - 1, 1], Wd[y, x, 2] - Wd[y, x - 1, 2]
        else:
            continue
        nx, ny, nz = float(a1 * b2 - a2 * b1), float(a2 * b0 - a0 * b2), float(a0 * b1 - a1 * b0)
        if nx * nx + ny * ny + nz * nz <= 0:
            continue
        nx, ny, nz = _norm3(nx, ny, nz)
        if (eye[0] - Wd[y, x, 0]) * nx + (eye[1] - Wd[y, x, 1]) * ny + (eye[2] - Wd[y, x, 2]) * nz < 0:
            nx, ny, nz = -nx, -ny, -nz
        A[j, 0], A[j, 1], A[j, 2], A[j, 3] = nx, ny, nz, 1.0


@njit(cache=True, parallel=True)
def decode_box(Wd, nd, center, depth, valid, kind, ior, fres, y0, y1, x0, x1, dirs, pos):
    """§3.3 in the specular box: incoming directions dirs[0] = (W_d - c_old)/|.|, and per
    first-level node i: r = reflect(d, n) (Eq. 1) or refract(d, n, eta), W_i = W_d + delta r_hat;
    valid[i] &= valid[0] & no TIR & delta > 0 (false outside the box)."""
    n_nodes = depth.shape[0]
    for y in prange(y0, y1):
        for x in range(x0, x1):
            d0, d1, d2 = _norm3(Wd[y, x, 0] - center[0], Wd[y, x, 1] - center[1], Wd[y, x, 2] - center[2])
            dirs[0, y, x, 0], dirs[0, y, x, 1], dirs[0, y, x, 2] = d0, d1, d2
            n0, n1, n2 = nd[y, x, 0], nd[y, x, 1], nd[y, x, 2]
            cos = d0 * n0 + d1 * n1 + d2 * n2
            for i in range(1, n_nodes):
                tir = False
                if kind[i] == 1:    # reflect(I, N) = I - 2 dot(N, I) N
                    r0, r1, r2 = d0 - 2 * cos * n0, d1 - 2 * cos * n1, d2 - 2 * cos * n2
                else:               # refract(I, N, eta) (GLSL)
                    eta = _eta(ior[y, x], fres[y, x])
                    k = 1.0 - eta * eta * (1.0 - cos * cos)
                    tir = k < 0
                    a = eta * cos + math.sqrt(max(k, 0.0))
                    r0, r1, r2 = eta * d0 - a * n0, eta * d1 - a * n1, eta * d2 - a * n2
                    if tir:
                        r0, r1, r2 = 0.0, 0.0, 0.0
                r0, r1, r2 = _norm3(r0, r1, r2)
                dl = depth[i, y, x]
                valid[i, y, x] = valid[i, y, x] and valid[0, y, x] and not tir and dl > 0
                dirs[i, y, x, 0], dirs[i, y, x, 1], dirs[i, y, x, 2] = r0, r1, r2
                pos[i, y, x, 0] = Wd[y, x, 0] + dl * r0
                pos[i, y, x, 1] = Wd[y, x, 1] + dl * r1
                pos[i, y, x, 2] = Wd[y, x, 2] + dl * r2


@njit(cache=True, parallel=True)
def quad_ok(valid, key, rel_tol, label, dirs, div_tol):
    """ops.Sampler's per-quad smoothness (H*W,): the 2x2 quad at (y, x) (replicate border) has 4
    valid pixels, equal labels (label.size > 0), and a key spread <= rel_tol min|key| (+ div_tol
    x the largest diagonal chord of the unit `dirs` x max|key| when div_tol > 0: the node's
    ray-spread slack of warp._node_tables)."""
    H, W = valid.shape
    out = np.zeros(H * W, np.bool_)
    use_label = label.size > 0
    for y in prange(H):
        ya, yb = y, min(y + 1, H - 1)
        for x in range(W):
            xa, xb = x, min(x + 1, W - 1)
            if not (valid[ya, xa] and valid[ya, xb] and valid[yb, xa] and valid[yb, xb]):
                continue
            if use_label:
                lb = label[ya, xa]
                if label[ya, xb] != lb or label[yb, xa] != lb or label[yb, xb] != lb:
                    continue
            a, b, c, d = key[ya, xa], key[ya, xb], key[yb, xa], key[yb, xb]
            kmin, kmax = min(min(a, b), min(c, d)), max(max(a, b), max(c, d))
            tol = np.float32(rel_tol) * np.float32(max(abs(kmin), 1e-6))
            if div_tol > 0:
                c1 = c2 = 0.0
                for k in range(3):
                    c1 += (dirs[ya, xa, k] - dirs[yb, xb, k]) ** 2
                    c2 += (dirs[ya, xb, k] - dirs[yb, xa, k]) ** 2
                tol = tol + np.float32(div_tol * math.sqrt(max(c1, c2))) * abs(kmax)
            out[y * W + x] = kmax - kmin <= tol
    return out


# ---------------------------------------------------------------- diffuse flow (§3.4, Fig. 4)
@njit(cache=True)
def project_splat(pos, valid, P, Wn, Hn):
    """Forward flow l_new = project(M_new, W_d) (uv (P, 2)) and point splatting with depth test
    (diffuse.splat_keys): per new pixel the smallest key z_q * P + old index (10 um depth
    quantum), BIG where nothing landed, and that old index (int32, -1). Serial (a scatter-min)."""
    n_old = pos.shape[0]
    uv = np.empty((n_old, 2), np.float32)
    keys = np.full(Wn * Hn, BIG, np.int64)
    idx = np.full(Wn * Hn, -1, np.int32)
    q = np.float32(1e5)
    for i in range(n_old):
        X0, X1, X2 = pos[i, 0], pos[i, 1], pos[i, 2]
        h0 = P[0, 0] * X0 + P[0, 1] * X1 + P[0, 2] * X2 + P[0, 3]
        h1 = P[1, 0] * X0 + P[1, 1] * X1 + P[1, 2] * X2 + P[1, 3]
        z = P[2, 0] * X0 + P[2, 1] * X1 + P[2, 2] * X2 + P[2, 3]
        zs = z if abs(z) > 1e-9 else 1e-9
        u, v = np.float32(h0 / zs), np.float32(h1 / zs)
        uv[i, 0], uv[i, 1] = u, v
        if not valid[i] or not z > 1e-6:
            continue
        tx, ty = np.rint(u), np.rint(v)
        if not (tx >= 0 and tx <= Wn - 1 and ty >= 0 and ty <= Hn - 1):
            continue
        zq = np.int64(np.rint(np.float32(min(np.float32(z), np.float32(1e4))) * q))
        key = zq * n_old + i
        t = int(ty) * Wn + int(tx)
        if key < keys[t]:
            keys[t] = key
            idx[t] = i
    return uv, keys, idx


@njit(cache=True, parallel=True)
def closest_3x3(keys, idx, Wn, Hn):
    """§3.4: each pixel takes the flow of the pixel closest to the camera (smallest key) in its
    3x3 neighbourhood; returns that old index (int32, -1 where none)."""
    rk = np.empty(Wn * Hn, np.int64)
    ri = np.empty(Wn * Hn, np.int32)
    for y in prange(Hn):
        for x in range(Wn):
            m, mi = BIG, -1
            for xx in range(max(x - 1, 0), min(x + 2, Wn)):
                if keys[y * Wn + xx] < m:
                    m, mi = keys[y * Wn + xx], idx[y * Wn + xx]
            rk[y * Wn + x], ri[y * Wn + x] = m, mi
    out = np.empty(Wn * Hn, np.int32)
    for y in prange(Hn):
        for x in range(Wn):
            m, mi = BIG, -1
            for yy in range(max(y - 1, 0), min(y + 2, Hn)):
                if rk[yy * Wn + x] < m:
                    m, mi = rk[yy * Wn + x], ri[yy * Wn + x]
            out[y * Wn + x] = mi
    return out


@njit(cache=True, parallel=True)
def fixed_point(uv, direct, filled, qok, valid, extra, W, H, Wn, Hn, eps, fallback, out, c0):
    """One fixed-point step (Bowles et al. 2012, §3.4, Fig. 4d) per new pixel from the 3x3-filled
    candidate, then (fallback) the directly splatted one: x1 = x0 + (l_new - uv(x0)); converged
    when the bilinear re-projection uv(x1) (nearest valid tap where the quad is not smooth, then
    2 eps) lies within eps of l_new. Converged pixels get src = x1, ok, the nearest tap, and the
    (P, C) `extra` image read at x1 into out[:, c0:c0 + C] (bilinear / nearest, ops.Sampler).
    direct / filled: per new pixel the splatted / 3x3-filled old pixel index (-1: none)."""
    N = Wn * Hn
    src = np.zeros((N, 2), np.float32)
    ok = np.zeros(N, np.bool_)
    near = np.full(N, -1, np.int32)
    for y in prange(Hn):
        _fpi_row(y, uv, direct, filled, qok, valid, extra, W, H, Wn, eps, fallback, out, c0, src, ok, near)
    return src, ok, near


@njit(cache=True)
def _fpi_row(y, uv, direct, filled, qok, valid, extra, W, H, Wn, eps, fallback, out, c0, src, ok, near):
    """fixed_point for the new pixels of row y."""
    C = extra.shape[1]
    dx, dy = (1 if W > 1 else 0), (W if H > 1 else 0)
    eps2 = eps * eps
    for x in range(Wn):
        j = y * Wn + x
        for attempt in range(2 if fallback else 1):
            idx = filled[j] if attempt == 0 else direct[j]
            if idx < 0:
                break
            sx = np.float32((idx % W) + (x - uv[idx, 0]))
            sy = np.float32((idx // W) + (y - uv[idx, 1]))
            i0, fx, fy, inside = _cell(float(sx), float(sy), W, H)
            smooth = qok[i0] and inside
            nr = _nearest(i0, fx, fy, smooth, inside, valid, dx, dy)
            if nr < 0:
                continue
            if smooth:
                vx, vy = _bilin(uv, 0, i0, fx, fy, dx, dy), _bilin(uv, 1, i0, fx, fy, dx, dy)
            else:
                vx, vy = uv[nr, 0], uv[nr, 1]
            res2 = (vx - x) ** 2 + (vy - y) ** 2
            if res2 < (eps2 if smooth else 4 * eps2) and sx > -0.5 and sx < W - 0.5 \
                    and sy > -0.5 and sy < H - 0.5:
                src[j, 0], src[j, 1] = sx, sy
                ok[j] = True
                near[j] = nr
                for c in range(C):
                    out[j, c0 + c] = _bilin(extra, c, i0, fx, fy, dx, dy) if smooth else extra[nr, c]
                break


@njit(cache=True)
def specular_pixels(ok, near, bits):
    """Flat indices of the converged new pixels whose first surface has a specular node."""
    n = 0
    for j in range(len(ok)):
        if ok[j] and (bits[near[j]] >> 1) != 0:
            n += 1
    out = np.empty(n, np.int64)
    n = 0
    for j in range(len(ok)):
        if ok[j] and (bits[near[j]] >> 1) != 0:
            out[n] = j
            n += 1
    return out


@njit(cache=True, parallel=True)
def root_attrs(pix, src, qok, valid, pos, normal, ior, fres, bits, c_new, W, H):
    """At the specular new pixels: W_d and n (bilinear at the fixed-point location, nearest valid
    tap across discontinuities; n normalised), IOR, Fresnel code and node bits (nearest tap), and
    the Fresnel weight F from the new view direction (§3.5)."""
    M = len(pix)
    dx, dy = (1 if W > 1 else 0), (W if H > 1 else 0)
    wn = np.empty((M, 6), np.float32)
    ior_s = np.empty(M, np.float32)
    code_s = np.empty(M, np.int64)
    bits_s = np.empty(M, np.int64)
    F = np.empty(M, np.float32)
    for m in prange(M):
        j = pix[m]
        i0, fx, fy, inside = _cell(float(src[j, 0]), float(src[j, 1]), W, H)
        smooth = qok[i0] and inside
        nr = max(_nearest(i0, fx, fy, smooth, inside, valid, dx, dy), 0)
        for c in range(3):
            wn[m, c] = _bilin(pos, c, i0, fx, fy, dx, dy) if smooth else pos[nr, c]
            wn[m, 3 + c] = _bilin(normal, c, i0, fx, fy, dx, dy) if smooth else normal[nr, c]
        n0, n1, n2 = _norm3(float(wn[m, 3]), float(wn[m, 4]), float(wn[m, 5]))
        wn[m, 3], wn[m, 4], wn[m, 5] = n0, n1, n2
        v0, v1, v2 = _norm3(wn[m, 0] - c_new[0], wn[m, 1] - c_new[1], wn[m, 2] - c_new[2])
        ior_s[m], code_s[m], bits_s[m] = ior[nr], fres[nr], bits[nr]
        F[m] = _fresnel(code_s[m], abs(v0 * n0 + v1 * n1 + v2 * n2), ior_s[m])
    return wn, ior_s, code_s, bits_s, F


@njit(cache=True, parallel=True)
def old_composite(rgb, valid, dirs0, normal0, kind, fres, ior):
    """warp.old_composite: the old image composited with Fresnel weights (H*W, 3)."""
    n_nodes, H, W = valid.shape
    out = np.zeros((H * W, 3), np.float32)
    for y in prange(H):
        for x in range(W):
            cos = abs(dirs0[y, x, 0] * normal0[y, x, 0] + dirs0[y, x, 1] * normal0[y, x, 1]
                      + dirs0[y, x, 2] * normal0[y, x, 2])
            code = fres[y, x]
            F = _fresnel(code, cos, ior[y, x])
            for c in range(3):
                v = rgb[0][y, x, c] if valid[0, y, x] else 0.0
                for i in range(1, n_nodes):
                    if valid[i, y, x]:
                        if kind[i] == 1:
                            wgt = 1.0 if code == F_NONE else F
                        else:
                            wgt = 0.0 if code == F_NONE else 1.0 - F
                        v += wgt * rgb[i][y, x, c]
                out[y * W + x, c] = v
    return out
