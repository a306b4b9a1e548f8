"""numba kernels of the ray-tree warper, part 2: the per-pixel specular search (§3.4, Figs. 5, 6,
8), node sampling, push-pull hole filling (§3.5) and compositing. The torch code (specular.py,
fill.py, warp.py) is the reference; these kernels follow it rule by rule (see nbkernels.py)."""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from .nbkernels import _bilin, _cell, _nearest, _norm3

PI = math.pi


@njit(cache=True)
def _energy(qx, qy, wx, wy, wz, ox, oy, oz, Ws, delta, valid, qok, W, H, dx, dy):
    """specular._Energy at one location: Delta(omega, W_s(q) - w) = angle (§3.4), its image-space
    gradient (bilinear finite differences of W_s in the quad: dp/dx = b + fy d, dp/dy = c + fx d,
    chained through dDelta/dp), smooth, the bilinear node depth delta(q) and `defined`.
    Not smooth: the nearest valid tap, zero gradient; no valid tap / outside: Delta = pi."""
    i0, fx, fy, inside = _cell(qx, qy, W, H)
    smooth = qok[i0] and inside
    if smooth:
        i1, i2, i3 = i0 + dx, i0 + dy, i0 + dx + dy
        a0, a1, a2 = Ws[i0, 0], Ws[i0, 1], Ws[i0, 2]
        b0, b1, b2 = Ws[i1, 0] - a0, Ws[i1, 1] - a1, Ws[i1, 2] - a2
        c0, c1, c2 = Ws[i2, 0] - a0, Ws[i2, 1] - a1, Ws[i2, 2] - a2
        d0 = Ws[i3, 0] - Ws[i1, 0] - Ws[i2, 0] + a0
        d1 = Ws[i3, 1] - Ws[i1, 1] - Ws[i2, 1] + a1
        d2 = Ws[i3, 2] - Ws[i1, 2] - Ws[i2, 2] + a2
        e0 = delta[i0]
        dl = e0 + (delta[i1] - e0) * fx + ((delta[i2] - e0) + (delta[i3] - delta[i1] - delta[i2] + e0) * fx) * fy
        defined = True
    else:
        nr = _nearest(i0, fx, fy, False, inside, valid, dx, dy)
        defined = nr >= 0
        j = max(nr, 0)
        a0, a1, a2 = Ws[j, 0], Ws[j, 1], Ws[j, 2]
        b0 = b1 = b2 = c0 = c1 = c2 = d0 = d1 = d2 = 0.0
        dl = delta[j]
    y0, y1, y2 = c0 + d0 * fx, c1 + d1 * fx, c2 + d2 * fx     # dp/dy
    x0, x1, x2 = b0 + d0 * fy, b1 + d1 * fy, b2 + d2 * fy     # dp/dx
    v0 = a0 + b0 * fx + y0 * fy - wx                         # v = W_s(q) - w
    v1 = a1 + b1 * fx + y1 * fy - wy
    v2 = a2 + b2 * fx + y2 * fy - wz
    vv = max(v0 * v0 + v1 * v1 + v2 * v2, 1e-18)
    dot = ox * v0 + oy * v1 + oz * v2
    k = dot / vv
    p0, p1, p2 = ox - k * v0, oy - k * v1, oz - k * v2       # omega minus its part along v
    pv = math.sqrt((p0 * p0 + p1 * p1 + p2 * p2) * vv)        # |omega x v|
    E = math.atan2(pv, dot)
    sc = -1.0 / max(pv, 1e-24)
    gx = (p0 * x0 + p1 * x1 + p2 * x2) * sc
    gy = (p0 * y0 + p1 * y1 + p2 * y2) * sc
    if not defined:
        E = PI
    return E, gx, gy, smooth, dl, defined


@njit(cache=True)
def _search_pixel(m, w, n, eta, refl, qd, Ws, delta, valid, qok, rgb, W, H, dx, dy, P, c_new, med,
                  has_med, steps, eps_rad, step_scale, max_step, min_step, snap_r, record,
                  q, En, dfn, val, hist, qs, lam_o):
    """The search of pixel m (specular_search); a separate function keeps the parallel loop
    small (numba compiles it ~10x faster)."""
    conv = 1e-5
    wx, wy, wz = float(w[m, 0]), float(w[m, 1]), float(w[m, 2])
    n0, n1, n2 = float(n[m, 0]), float(n[m, 1]), float(n[m, 2])
    d0, d1, d2 = _norm3(wx - c_new[0], wy - c_new[1], wz - c_new[2])
    cos = d0 * n0 + d1 * n1 + d2 * n2
    ok = True
    if refl:
        o0, o1, o2 = d0 - 2 * cos * n0, d1 - 2 * cos * n1, d2 - 2 * cos * n2
    else:
        e = float(eta[m])
        kk = 1.0 - e * e * (1.0 - cos * cos)
        ok = kk >= 0
        a = e * cos + math.sqrt(max(kk, 0.0))
        o0, o1, o2 = e * d0 - a * n0, e * d1 - a * n1, e * d2 - a * n2
        if not ok:
            o0, o1, o2 = 0.0, 0.0, 0.0
    o0, o1, o2 = _norm3(o0, o1, o2)
    # initial guesses (§3.4, Fig. 6)
    qdx, qdy = float(qd[m, 0]), float(qd[m, 1])
    Ed, gdx, gdy, _, dl, ddef = _energy(qdx, qdy, wx, wy, wz, o0, o1, o2, Ws, delta, valid, qok, W, H, dx, dy)
    if has_med and not (ddef and dl > 0):
        dl = med
    V0, V1, V2 = wx + dl * d0, wy + dl * d1, wz + dl * d2
    h0 = P[0, 0] * V0 + P[0, 1] * V1 + P[0, 2] * V2 + P[0, 3]
    h1 = P[1, 0] * V0 + P[1, 1] * V1 + P[1, 2] * V2 + P[1, 3]
    z = P[2, 0] * V0 + P[2, 1] * V1 + P[2, 2] * V2 + P[2, 3]
    zs = z if abs(z) > 1e-9 else 1e-9
    qsx, qsy = float(np.float32(h0 / zs)), float(np.float32(h1 / zs))
    qsx = -1e4 if qsx != qsx else min(max(qsx, -1e4), 1e4)
    qsy = -1e4 if qsy != qsy else min(max(qsy, -1e4), 1e4)
    Es, gsx, gsy, _, _, _ = _energy(qsx, qsy, wx, wy, wz, o0, o1, o2, Ws, delta, valid, qok, W, H, dx, dy)
    den = Ed + Es
    lam = 1.0 - Ed / max(den, 1e-12) if den > 0 else 0.5
    if lam < 0.5:   # torch.lerp(q_s, q_d, lambda)
        qx, qy = qsx + lam * (qdx - qsx), qsy + lam * (qdy - qsy)
    else:
        qx, qy = qdx - (qdx - qsx) * (1 - lam), qdy - (qdy - qsy) * (1 - lam)
    E, gx, gy, _, _, _ = _energy(qx, qy, wx, wy, wz, o0, o1, o2, Ws, delta, valid, qok, W, H, dx, dy)
    if Ed < E:
        qx, qy, gx, gy, E = qdx, qdy, gdx, gdy, Ed
    if Es < E:
        qx, qy, gx, gy, E = qsx, qsy, gsx, gsy, Es
    hist[0, m] = E
    active = E > conv and gx * gx + gy * gy > 0
    s = step_scale
    for it in range(steps):
        if active:
            gn2 = gx * gx + gy * gy
            k = s * E / max(gn2, 1e-20)                 # Polyak step length factor
            L = k * math.sqrt(gn2)
            k = k * min(max_step / max(L, 1e-12), 1.0)
            cx, cy = qx - k * gx, qy - k * gy
            E1, g1x, g1y, s1, _, _ = _energy(cx, cy, wx, wy, wz, o0, o1, o2, Ws, delta, valid, qok, W, H, dx, dy)
            # reject steps onto undefined pixels / depth discontinuities or uphill; shrink
            acc = s1 and E1 < E
            if acc:
                qx, qy, gx, gy, E = cx, cy, g1x, g1y, E1
            else:
                s = s * 0.5
            active = E > conv and L > min_step and (not acc or g1x * g1x + g1y * g1y > 0)
        if record:
            hist[it + 1, m] = E
    if snap_r > 0 and E > eps_rad:
        # discrete check (our addition): the valid old pixels of the window around round(q)
        rx, ry = int(np.rint(qx)), int(np.rint(qy))
        bE, bx, by = 10.0, 0, 0
        for ddy in range(-snap_r, snap_r + 1):
            ys = min(max(ry + ddy, 0), H - 1)
            for ddx in range(-snap_r, snap_r + 1):
                xs = min(max(rx + ddx, 0), W - 1)
                i = ys * W + xs
                Ec = PI
                if valid[i]:
                    v0, v1, v2 = Ws[i, 0] - wx, Ws[i, 1] - wy, Ws[i, 2] - wz
                    cr0, cr1, cr2 = o1 * v2 - o2 * v1, o2 * v0 - o0 * v2, o0 * v1 - o1 * v0
                    Ec = math.atan2(math.sqrt(cr0 * cr0 + cr1 * cr1 + cr2 * cr2), o0 * v0 + o1 * v1 + o2 * v2)
                if Ec < bE:
                    bE, bx, by = Ec, xs, ys
        if bE < E:
            qx, qy, E = float(bx), float(by), bE
    if not ok:
        E = PI
    if not record:
        hist[0, m] = E
    q[m, 0], q[m, 1], En[m] = qx, qy, E
    qs[m, 0], qs[m, 1], lam_o[m] = qsx, qsy, lam
    if E <= eps_rad:   # the node radiance at the result (ops.Sampler of the node)
        i0, fx, fy, inside = _cell(qx, qy, W, H)
        smooth = qok[i0] and inside
        nr = _nearest(i0, fx, fy, smooth, inside, valid, dx, dy)
        if nr >= 0:
            dfn[m] = True
            for c in range(3):
                val[m, c] = _bilin(rgb, c, i0, fx, fy, dx, dy) if smooth else rgb[nr, c]


@njit(cache=True, parallel=True)
def specular_search(w, n, eta, refl, qd, Ws, delta, valid, qok, rgb, W, H, P, c_new, med, has_med,
                    steps, eps_rad, step_scale, max_step, min_step, snap_r, record):
    """§3.4 "Specular flow" for M new pixels (one thread per pixel; = specular.specular_flow):
    omega = reflect / refract(w - c_new, n, eta); initial guess (Fig. 6) from the diffuse-flow
    location q_d and the specular guess q_s (the point at the node depth along the new view ray,
    projected with the old P), q0 = lambda q_d + (1 - lambda) q_s, lambda = 1 - D_d / (D_d + D_s),
    started from the best of {q0, q_d, q_s}; `steps` Polyak steps q <- q - s Delta g/|g|^2 (capped
    at max_step px), rejecting steps onto non-smooth locations (undefined pixels / depth
    discontinuities) or uphill and halving s; a pixel stops once Delta < 1e-5, its gradient is 0
    or its step < min_step; then the (2 snap_r + 1)^2 window check; undefined if Delta > eps.
    The node radiance `rgb` is read at the result (bilinear / nearest valid tap).
    Returns q (M, 2), Delta (M,), defined (M,), value (M, 3), history (steps + 1, M) (record)
    or (1, M), q_s (M, 2), lambda (M,)."""
    M = len(w)
    dx, dy = (1 if W > 1 else 0), (W if H > 1 else 0)
    q = np.empty((M, 2), np.float32)
    qs = np.empty((M, 2), np.float32)
    lam_o = np.empty(M, np.float32)
    En = np.empty(M, np.float32)
    dfn = np.zeros(M, np.bool_)
    val = np.zeros((M, 3), np.float32)
    hist = np.empty((steps + 1 if record else 1, M), np.float32)
    for m in prange(M):
        _search_pixel(m, w, n, eta, refl, qd, Ws, delta, valid, qok, rgb, W, H, dx, dy, P, c_new, med,
                      has_med, steps, eps_rad, step_scale, max_step, min_step, snap_r, record,
                      q, En, dfn, val, hist, qs, lam_o)
    return q, En, dfn, val, hist, qs, lam_o


@njit(cache=True, parallel=True)
def sample_points(q, qok, valid, img, W, H):
    """ops.Sampler.sample at locations q (M, 2): bilinear where smooth, else the nearest valid
    tap; returns values (M, C) and defined (M,)."""
    M, C = len(q), img.shape[1]
    dx, dy = (1 if W > 1 else 0), (W if H > 1 else 0)
    out = np.zeros((M, C), np.float32)
    ok = np.zeros(M, np.bool_)
    for m in prange(M):
        i0, fx, fy, inside = _cell(float(q[m, 0]), float(q[m, 1]), W, H)
        smooth = qok[i0] and inside
        nr = _nearest(i0, fx, fy, smooth, inside, valid, dx, dy)
        ok[m] = nr >= 0
        for c in range(C):
            out[m, c] = _bilin(img, c, i0, fx, fy, dx, dy) if smooth else img[max(nr, 0), c]
    return out, ok


# ---------------------------------------------------------------- push-pull (§3.5)
@njit(cache=True, parallel=True)
def pull(c, w):
    """One pull level (Gortler et al. 1996): each coarser pixel = mean of its valid 2x2 children
    (odd borders: the existing ones), weight = any valid child."""
    h, wd, C = c.shape
    h2, w2 = (h + 1) // 2, (wd + 1) // 2
    co = np.zeros((h2, w2, C), np.float32)
    wo = np.zeros((h2, w2), np.float32)
    for y in prange(h2):
        acc = np.zeros(C)
        for x in range(w2):
            ws = 0.0
            acc[:] = 0.0
            for yy in range(2 * y, min(2 * y + 2, h)):
                for xx in range(2 * x, min(2 * x + 2, wd)):
                    if w[yy, xx] > 0:
                        ws += w[yy, xx]
                        for k in range(C):
                            acc[k] += c[yy, xx, k] * w[yy, xx]
            if ws > 0:
                wo[y, x] = 1.0
                for k in range(C):
                    co[y, x, k] = acc[k] / ws
    return co, wo


@njit(cache=True)
def _src(d, n_in, n_out):
    """Bilinear source index (F.interpolate, align_corners=False): (lo, hi, frac)."""
    s = max((d + 0.5) * (n_in / n_out) - 0.5, 0.0)
    lo = min(int(math.floor(s)), n_in - 1)
    return lo, min(lo + 1, n_in - 1), s - lo


@njit(cache=True, parallel=True)
def push(filled, c, w, holes_only, valid):
    """One push level: pixels with weight keep their value; the others take the bilinear
    upsample of the coarser `filled`. holes_only: `c` is the full-resolution image, only the
    invalid pixels (valid == False) are written (the finest level, in place)."""
    h, wd, C = c.shape
    hi, wi = filled.shape[0], filled.shape[1]
    out = c if holes_only else np.empty_like(c)
    for y in prange(h):
        y0, y1, ly = _src(y, hi, h)
        for x in range(wd):
            keep = valid[y, x] if holes_only else w[y, x] > 0
            if keep:
                if not holes_only:
                    for k in range(C):
                        out[y, x, k] = c[y, x, k]
                continue
            x0, x1, lx = _src(x, wi, wd)
            for k in range(C):
                out[y, x, k] = (1 - ly) * ((1 - lx) * filled[y0, x0, k] + lx * filled[y0, x1, k]) + \
                    ly * ((1 - lx) * filled[y1, x0, k] + lx * filled[y1, x1, k])
    return out


@njit(cache=True)
def positive(buf, ch, W):
    """Mask buf[:, ch] > 0 (N,) and its bounding box (y0, y1, x0, x1) in a W-wide image
    (empty: y1 <= y0)."""
    N = buf.shape[0]
    use = np.zeros(N, np.bool_)
    y0, y1, x0, x1 = N, 0, W, 0
    for j in range(N):
        if buf[j, ch] > 0:
            use[j] = True
            y, x = j // W, j % W
            y0, y1, x0, x1 = min(y0, y), max(y1, y + 1), min(x0, x), max(x1, x + 1)
    return use, (y0, y1, x0, x1)


@njit(cache=True, parallel=True)
def add_weighted(img, buf, ch, node, use):
    """Compositing (§3.5): img += buf[:, ch] * node where `use` (N, 3)."""
    for j in prange(len(use)):
        if use[j]:
            for c in range(3):
                img[j, c] += buf[j, ch] * node[j, c]


# ------------------------------------- position-domain fill of undefined pixels (our extension)
@njit(cache=True)
def position_fill(q, known, pix, Wn, Hn, radius, rounds):
    """Our extension after §3.4's search (replaces §3.5's colour push-pull for the pixels it can
    reach; = specular.position_fill): each round, every not-yet-known pixel of the searched set
    with >= 3 known pixels of the set in its (2 radius + 1)^2 new-image window gets q from the
    least-squares affine fit q = c0 + c1 dx + c2 dy of those neighbours, evaluated at its own
    position (c0; skipped this round where the offsets are collinear). Rounds are Jacobi (values found
    in a round are used from the next one); stops early when a round fills nothing.
    q (M, 2) float32, known (M,) bool, pix (M,) flat new-image indices. Returns (q, filled)."""
    M = len(q)
    qo = q.copy()
    kn = known.copy()
    filled = np.zeros(M, np.bool_)
    grid = np.full(Wn * Hn, -1, np.int64)
    for m in range(M):
        grid[pix[m]] = m
    new = np.zeros((M, 2), np.float64)
    got = np.zeros(M, np.bool_)
    for _ in range(rounds):
        any_new = False
        for m in range(M):
            got[m] = False
            if kn[m]:
                continue
            x0, y0 = pix[m] % Wn, pix[m] // Wn
            n = sx = sy = sxx = sxy = syy = 0.0
            s0 = s1 = sx0 = sx1 = sy0 = sy1 = 0.0
            for dy in range(-radius, radius + 1):
                y = y0 + dy
                if y < 0 or y >= Hn:
                    continue
                for dx in range(-radius, radius + 1):
                    x = x0 + dx
                    if x < 0 or x >= Wn:
                        continue
                    j = grid[y * Wn + x]
                    if j < 0 or not kn[j]:
                        continue
                    a, b = float(qo[j, 0]), float(qo[j, 1])
                    n += 1.0
                    sx += dx
                    sy += dy
                    sxx += dx * dx
                    sxy += dx * dy
                    syy += dy * dy
                    s0 += a
                    s1 += b
                    sx0 += dx * a
                    sx1 += dx * b
                    sy0 += dy * a
                    sy1 += dy * b
            if n < 3:
                continue
            m11 = sxx * syy - sxy * sxy
            det = n * m11 - sx * (sx * syy - sxy * sy) + sy * (sx * sxy - sxx * sy)
            if det < 0.5:   # integer offsets: det is an integer, 0 when they are collinear
                continue    # (no fit across the line; a later round may see more neighbours)
            new[m, 0] = (s0 * m11 - sx * (sx0 * syy - sxy * sy0) + sy * (sx0 * sxy - sxx * sy0)) / det
            new[m, 1] = (s1 * m11 - sx * (sx1 * syy - sxy * sy1) + sy * (sx1 * sxy - sxx * sy1)) / det
            got[m] = True
            any_new = True
        if not any_new:
            break
        for m in range(M):
            if got[m]:
                qo[m, 0], qo[m, 1] = new[m, 0], new[m, 1]
                kn[m] = True
                filled[m] = True
    return qo, filled
