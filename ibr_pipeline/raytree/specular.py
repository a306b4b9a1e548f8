"""Specular flow (Lochmann et al. 2014, §3.4 "Specular flow", Figs. 5, 6, 8).

For a new-view pixel on a specular surface, with warped diffuse position w (W_d read through the
diffuse flow), warped normal n and new camera centre c_new:
  omega = reflect(w - c_new, n)   (reflective node)   or   refract(w - c_new, n, eta) (refractive)
  Delta(omega, p) = angle(omega, p - w)                                        (§3.4)
  p*(omega) = argmin_{p in W_s} Delta(omega, p)
searched over continuous old-image locations q (p = W_s(q), bilinear) by gradient descent with
image-space finite differences; steps landing on undefined pixels or depth discontinuities are
rejected and the step shrunk; 10 steps; the pixel is undefined when the best Delta > 1 deg.
Initial guess (§3.4, Fig. 6): q0 = lambda q_d + (1 - lambda) q_s, lambda = 1 - D_d / (D_d + D_s),
q_d the diffuse flow, q_s the specular guess: the point at the node's depth along the new view ray
behind the surface, w + delta (w - c_new)/|w - c_new|, projected into the old camera. For a
reflection that is the mirror image of the reflected point about the current tangent plane
("a simple reflection around the current normal"); for a refraction it is the straight
continuation ("treat the interface as transparent with an IOR ratio of 1").

Step size (deviation, see docs/RAYTREE.md): the paper uses a fixed step of 1e-5 in units it does
not state; we use the Polyak step q <- q - s Delta g / |g|^2 (the minimum of Delta is 0), with
s = 1 halved on every rejected step. The image-space gradient g is the bilinear finite
difference of W_s between the 4 pixels around q, chained through d Delta / d p.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from . import ops


@dataclass
class SpecularOptions:
    steps: int = 10           # §3.4 "10 gradient descent steps"
    eps_deg: float = 1.0      # §3.4 "epsilon = 1 deg": undefined above
    step_scale: float = 1.0   # initial Polyak step multiplier s (halved on rejection)
    max_step_px: float = 64.0  # longest single step in old-image pixels
    rel_tol: float = 0.1      # depth discontinuity: node depths of the 4 taps differ > 10 %
    div_tol: float = 8.0      # ... plus div_tol x (angle between the quad's rays) x depth: a
                              # continuous surface seen at incidence i changes its distance by
                              # ~ tan(i) x angle x depth between two rays (8: i up to 83 deg);
                              # where the rays diverge (a convex mirror's rim) a fixed 10 % flags
                              # continuous surfaces as discontinuities. 0: the fixed test only
    min_step_px: float = 1.0 / 64  # a pixel stops when its step is shorter (0: never)
    snap_radius: int = 2      # after the descent, undefined pixels test the old pixels in a
                              # (2r+1)^2 window around their best location (0: off)
    fill_radius: int = 3      # our extension: undefined pixels take q from an affine fit of the
                              # found q of their defined neighbours in a (2r+1)^2 new-image
                              # window and read the node there (position_fill); 0: off, i.e.
                              # the paper's colour push-pull alone (§3.5)
    fill_rounds: int = 4      # ... rounds (each reaches one band further into a hole)


@dataclass
class SpecularResult:
    q: torch.Tensor        # (M, 2) best old-image location
    energy: torch.Tensor   # (M,) best Delta (radians)
    defined: torch.Tensor  # (M,) bool, best Delta <= eps
    history: torch.Tensor  # (steps + 1, M) Delta after each step (Fig. 8)
    q_d: torch.Tensor      # (M, 2) diffuse-flow guess
    q_s: torch.Tensor      # (M, 2) specular guess
    lam: torch.Tensor      # (M,) blend weight lambda


def specular_directions(w: torch.Tensor, n: torch.Tensor, c_new: torch.Tensor,
                        eta: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
    """omega (M, 3) unit and an ok mask (M,) (False on total internal reflection)."""
    d = ops.normalize(w - c_new)
    if eta is None:
        return ops.normalize(ops.reflect(d, n)), torch.ones(len(w), dtype=torch.bool, device=w.device)
    t, tir = ops.refract(d, n, eta)
    return ops.normalize(t), ~tir


def quad_table(Ws: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
    """(H*W, 16) bilinear coefficients of every 2x2 quad (top-left pixel, order x, y) of the
    positions Ws (H, W, 3) and the node depth delta (H, W): rows [a | b | c | d] with
    f(x0 + fx, y0 + fy) = a + fx b + fy c + fx fy d, i.e. a = P00, b = P10 - P00, c = P01 - P00,
    d = P11 - P10 - P01 + P00 (columns 0-11 the position, 12-15 delta). A per-tree table: one
    64-byte row gather gives the bilinear value *and* the image-space finite differences
    dp/dx = b + fy d, dp/dy = c + fx d (§3.4 "image-space finite differences") of a location."""
    H, W = delta.shape
    X = torch.cat([Ws, delta[..., None]], -1).permute(2, 0, 1)[None]             # (1, 4, H, W)
    Xp = torch.nn.functional.pad(X, (0, 1, 0, 1), mode="replicate")[0]           # (4, H+1, W+1)
    P00, P10, P01, P11 = Xp[:, :H, :W], Xp[:, :H, 1:], Xp[:, 1:, :W], Xp[:, 1:, 1:]
    if W == 1:   # the sampler's taps then use the same column (offset 0)
        P10, P11 = P00, P01
    if H == 1:
        P01, P11 = P00, P10
    a, b, c, d = P00, P10 - P00, P01 - P00, P11 - P10 - P01 + P00
    # column layout: position a b c d (12), then delta a b c d (4)
    T = torch.cat([a[:3], b[:3], c[:3], d[:3], a[3:], b[3:], c[3:], d[3:]], 0)  # (16, H, W)
    return T.reshape(16, -1).T.contiguous()


class _Energy:
    """Delta(omega, W_s(q) - w) and its image-space gradient for M pixels at once.

    One row gather of the per-tree quad table (quad_table) per evaluation; the vector algebra
    runs on separate (M,) planes with fused multiply-adds (the fewest passes over memory in
    eager torch). Non-smooth locations (an invalid tap or a depth discontinuity, ops.Sampler)
    read the nearest valid tap with a zero gradient; outside / no valid tap: Delta = pi."""

    def __init__(self, Ws, delta, valid, rel_tol, sampler=None, quad=None):
        self.H, self.W = valid.shape
        self.Ws = Ws.reshape(-1, 3)
        self.sampler = sampler or ops.Sampler(valid, delta, rel_tol)
        self.quad = quad_table(Ws, delta) if quad is None else quad
        self.quad_ok = self.sampler.quad_ok

    def coeffs(self, qx, qy):
        """(16, M) quad coefficients at locations (qx, qy), fractions fx, fy, smooth (M,) and
        defined (M,) (a valid tap was read)."""
        i0, fx, fy, inside = ops.cell(qx, qy, self.W, self.H)
        smooth = self.quad_ok[i0] & inside
        C = self.quad.index_select(0, i0).T.contiguous()
        defined = smooth
        rough = torch.nonzero(~smooth).squeeze(-1)
        if len(rough):   # nearest valid tap (ops.Sampler rule), constant: zero differences
            nr = self.sampler.taps(torch.stack([qx[rough], qy[rough]], -1)).nearest
            C[:, rough] = 0.0
            C[0:3, rough] = self.Ws[nr.clamp_min(0)].T
            C[12, rough] = self.quad[nr.clamp_min(0), 12]
            defined = smooth.clone()
            defined[rough] = nr >= 0
        return C, fx, fy, smooth, defined

    def __call__(self, qx, qy, w, om, with_delta=False):
        """qx, qy (M,); w, om: 3-tuples of (M,) planes. Returns Delta (M,), gradient gx, gy (M,),
        smooth (M,) [, bilinear delta (M,), defined (M,)]."""
        C, fx, fy, smooth, defined = self.coeffs(qx, qy)
        a0, a1, a2, b0, b1, b2, c0, c1, c2, d0, d1, d2 = C[:12].unbind(0)
        y0, y1, y2 = torch.addcmul(c0, d0, fx), torch.addcmul(c1, d1, fx), torch.addcmul(c2, d2, fx)
        x0, x1, x2 = torch.addcmul(b0, d0, fy), torch.addcmul(b1, d1, fy), torch.addcmul(b2, d2, fy)
        # v = W_s(q) - w (bilinear), dp/dx = x*, dp/dy = y*
        v0 = torch.addcmul(torch.addcmul(a0, b0, fx), y0, fy).sub_(w[0])
        v1 = torch.addcmul(torch.addcmul(a1, b1, fx), y1, fy).sub_(w[1])
        v2 = torch.addcmul(torch.addcmul(a2, b2, fx), y2, fy).sub_(w[2])
        # Delta = angle(omega, v) = atan2(|omega x v|, omega . v), |omega| = 1 (§3.4)
        vv = (v0 * v0).addcmul_(v1, v1).addcmul_(v2, v2).clamp_min_(1e-18)
        dot = (om[0] * v0).addcmul_(om[1], v1).addcmul_(om[2], v2)
        k = dot / vv
        p0, p1, p2 = om[0] - k * v0, om[1] - k * v1, om[2] - k * v2    # omega minus its part along v
        pv = (p0 * p0).addcmul_(p1, p1).addcmul_(p2, p2).mul_(vv).sqrt_()   # |omega x v|
        E = torch.atan2(pv, dot)
        # d Delta / d p = -omega_perp / (|v| |omega_perp|), chained with dp/dx, dp/dy
        sc = pv.clamp_min(1e-24).reciprocal_().neg_()
        gx = (p0 * x0).addcmul_(p1, x1).addcmul_(p2, x2).mul_(sc)
        gy = (p0 * y0).addcmul_(p1, y1).addcmul_(p2, y2).mul_(sc)
        E = torch.where(defined, E, torch.full_like(E, math.pi))
        if with_delta:
            dl = torch.addcmul(torch.addcmul(C[12], C[13], fx), torch.addcmul(C[14], C[15], fx), fy)
            return E, gx, gy, smooth, dl, defined
        return E, gx, gy, smooth


def specular_flow(w: torch.Tensor, n: torch.Tensor, c_new: torch.Tensor, eta: torch.Tensor | None,
                  q_d: torch.Tensor, Ws: torch.Tensor, delta: torch.Tensor, valid: torch.Tensor,
                  P_old: torch.Tensor, options: SpecularOptions | None = None,
                  sampler: ops.Sampler | None = None, record_history: bool = True,
                  quad: torch.Tensor | None = None) -> SpecularResult:
    """Vectorised specular search for M new-view pixels (all tensors on one device).

    w, n (M, 3): warped diffuse positions and normals; c_new (3,); eta (M,) IOR ratio for a
    refractive node or None for a reflective one; q_d (M, 2): diffuse-flow location in the old
    image; Ws (H, W, 3), delta (H, W), valid (H, W): the node's decoded positions, depth relative
    to the parent and validity; P_old (3, 4) old pixel projection; `sampler` an ops.Sampler of
    (valid, delta, options.rel_tol) and `quad` its quad_table(Ws, delta), to reuse per tree.

    The descent runs on the compacted set of still-active pixels: a pixel leaves it once its
    Delta is below 1e-5 rad (0.0006 deg, far below eps), its gradient is zero (a non-smooth
    location: it cannot move) or its last step was shorter than options.min_step_px (1/64 px:
    the Polyak steps shrink geometrically near the minimum, so the remaining steps could not
    move it visibly). Every pixel still gets at most `steps` steps (§3.4: 10)."""
    o = options or SpecularOptions()
    M = len(w)
    for t, shape, name in ((w, (M, 3), "w"), (n, (M, 3), "n"), (q_d, (M, 2), "q_d"),
                           (Ws, (None, None, 3), "Ws"), (P_old, (3, 4), "P_old")):
        ops.check(t, shape, name)
    ops.check(delta, tuple(Ws.shape[:2]), "delta")
    ops.check(valid, tuple(Ws.shape[:2]), "valid")
    if eta is not None:
        ops.check(eta, (M,), "eta")
    energy = _Energy(Ws, delta, valid, o.rel_tol, sampler, quad)
    omega, ok = specular_directions(w, n, c_new, eta)
    wP, omP = w.T.contiguous().unbind(0), omega.T.contiguous().unbind(0)   # (M,) planes
    # initial guesses (§3.4, Fig. 6)
    qdx, qdy = q_d[:, 0].contiguous(), q_d[:, 1].contiguous()
    E_d, gdx, gdy, _, d0, d_def = energy(qdx, qdy, wP, omP, with_delta=True)
    if bool(valid.any()):
        d0 = torch.where(d_def & (d0 > 0), d0, delta[valid].median())
    V = w + d0[:, None] * ops.normalize(w - c_new)
    q_s, _ = ops.project(P_old, V)
    q_s = torch.nan_to_num(q_s, nan=-1e4, posinf=1e4, neginf=-1e4).clamp(-1e4, 1e4)
    qsx, qsy = q_s[:, 0].contiguous(), q_s[:, 1].contiguous()
    E_s, gsx, gsy, _ = energy(qsx, qsy, wP, omP)
    den = E_d + E_s
    lam = torch.where(den > 0, 1 - E_d / den.clamp_min(1e-12), torch.full_like(den, 0.5))
    qx, qy = torch.lerp(qsx, qdx, lam), torch.lerp(qsy, qdy, lam)   # lam q_d + (1 - lam) q_s
    E, gx, gy, _ = energy(qx, qy, wP, omP)
    # start from the best of the three guesses (q0 unless a pure guess is better)
    for ax, ay, EE, bx, by in ((qdx, qdy, E_d, gdx, gdy), (qsx, qsy, E_s, gsx, gsy)):
        better = EE < E
        qx, qy = torch.where(better, ax, qx), torch.where(better, ay, qy)
        gx, gy = torch.where(better, bx, gx), torch.where(better, by, gy)
        E = torch.where(better, EE, E)
    hist = [E.clone()] if record_history else []
    converged = 1e-5
    act = torch.nonzero((E > converged) & (gx * gx + gy * gy > 0)).squeeze(-1)
    # compact state of the active pixels; written back when a pixel leaves the set
    A = [qx[act], qy[act], E[act], gx[act], gy[act], torch.full((len(act),), o.step_scale, device=w.device)]
    wa, oa = [x[act] for x in wP], [x[act] for x in omP]
    for _ in range(o.steps):
        if len(act):
            qax, qay, Ea, gax, gay, sa = A
            gn2 = gax * gax + gay * gay
            k = sa * Ea / gn2.clamp_min(1e-20)                     # Polyak step length factor
            L = k * gn2.sqrt()
            k = k * (o.max_step_px / L.clamp_min(1e-12)).clamp_(max=1.0)
            cx, cy = qax - k * gax, qay - k * gay
            E1, g1x, g1y, s1 = energy(cx, cy, wa, oa)
            # reject steps onto undefined pixels / depth discontinuities or uphill; shrink the step
            acc = s1 & (E1 < Ea)
            qax, qay = torch.where(acc, cx, qax), torch.where(acc, cy, qay)
            gax, gay = torch.where(acc, g1x, gax), torch.where(acc, g1y, gay)
            Ea = torch.where(acc, E1, Ea)
            sa = torch.where(acc, sa, sa * 0.5)
            A = [qax, qay, Ea, gax, gay, sa]
            # a pixel leaves the active set once converged, stuck (zero gradient) or when its
            # step fell below min_step_px (further steps cannot move it visibly)
            still = (Ea > converged) & (L > o.min_step_px) & (~acc | (g1x * g1x + g1y * g1y > 0))
            if record_history:
                E[act] = Ea
            if not bool(still.all()):
                done = torch.nonzero(~still).squeeze(-1)
                da = act[done]
                qx[da], qy[da], E[da] = qax[done], qay[done], Ea[done]
                keep = torch.nonzero(still).squeeze(-1)
                act = act[keep]
                A = [x[keep] for x in A]
                wa, oa = [x[keep] for x in wa], [x[keep] for x in oa]
        if record_history:
            hist.append(E.clone())
    if len(act):
        qx[act], qy[act], E[act] = A[0], A[1], A[2]
    q = torch.stack([qx, qy], -1)
    if o.snap_radius > 0:
        # discrete check (our addition, after the 10 steps): a pixel still above eps tests the
        # valid old pixels in a (2r+1)^2 window around its best location. The descent cannot
        # step onto a depth discontinuity, so a solution on the far side of a reflected
        # silhouette (or inside its non-smooth quad) is otherwise out of reach.
        bad = torch.nonzero(E > math.radians(o.eps_deg)).squeeze(-1)
        if len(bad):
            qb, Eb = _snap(q[bad], E[bad], w[bad], omega[bad], energy, valid, o.snap_radius)
            q[bad], E[bad] = qb, Eb
    E = torch.where(ok, E, torch.full_like(E, math.pi))
    defined = E <= math.radians(o.eps_deg)
    H = torch.stack(hist) if record_history else E[None]
    return SpecularResult(q, E, defined, H, q_d, q_s, lam)


def _snap(q, E, w, omega, energy: _Energy, valid: torch.Tensor, r: int):
    """Best valid integer pixel in the (2r+1)^2 window around round(q), where it beats E."""
    Hh, Ww = valid.shape
    d = torch.arange(-r, r + 1, device=q.device)
    dy, dx = torch.meshgrid(d, d, indexing="ij")
    qi = q.round().long()
    xs = (qi[:, :1] + dx.reshape(1, -1)).clamp(0, Ww - 1)        # (B, C)
    ys = (qi[:, 1:] + dy.reshape(1, -1)).clamp(0, Hh - 1)
    idx = ys * Ww + xs
    v = energy.Ws[idx] - w[:, None]                               # (B, C, 3)
    om = omega[:, None].expand_as(v)
    Ec = ops.angle(om, v)
    Ec = torch.where(valid.reshape(-1)[idx], Ec, torch.full_like(Ec, math.pi))
    Eb, j = Ec.min(-1)
    better = Eb < E
    qn = torch.stack([xs.gather(1, j[:, None])[:, 0], ys.gather(1, j[:, None])[:, 0]], -1).to(q.dtype)
    return torch.where(better[:, None], qn, q), torch.where(better, Eb, E)


def position_fill(q: torch.Tensor, known: torch.Tensor, pix: torch.Tensor, size: tuple[int, int],
                  radius: int, rounds: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Position-domain filling of undefined pixels (our extension after §3.4's search; §3.5
    push-pull of colours then only fills what this cannot reach). Each round, every not-yet-known
    pixel of the searched set with >= 3 known pixels of the set in its (2 radius + 1)^2 window of
    the new image gets q = c0 of the least-squares affine fit q = c0 + c1 dx + c2 dy of those
    neighbours' q (skipped in a round where the offsets are collinear); Jacobi rounds, early stop.

    Why positions, not colours: the undefined pixels sit on rims and borders (sphere silhouette,
    mirror frame), where the reconstructed normal (§3.3, 7x7 blur across the depth edge) makes
    omega itself wrong, so no search can get within epsilon; the flow q of the neighbours is
    smooth there (affine for a planar mirror), and the node read at the extrapolated q keeps the
    reflected texture where push-pull smears it. No Delta re-check for the same reason (omega is
    wrong). q (M, 2), known (M,) bool, pix (M,) flat indices of a size = (W, H) image.
    Returns (q (M, 2), filled (M,) bool: filled here). = nbsearch.position_fill."""
    Wn, Hn = size
    M = len(q)
    filled = torch.zeros(M, dtype=torch.bool, device=q.device)
    if M == 0 or radius <= 0 or rounds <= 0 or bool(known.all()):
        return q, filled
    q, kn = q.clone(), known.clone()
    grid = torch.full((Wn * Hn,), -1, dtype=torch.long, device=q.device)
    grid[pix] = torch.arange(M, device=q.device)
    d = torch.arange(-radius, radius + 1, device=q.device)
    oy, ox = torch.meshgrid(d, d, indexing="ij")
    keep = (ox != 0) | (oy != 0)
    ox, oy = ox[keep], oy[keep]                                     # (K,)
    for _ in range(rounds):
        bad = torch.nonzero(~kn).squeeze(-1)
        x = (pix[bad] % Wn)[:, None] + ox
        y = (pix[bad] // Wn)[:, None] + oy                           # (B, K)
        inside = (x >= 0) & (x < Wn) & (y >= 0) & (y < Hn)
        j = torch.where(inside, grid[(y.clamp(0, Hn - 1) * Wn + x.clamp(0, Wn - 1))], -1)
        use = (j >= 0) & kn[j.clamp_min(0)]
        u = use.double()
        fx, fy = ox.double() * u, oy.double() * u
        qj = q[j.clamp_min(0)].double() * u[..., None]               # (B, K, 2)
        n, sx, sy = u.sum(1), fx.sum(1), fy.sum(1)
        sxx, sxy, syy = (fx * ox).sum(1), (fx * oy).sum(1), (fy * oy).sum(1)
        s, sxq, syq = qj.sum(1), (qj * ox.double()[:, None]).sum(1), (qj * oy.double()[:, None]).sum(1)
        m11 = sxx * syy - sxy * sxy
        det = n * m11 - sx * (sx * syy - sxy * sy) + sy * (sx * sxy - sxx * sy)
        c0 = (s * m11[:, None] - sx[:, None] * (sxq * syy[:, None] - sxy[:, None] * syq)
              + sy[:, None] * (sxq * sxy[:, None] - sxx[:, None] * syq)) / det.clamp_min(0.5)[:, None]
        ok = (n >= 3) & (det > 0.5)   # integer offsets: det = 0 when collinear (no fit across
                                      # the line; a later round may see more neighbours)
        if not bool(ok.any()):
            break
        b = bad[ok]
        q[b] = c0[ok].to(q.dtype)
        kn[b] = True
        filled[b] = True
    return q, filled


def brute_force_search(w: np.ndarray, omega: np.ndarray, Ws: np.ndarray, valid: np.ndarray):
    """The slow, straightforward reference: for every query (M, 3) the old pixel (x, y) with the
    smallest Delta over ALL valid pixels of W_s. Returns (locations (M, 2), Delta (M,))."""
    w = np.asarray(w, np.float64)
    omega = np.asarray(omega, np.float64)
    if w.ndim != 2 or w.shape[1] != 3 or omega.shape != w.shape:
        raise ValueError(f"w and omega must both be (M, 3), got {w.shape}, {omega.shape}")
    if Ws.ndim != 3 or Ws.shape[2] != 3 or valid.shape != Ws.shape[:2]:
        raise ValueError(f"Ws must be (H, W, 3) with valid (H, W), got {Ws.shape}, {valid.shape}")
    ys, xs = np.nonzero(valid)
    P = Ws[ys, xs].astype(np.float64)
    loc = np.zeros((len(w), 2))
    best = np.full(len(w), np.pi)
    for i in range(len(w)):  # one query at a time: deliberately straightforward
        v = P - w[i]
        om = omega[i] / np.linalg.norm(omega[i])
        cr = np.linalg.norm(np.cross(v, om), axis=1)
        a = np.arctan2(cr, v @ om)
        j = int(np.argmin(a))
        loc[i] = (xs[j], ys[j])
        best[i] = a[j]
    return loc, best
