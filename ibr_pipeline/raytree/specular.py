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
    min_step_px: float = 1.0 / 64  # a pixel stops when its step is shorter (0: never)
    snap_radius: int = 2      # after the descent, undefined pixels test the old pixels in a
                              # (2r+1)^2 window around their best location (0: off)


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


class _Energy:
    """Delta(omega, W_s(q) - w) and its image-space gradient for M pixels at once.

    Vectors are kept as (3, M) rows (structure of arrays): the 4 bilinear taps are 4 column
    gathers of the (3, H*W) position table, and every dot product is a sum over the short first
    axis, which vectorises over M."""

    def __init__(self, Ws, delta, valid, rel_tol, sampler=None):
        self.H, self.W = valid.shape
        self.Ws = Ws.reshape(-1, 3)
        self.WsT = self.Ws.T.contiguous()                      # (3, H*W)
        self.sampler = sampler or ops.Sampler(valid, delta, rel_tol)

    def __call__(self, q, wT, omT, taps=None):
        """q (M, 2); wT, omT (3, M). Returns Delta (M,), gradient (M, 2), smooth (M,)."""
        t = self.sampler.taps(q) if taps is None else taps
        o1, o2 = self.sampler.offs[1], self.sampler.offs[2]
        i0 = t.i0
        P0 = self.WsT.index_select(1, i0)
        P1 = self.WsT.index_select(1, i0 + o1)
        P2 = self.WsT.index_select(1, i0 + o2)
        P3 = self.WsT.index_select(1, i0 + (o1 + o2))
        fx, fy = t.fx, t.fy
        d01 = P1 - P0
        d23 = P3 - P2
        top = P0 + fx * d01
        dpy = (P2 + fx * d23) - top                          # dp/dy (bilinear finite difference)
        p = top + fy * dpy                                   # bilinear W_s(q)
        rough = torch.nonzero(~t.smooth).squeeze(-1)
        if len(rough):
            p[:, rough] = self.WsT[:, t.nearest[rough].clamp_min(0)]
        v = p - wT
        # Delta = angle(omega, v) = atan2(|omega x v|, omega . v), |omega| = 1
        vv = (v * v).sum(0).clamp_min(1e-18)
        dot = (omT * v).sum(0)
        perp = omT - (dot / vv) * v                          # omega minus its part along v
        pv = ((perp * perp).sum(0) * vv).sqrt()              # |omega_perp| |v| = |omega x v|
        E = torch.atan2(pv, dot)
        dpx = d01 + fy * (d23 - d01)                         # dp/dx
        # d Delta / d p = -omega_perp / (|v| |omega_perp|): magnitude 1/|v|
        gp = perp * (-1.0 / pv.clamp_min(1e-24))
        g = torch.stack([(gp * dpx).sum(0), (gp * dpy).sum(0)], -1)
        if len(rough):
            g[rough] = 0.0
            E[rough[t.nearest[rough] < 0]] = math.pi
        return E, g, t.smooth


def specular_flow(w: torch.Tensor, n: torch.Tensor, c_new: torch.Tensor, eta: torch.Tensor | None,
                  q_d: torch.Tensor, Ws: torch.Tensor, delta: torch.Tensor, valid: torch.Tensor,
                  P_old: torch.Tensor, options: SpecularOptions | None = None,
                  sampler: ops.Sampler | None = None, record_history: bool = True) -> SpecularResult:
    """Vectorised specular search for M new-view pixels (all tensors on one device).

    w, n (M, 3): warped diffuse positions and normals; c_new (3,); eta (M,) IOR ratio for a
    refractive node or None for a reflective one; q_d (M, 2): diffuse-flow location in the old
    image; Ws (H, W, 3), delta (H, W), valid (H, W): the node's decoded positions, depth relative
    to the parent and validity; P_old (3, 4) old pixel projection; `sampler` an ops.Sampler of
    (valid, delta, options.rel_tol) to reuse.

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
    energy = _Energy(Ws, delta, valid, o.rel_tol, sampler)
    omega, ok = specular_directions(w, n, c_new, eta)
    wT, omT = w.T.contiguous(), omega.T.contiguous()
    # initial guesses (§3.4, Fig. 6)
    t_d = energy.sampler.taps(q_d)
    E_d, g_d, s_d = energy(q_d, wT, omT, t_d)
    d0, _, d_def = energy.sampler.sample(delta[..., None], q_d, t_d)
    d0 = d0[:, 0]
    if bool(valid.any()):
        d0 = torch.where(d_def & (d0 > 0), d0, delta[valid].median())
    V = w + d0[:, None] * ops.normalize(w - c_new)
    q_s, _ = ops.project(P_old, V)
    q_s = torch.nan_to_num(q_s, nan=-1e4, posinf=1e4, neginf=-1e4).clamp(-1e4, 1e4)
    E_s, g_s, s_s = energy(q_s, wT, omT)
    den = E_d + E_s
    lam = torch.where(den > 0, 1 - E_d / den.clamp_min(1e-12), torch.full_like(den, 0.5))
    q0 = lam[:, None] * q_d + (1 - lam[:, None]) * q_s
    E0, g0, s0 = energy(q0, wT, omT)
    # start from the best of the three guesses (q0 unless a pure guess is better)
    q, E, g = q0, E0, g0
    for qq, EE, gg in ((q_d, E_d, g_d), (q_s, E_s, g_s)):
        better = EE < E
        q = torch.where(better[:, None], qq, q)
        g = torch.where(better[:, None], gg, g)
        E = torch.where(better, EE, E)
    s = torch.full_like(E, o.step_scale)
    hist = [E.clone()] if record_history else []
    converged = 1e-5
    act = torch.nonzero((E > converged) & ((g * g).sum(-1) > 0)).squeeze(-1)
    for _ in range(o.steps):
        if len(act):
            qa, Ea, ga, sa = q[act], E[act], g[act], s[act]
            gn2 = (ga * ga).sum(-1)
            step = ga * (sa * Ea / gn2.clamp_min(1e-20))[:, None]      # Polyak step
            L = (step * step).sum(-1).sqrt()
            step = step * (o.max_step_px / L.clamp_min(1e-12)).clamp(max=1.0)[:, None]
            cand = qa - step
            E1, g1, s1 = energy(cand, wT[:, act], omT[:, act])
            # reject steps onto undefined pixels / depth discontinuities or uphill; shrink the step
            acc = s1 & (E1 < Ea)
            q[act] = torch.where(acc[:, None], cand, qa)
            g[act] = torch.where(acc[:, None], g1, ga)
            Ea = torch.where(acc, E1, Ea)
            E[act] = Ea
            s[act] = torch.where(acc, sa, sa * 0.5)
            # a pixel leaves the active set once converged, stuck (zero gradient) or when its
            # step fell below min_step_px (further steps cannot move it visibly)
            moved = (L > o.min_step_px)
            still = (Ea > converged) & moved & ((acc & ((g1 * g1).sum(-1) > 0)) | ~acc)
            act = act[still]
        if record_history:
            hist.append(E.clone())
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
