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
    """Delta(omega, W_s(q) - w) and its image-space gradient for M pixels at once."""

    def __init__(self, Ws, delta, valid, rel_tol):
        self.H, self.W = valid.shape
        self.Ws = Ws.reshape(-1, 3)
        self.sampler = ops.Sampler(valid, delta, rel_tol)

    def __call__(self, q, w, omega):
        idx, wt, tv, smooth, nearest = self.sampler.taps(q)
        P = self.Ws[idx]                                      # (M, 4, 3)
        bil = (P * wt[..., None]).sum(1)
        p = torch.where(smooth[:, None], bil, self.Ws[nearest.clamp_min(0)])
        v = p - w
        E = ops.angle(omega, v)
        E = torch.where(nearest >= 0, E, torch.full_like(E, math.pi))
        # bilinear derivatives dp/dx, dp/dy = image-space finite differences of W_s
        x = q[:, 0].clamp(0, self.W - 1)
        y = q[:, 1].clamp(0, self.H - 1)
        fx = (x - x.floor().clamp(max=max(self.W - 2, 0)))[:, None]
        fy = (y - y.floor().clamp(max=max(self.H - 2, 0)))[:, None]
        dpx = (1 - fy) * (P[:, 1] - P[:, 0]) + fy * (P[:, 3] - P[:, 2])
        dpy = (1 - fx) * (P[:, 2] - P[:, 0]) + fx * (P[:, 3] - P[:, 1])
        # d Delta / d p = -(omega_perp) / (|v| |omega_perp|): magnitude 1/|v|
        vn = v.norm(dim=-1, keepdim=True).clamp_min(1e-9)
        vh = v / vn
        perp = omega - (omega * vh).sum(-1, keepdim=True) * vh
        gp = -perp / (perp.norm(dim=-1, keepdim=True).clamp_min(1e-12) * vn)
        g = torch.stack([(gp * dpx).sum(-1), (gp * dpy).sum(-1)], -1)
        g = torch.where(smooth[:, None], g, torch.zeros_like(g))
        return E, g, smooth


def specular_flow(w: torch.Tensor, n: torch.Tensor, c_new: torch.Tensor, eta: torch.Tensor | None,
                  q_d: torch.Tensor, Ws: torch.Tensor, delta: torch.Tensor, valid: torch.Tensor,
                  P_old: torch.Tensor, options: SpecularOptions | None = None) -> SpecularResult:
    """Vectorised specular search for M new-view pixels (all tensors on one device).

    w, n (M, 3): warped diffuse positions and normals; c_new (3,); eta (M,) IOR ratio for a
    refractive node or None for a reflective one; q_d (M, 2): diffuse-flow location in the old
    image; Ws (H, W, 3), delta (H, W), valid (H, W): the node's decoded positions, depth relative
    to the parent and validity; P_old (3, 4) old pixel projection."""
    o = options or SpecularOptions()
    M = len(w)
    for t, shape, name in ((w, (M, 3), "w"), (n, (M, 3), "n"), (q_d, (M, 2), "q_d"),
                           (Ws, (None, None, 3), "Ws"), (P_old, (3, 4), "P_old")):
        ops.check(t, shape, name)
    ops.check(delta, tuple(Ws.shape[:2]), "delta")
    ops.check(valid, tuple(Ws.shape[:2]), "valid")
    if eta is not None:
        ops.check(eta, (M,), "eta")
    energy = _Energy(Ws, delta, valid, o.rel_tol)
    omega, ok = specular_directions(w, n, c_new, eta)
    # initial guesses (§3.4, Fig. 6)
    E_d, g_d, s_d = energy(q_d, w, omega)
    d0, _, d_def = energy.sampler.sample(delta[..., None], q_d)
    d0 = d0[:, 0]
    if bool(valid.any()):
        d0 = torch.where(d_def & (d0 > 0), d0, delta[valid].median())
    V = w + d0[:, None] * ops.normalize(w - c_new)
    q_s, _ = ops.project(P_old, V)
    q_s = torch.nan_to_num(q_s, nan=-1e4, posinf=1e4, neginf=-1e4).clamp(-1e4, 1e4)
    E_s, g_s, s_s = energy(q_s, w, omega)
    den = E_d + E_s
    lam = torch.where(den > 0, 1 - E_d / den.clamp_min(1e-12), torch.full_like(den, 0.5))
    q0 = lam[:, None] * q_d + (1 - lam[:, None]) * q_s
    E0, g0, s0 = energy(q0, w, omega)
    # start from the best of the three guesses (q0 unless a pure guess is better)
    q, E, g = q0, E0, g0
    for qq, EE, gg in ((q_d, E_d, g_d), (q_s, E_s, g_s)):
        better = EE < E
        q = torch.where(better[:, None], qq, q)
        g = torch.where(better[:, None], gg, g)
        E = torch.where(better, EE, E)
    s = torch.full_like(E, o.step_scale)
    hist = [E]
    for _ in range(o.steps):
        gn2 = (g * g).sum(-1)
        step = torch.where(gn2[:, None] > 0, (s * E / gn2.clamp_min(1e-20))[:, None] * g,
                           torch.zeros_like(g))
        L = step.norm(dim=-1, keepdim=True)
        step = step * (o.max_step_px / L.clamp_min(1e-12)).clamp(max=1.0)
        cand = q - step
        E1, g1, s1 = energy(cand, w, omega)
        # reject steps onto undefined pixels / depth discontinuities or uphill; shrink the step
        acc = s1 & (E1 < E) & (gn2 > 0)
        q = torch.where(acc[:, None], cand, q)
        g = torch.where(acc[:, None], g1, g)
        E = torch.where(acc, E1, E)
        s = torch.where(acc, s, s * 0.5)
        hist.append(E)
    E = torch.where(ok, E, torch.full_like(E, math.pi))
    defined = E <= math.radians(o.eps_deg)
    return SpecularResult(q, E, defined, torch.stack(hist), q_d, q_s, lam)


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
