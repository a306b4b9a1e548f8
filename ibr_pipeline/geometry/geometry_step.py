"""Per-vertex optimisation of the reflection mesh M1 (Xu et al. §4.3.2, Eq. 7 variables M^1 and
the mesh part of the smoothness term Eq. 9).

Variables. Relative depth offsets delta of a coarse control mesh (`mesh_laplacian.ControlMesh`,
a regular grid of triangles over the reflector's beta support in the reference view k,
piecewise-linear interpolation to pixels): M1's point at pixel u moves along k's camera ray to
z-depth D1(u) (1 + delta(u)). Its projection into k is unchanged, so the image variables
(R = beta I1 on k's pixels) keep their meaning.

Data term (Eq. 8) linearised like the (R, T) step. Neighbour k' pixel q sees M1 at X (its own
mirror-world point, the proxy of "rendering M1_k at k'"), b_q = project_k(X). Moving along
k''s ray, X(t) = X + t d (d = X - centre_k'), b moves by P d t (P = d project_k / dX, 2 x 3)
and k's z-depth by z' t (z' = e_z . d). X(t) is on the surface z = S(b) when
    z(X) + z' t = S(b) + grad S(b) . P d t,
so t = (S(b) - z(X)) / (z' - grad S . P d). With S = D1 (1 + delta) and first order in delta:
    b_q(delta) = b_q + J_q (eps_q + delta(b_q)),   J_q = D1(b_q) P d / (z' - grad D1(b_q) . P d),
where eps_q = D1(b_q) / z(X) - 1 moves the neighbour's proxy point onto k's own M1 (zero when
both views' M1 agree). The slope term grad D1 . P d is kept (it matters on slanted reflected
surfaces, e.g. a mirrored floor), except across depth jumps of D1 (> 5 %) and near grazing
denominators, where J_q is set to 0 (the point does not constrain delta).

Smoothness. E_lap = delta^T L delta with L the cotangent Laplacian of the control mesh in the
image plane (pixel units): for the piecewise-linear delta this is exactly the integral of
|grad delta|^2 over the pixels, the continuous form of Eq. 9's sum_u ||grad . ||^2, so its weight
is on the per-pixel scale of the image part of E_s (the paper's lambda_s = 0.04 for E_s as a
whole). We penalise the offset field, not ||L X||^2 of M1 itself: M1 is the mirrored scene with
depth discontinuities that a curvature term on a coarse mesh would flatten.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .decompose import DataTerm, ViewGeom, bilinear_cells, bilinear_matrix, project, sample_bilinear
from .mesh_laplacian import ControlMesh, cotangent_laplacian, grid_control_mesh


def depth_gradient(D: np.ndarray, max_rel_jump: float = 0.05) -> np.ndarray:
    """(H, W, 2) d/du, d/dv of a z-depth map by central (or one-sided) differences between valid
    pixels (D > 0) whose depths differ by at most `max_rel_jump`; 0 where none applies."""
    D = np.asarray(D, np.float64)
    if D.ndim != 2:
        raise ValueError(f"depth must be (H, W), got {D.shape}")
    out = np.zeros(D.shape + (2,))
    for ax, k in ((1, 0), (0, 1)):
        P = np.pad(D, [(1, 1) if a == ax else (0, 0) for a in (0, 1)])
        sl = [slice(None), slice(None)]
        sl[ax] = slice(2, None)
        fwd = P[tuple(sl)]
        sl[ax] = slice(0, -2)
        bwd = P[tuple(sl)]
        okf = (D > 0) & (fwd > 0) & (np.abs(fwd - D) <= max_rel_jump * np.minimum(fwd, np.where(D > 0, D, 1)))
        okb = (D > 0) & (bwd > 0) & (np.abs(D - bwd) <= max_rel_jump * np.minimum(bwd, np.where(D > 0, D, 1)))
        g = np.where(okf & okb, (fwd - bwd) / 2, np.where(okf, fwd - D, np.where(okb, D - bwd, 0.0)))
        out[..., k] = g
    return out


def projection_jacobian(camera, X: np.ndarray) -> np.ndarray:
    """(N, 2, 3) d project(X) / dX for (N, 3) world points (pinhole, K with zero skew or not)."""
    X = np.asarray(X, np.float64)
    if X.ndim != 2 or X.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {X.shape}")
    Y = X @ camera.R.T + camera.t
    z = Y[:, 2]
    uv = (Y @ camera.K.T)[:, :2] / z[:, None]
    K = camera.K
    dY = (K[None, :2, :] - uv[:, :, None] * K[None, 2:3, :]) / z[:, None, None]  # (N, 2, 3)
    return dY @ camera.R


def shift_jacobian(camera, X: np.ndarray, d: np.ndarray, D1: np.ndarray,
                   grad: np.ndarray | None = None, min_den: float = 0.25):
    """First-order motion of b = project(X) when the surface z = D1 (1 + delta) of `camera`'s view
    is offset by delta, X sliding along the direction d (module docstring).
    Returns J (N, 2) pixels per unit relative offset and eps (N,) = D1(b) / z(X) - 1 (both 0 where
    D1 is missing / jumps at b or the denominator is grazing)."""
    X, d = np.asarray(X, np.float64), np.asarray(d, np.float64)
    if X.shape != d.shape or X.ndim != 2 or X.shape[1] != 3:
        raise ValueError(f"X and d must be (N, 3), got {X.shape}, {d.shape}")
    D1 = np.asarray(D1, np.float64)
    if D1.shape != (camera.height, camera.width):
        raise ValueError(f"D1 must be ({camera.height}, {camera.width}), got {D1.shape}")
    grad = depth_gradient(D1) if grad is None else grad
    b, z = project(camera, X)
    P = projection_jacobian(camera, X)
    Pd = np.einsum("nij,nj->ni", P, d)
    zdot = d @ camera.R[2]
    # D1 at b: bilinear where the four taps are valid and within 5 % of each other
    H, W = D1.shape
    x0 = np.clip(np.floor(b[:, 0]).astype(np.int64), 0, max(W - 2, 0))
    y0 = np.clip(np.floor(b[:, 1]).astype(np.int64), 0, max(H - 2, 0))
    taps = np.stack([D1[y0, x0], D1[y0, x0 + 1], D1[y0 + 1, x0], D1[y0 + 1, x0 + 1]], 1)
    ok = np.all(taps > 0, axis=1) & (taps.max(1) <= 1.05 * np.where(taps.min(1) > 0, taps.min(1), 1))
    S = sample_bilinear(D1[..., None], b)[:, 0]
    g = sample_bilinear(grad, b)
    den = zdot - (g * Pd).sum(1)
    ok &= (np.abs(den) >= min_den * np.abs(zdot)) & (np.sign(den) == np.sign(zdot)) & (z > 0)
    J = np.where(ok[:, None], S[:, None] * Pd / np.where(ok, den, 1.0)[:, None], 0.0)
    eps = np.where(ok, S / np.where(z > 0, z, 1.0) - 1.0, 0.0)
    eps = np.where(np.abs(eps) <= 0.05, eps, 0.0)  # the data terms' visibility tolerance
    return J, eps


@dataclass
class M1Offsets:
    """The delta variables of one Problem: control mesh, its Laplacian, and per data term the
    interpolation weights W (N, V) at b_q, J_q (N, 2) and eps_q (N,)."""

    mesh: ControlMesh
    L: object  # (V, V) sparse cotangent Laplacian
    W: list
    J: list
    eps: list
    delta: np.ndarray  # (V,) relative depth offsets
    lam: float

    def shift(self, i: int, sub=None, delta: np.ndarray | None = None) -> np.ndarray:
        """(N, 2) pixel shift of term i's b_q for the offsets `delta` (default: current)."""
        d = self.delta if delta is None else delta
        W, J, e = self.W[i], self.J[i], self.eps[i]
        if sub is not None:
            W, J, e = W[sub], J[sub], e[sub]
        return J * (e + W @ d)[:, None]

    def e_lap(self, delta: np.ndarray | None = None) -> float:
        d = self.delta if delta is None else delta
        return float(d @ (self.L @ d))  # Eq. 9 mesh part (module docstring)

    def pixel_offsets(self, shape: tuple[int, int], mask: np.ndarray) -> np.ndarray:
        """(H, W) delta interpolated at the pixels of `mask` (0 elsewhere)."""
        out = np.zeros(shape)
        ys, xs = np.nonzero(mask)
        out[ys, xs] = self.mesh.weights(np.c_[xs, ys].astype(np.float64)) @ self.delta
        return out


def build_offsets(ref: ViewGeom, terms: list[DataTerm], centres: dict, cell: int,
                  lam: float) -> M1Offsets:
    """The M1 offset variables of `ref` (cropped view) for its data terms; `centres` maps each
    neighbour name to its camera centre (the origin of the rays through q)."""
    D1 = np.where(ref.mask, ref.D1, 0.0)
    mesh = grid_control_mesh(ref.mask & (ref.D1 > 0), cell)
    L = cotangent_laplacian(mesh.xy, mesh.faces)
    grad = depth_gradient(D1)
    Ws, Js, es = [], [], []
    for t in terms:
        J, eps = shift_jacobian(ref.camera, t.X1, t.X1 - np.asarray(centres[t.name]), D1, grad)
        Ws.append(mesh.weights(t.b))
        Js.append(J)
        es.append(eps)
    return M1Offsets(mesh, L, Ws, Js, es, np.zeros(len(mesh.xy)), float(lam))


def bilinear_gradient(img: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """(N, C, 2) exact d/dx, d/dy of `sample_bilinear(img, pos)` (the bilinear model's own slope
    inside each cell, positions clamped like the sampler). A smoothed (Sobel) image gradient has
    the wrong sign where R varies at the pixel scale, and the offsets move b by tenths of pixels."""
    img = np.asarray(img, np.float64)
    if img.ndim != 3 or np.ndim(pos) != 2 or np.shape(pos)[1] != 2:
        raise ValueError(f"need (H, W, C) and (N, 2), got {img.shape}, {np.shape(pos)}")
    x0, y0, x1, y1, ax, ay = bilinear_cells(pos, *img.shape[:2])
    a, b, c, d = img[y0, x0], img[y0, x1], img[y1, x0], img[y1, x1]
    return np.stack([(1 - ay) * (b - a) + ay * (d - c), (1 - ax) * (c - a) + ax * (d - b)], -1)


def vertex_step(prob, R: np.ndarray, history: list) -> None:
    """Minimise E_d + lambda_lap E_lap over the M1 offsets with the images and (R, T) fixed:
    Gauss-Newton / Levenberg-Marquardt with the exact bilinear image gradient on a deterministic subset
    of the data points (as the (R, T) step), accepted only if the full Eq. 7 energy drops."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla
    off, o = prob.offsets, prob.opts
    E0 = prob.energy(R)
    V = len(off.delta)
    if not prob.terms or o.m1_iterations <= 0 or V == 0:
        history.append({"step": "vertices", "energy": E0, "vertices": V})
        return
    x = prob._x(R)
    n_all = sum(len(t.target) for t in prob.terms)
    stride = max(1, -(-n_all // max(o.m1_samples, 1)))
    subs = [np.arange(0, len(t.target), stride) for t in prob.terms]
    base = np.concatenate([
        prob.Sa_I[i][s] - bilinear_matrix(t.a[s], prob.W, prob.H)[:, prob.flat] @ x - t.target[s]
        for i, (t, s) in enumerate(zip(prob.terms, subs))])
    b_fix = np.concatenate([prob.b_positions(prob.pose, i, s, offsets=False)
                            for i, s in enumerate(subs)])
    Wm = sp.vstack([off.W[i][s] for i, s in enumerate(subs)]).tocsr()
    Jq = np.concatenate([off.J[i][s] for i, s in enumerate(subs)])
    eps = np.concatenate([off.eps[i][s] for i, s in enumerate(subs)])
    lam, L = off.lam, off.L
    ridge = 1e-6 * sp.identity(V)

    def evaluate(d):
        b = b_fix + Jq * (eps + Wm @ d)[:, None]
        r = base + sample_bilinear(R, b)
        return b, r, float((r ** 2).sum()) + lam * float(d @ (L @ d))

    d = off.delta.copy()
    b, r, e = evaluate(d)
    energies, mu = [e], 1e-3
    for _ in range(o.m1_iterations):  # Gauss-Newton / LM
        G = bilinear_gradient(R, b)  # (N, 3, 2)
        s = np.einsum("ncd,nd->nc", G, Jq)  # d r_c / d(offset at q)
        JtJ = sum(Wm.T @ sp.diags(s[:, c] ** 2) @ Wm for c in range(3))
        Jtr = sum(Wm.T @ (s[:, c] * r[:, c]) for c in range(3))
        A = (JtJ + lam * L + ridge).tocsc()
        g = Jtr + lam * (L @ d)
        dj = JtJ.diagonal()
        for _try in range(4):
            step = spla.spsolve((A + mu * sp.diags(dj + 1e-12)).tocsc(), -g)
            dn = np.clip(d + step, -o.m1_max_offset, o.m1_max_offset)
            bn, rn, en = evaluate(dn)
            if en < e:
                d, b, r, e, mu = dn, bn, rn, en, mu * 0.3
                break
            mu *= 10
        else:
            break
        energies.append(e)
    old = off.delta
    off.delta = d
    E1 = prob.energy(R)
    if not E1 < E0:
        off.delta = old
    history.append({"step": "vertices", "energy": float(min(E0, E1)), "vertices": V,
                    "subset_energy": [float(v) for v in energies],
                    "E_lap": off.e_lap(), "max_abs_offset": float(np.abs(off.delta).max())})

