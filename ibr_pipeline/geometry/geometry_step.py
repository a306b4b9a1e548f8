"""The geometry step of Eq. 7 (Xu et al. §4.3.2): the rigid transform (R, T) of M1 and per-vertex
offsets of the meshes M0 and M1 ("(R, T) of M1, the meshes M0, M1"), alternated with the image
step (decompose.Problem.image_step); the mesh part of the smoothness term Eq. 9 (cotangent
Laplacian) regularises the offsets.

Vertex variables (one set per layer, `LayerOffsets`). Relative depth offsets delta of a coarse
control mesh (`mesh_laplacian.ControlMesh`, a regular grid of triangles over the reflector's beta
support in the reference view k, piecewise-linear interpolation to pixels): the layer's point at
pixel u moves along k's camera ray to z-depth D(u) (1 + delta(u)), D = D1 for M1 (mirror-world
points), D = the view depth for M0 (surface points). Its projection into k is unchanged, so the
image variables (R = beta I1 on k's pixels, I0 = I - R) keep their meaning.

Data term (Eq. 8) linearised. Neighbour k' pixel q sees the layer at X (its own point: X1_k'(q)
for M1, X0_k'(q) for M0, the proxy of "rendering M_k at k'"); the layer's position in k is
p_q = project_k(X) (b_q for M1, a_q for M0). Moving along k''s ray, X(t) = X + t d
(d = X - centre_k'), p moves by P d t (P = d project_k / dX, 2 x 3) and k's z-depth by z' t
(z' = e_z . d). X(t) is on the surface z = S(p) when
    z(X) + z' t = S(p) + grad S(p) . P d t,
so t = (S(p) - z(X)) / (z' - grad S . P d). With S = D (1 + delta) and first order in delta:
    p_q(delta) = p_q + J_q (eps_q + delta(p_q)),   J_q = D(p_q) P d / (z' - grad D(p_q) . P d),
where eps_q = D(p_q) / z(X) - 1 moves the neighbour's proxy point onto k's own mesh (zero when
both views agree). The slope term grad D . P d is kept (slanted surfaces, e.g. a mirrored floor),
except across depth jumps of D (> 5 %) and near grazing denominators, where J_q is set to 0 (the
point does not constrain delta). E_d's residual is I0(a_q) + R(b_q) - I_k'(q), so the M1 offsets
act through R's samples and the M0 offsets through I0 = I - R's.

Smoothness. E_lap = delta^T L delta with L the cotangent Laplacian of the control mesh in the
image plane (pixel units): for the piecewise-linear delta this is exactly the integral of
|grad delta|^2 over the pixels, the continuous form of Eq. 9's sum_u ||grad . ||^2, so its weight
is on the per-pixel scale of the image part of E_s (the paper's lambda_s = 0.04 for E_s as a
whole). We penalise the offset field, not ||L X||^2 of the mesh itself: M1 is the mirrored scene
and M0 the captured surface, both with depth discontinuities that a curvature term on a coarse
mesh would flatten.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .decompose_terms import DataTerm, ViewGeom, bilinear_cells, project, rodrigues, sample_bilinear
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


def shift_jacobian(camera, X: np.ndarray, d: np.ndarray, D: np.ndarray,
                   grad: np.ndarray | None = None, min_den: float = 0.25):
    """First-order motion of p = project(X) when the surface z = D (1 + delta) of `camera`'s view
    (D = D1 for M1, the view depth for M0) is offset by delta, X sliding along the direction d
    (module docstring). Returns J (N, 2) pixels per unit relative offset and eps (N,) =
    D(p) / z(X) - 1 (both 0 where D is missing / jumps at p or the denominator is grazing)."""
    X, d = np.asarray(X, np.float64), np.asarray(d, np.float64)
    if X.shape != d.shape or X.ndim != 2 or X.shape[1] != 3:
        raise ValueError(f"X and d must be (N, 3), got {X.shape}, {d.shape}")
    D1 = np.asarray(D, np.float64)
    if D1.shape != (camera.height, camera.width):
        raise ValueError(f"D must be ({camera.height}, {camera.width}), got {D1.shape}")
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


LAYERS = {"a": "M0", "b": "M1"}  # E_d position (a_q / b_q) -> the mesh whose offsets move it


@dataclass
class LayerOffsets:
    """The delta variables of one layer of one Problem: control mesh, its Laplacian, and per data
    term the interpolation weights W (N, V) at p_q, J_q (N, 2) and eps_q (N,). `layer` is the E_d
    position they move: "a" (a_q, M0) or "b" (b_q, M1)."""

    layer: str
    mesh: ControlMesh
    L: object  # (V, V) sparse cotangent Laplacian
    W: list
    J: list
    eps: list
    delta: np.ndarray  # (V,) relative depth offsets
    lam: float

    def shift(self, i: int, sub=None, delta: np.ndarray | None = None) -> np.ndarray:
        """(N, 2) pixel shift of term i's p_q for the offsets `delta` (default: current)."""
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


def layer_depth(ref: ViewGeom, layer: str) -> np.ndarray:
    """The z-depth that `layer`'s offsets scale, inside the beta support (0 elsewhere)."""
    return np.where(ref.mask, ref.depth if layer == "a" else ref.D1, 0.0)


def build_offsets(ref: ViewGeom, terms: list[DataTerm], centres: dict, cell: int,
                  lam: float, layer: str = "b") -> LayerOffsets:
    """The offset variables of `layer` ("a": M0, "b": M1) of `ref` (cropped view) for its data
    terms; `centres` maps each neighbour name to its camera centre (the origin of the rays
    through q)."""
    if layer not in LAYERS:
        raise ValueError(f"layer must be one of {sorted(LAYERS)}, got {layer!r}")
    D = layer_depth(ref, layer)
    mesh = grid_control_mesh(D > 0, cell)
    L = cotangent_laplacian(mesh.xy, mesh.faces)
    grad = depth_gradient(D)
    Ws, Js, es = [], [], []
    for t in terms:
        X, p = (t.X0, t.a) if layer == "a" else (t.X1, t.b)
        J, eps = shift_jacobian(ref.camera, X, X - np.asarray(centres[t.name]), D, grad)
        Ws.append(mesh.weights(p))
        Js.append(J)
        es.append(eps)
    return LayerOffsets(layer, mesh, L, Ws, Js, es, np.zeros(len(mesh.xy)), float(lam))


def bilinear_gradient(img: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """(N, C, 2) exact d/dx, d/dy of `sample_bilinear(img, pos)` (the bilinear model's own slope
    inside each cell, positions clamped like the sampler). A smoothed (Sobel) image gradient has
    the wrong sign where R varies at the pixel scale, and the offsets move p by tenths of pixels."""
    img = np.asarray(img, np.float64)
    if img.ndim != 3 or np.ndim(pos) != 2 or np.shape(pos)[1] != 2:
        raise ValueError(f"need (H, W, C) and (N, 2), got {img.shape}, {np.shape(pos)}")
    x0, y0, x1, y1, ax, ay = bilinear_cells(pos, *img.shape[:2])
    a, b, c, d = img[y0, x0], img[y0, x1], img[y1, x0], img[y1, x1]
    return np.stack([(1 - ay) * (b - a) + ay * (d - c), (1 - ax) * (c - a) + ax * (d - b)], -1)


def subsets(prob, samples: int) -> list[np.ndarray]:
    """A deterministic stride over every term's data points, <= `samples` in all."""
    n_all = sum(len(t.target) for t in prob.terms)
    stride = max(1, -(-n_all // max(samples, 1)))
    return [np.arange(0, len(t.target), stride) for t in prob.terms]


def layer_image(prob, R: np.ndarray, layer: str) -> np.ndarray:
    """The image E_d samples at `layer`'s positions: R at b_q, I0 = I - R at a_q (Eq. 3)."""
    Rm = prob._R(prob._x(R))
    return Rm if layer == "b" else prob.I - Rm


def fixed_part(prob, R: np.ndarray, layer: str, subs: list) -> np.ndarray:
    """(N, 3) E_d residual (Eq. 8) without `layer`'s sample: the other layer sampled at its
    current positions, minus the neighbours' colours."""
    other = "a" if layer == "b" else "b"
    img = layer_image(prob, R, other)
    return np.concatenate([sample_bilinear(img, prob.positions(other, i, s)) - t.target[s]
                           for i, (t, s) in enumerate(zip(prob.terms, subs))])


def lm_try(solve, evaluate, e: float, mu: float):
    """One Levenberg-Marquardt iteration: up to 4 solves with the damping mu (x 10 after each
    failure); the first whose evaluation (..., energy) is below e wins. Returns (x, evaluation,
    mu / 3.3) or None when none lowered the energy."""
    for _try in range(4):
        x = solve(mu)
        ev = evaluate(x)
        if ev[-1] < e:
            return x, ev, mu * 0.3
        mu *= 10
    return None


def pose_step(prob, R: np.ndarray, history: list) -> None:
    """Minimise E_d over the rigid transform (R, T) of M1 with the images fixed (the other
    terms do not depend on it): Levenberg-Marquardt, accepted only if the energy drops."""
    import cv2
    E0 = prob.energy(R, prob.pose)
    if not prob.terms or prob.opts.pose_iterations <= 0:
        history.append({"step": "pose", "energy": E0, "pose": prob.pose.tolist()})
        return
    # 6 unknowns: a deterministic subset of the data points suffices for the LM steps (speed);
    # the step is accepted on the full energy below
    sub = subsets(prob, prob.opts.pose_samples)
    base = fixed_part(prob, R, "b", sub).reshape(-1)
    R32 = R.astype(np.float32)
    gx = np.stack([cv2.Sobel(R32[..., c], cv2.CV_32F, 1, 0, ksize=3) / 8 for c in range(3)], -1)
    gy = np.stack([cv2.Sobel(R32[..., c], cv2.CV_32F, 0, 1, ksize=3) / 8 for c in range(3)], -1)

    def bpos(p):
        return np.concatenate([prob.b_positions(p, i, sub[i]) for i in range(len(prob.terms))])

    def evaluate(p):
        evals[0] += 1
        b = bpos(p)
        r = base + sample_bilinear(R, b).reshape(-1)
        return b, r, float(r @ r)

    evals = [0]
    p = prob.pose.copy()
    b, r, e = evaluate(p)
    lam, h = 1e-3, 1e-4
    for _ in range(prob.opts.pose_iterations):  # Gauss-Newton / LM, analytic image gradient
        G = np.stack([sample_bilinear(gx, b), sample_bilinear(gy, b)], -1)  # (N, 3, 2)
        J = np.empty((len(r), 6))
        for k in range(6):
            dp = np.zeros(6)
            dp[k] = h
            db = (bpos(p + dp) - b) / h  # (N, 2)
            J[:, k] = np.einsum("ncd,nd->nc", G, db).reshape(-1)
        JtJ, Jtr = J.T @ J, J.T @ r
        got = lm_try(lambda mu: p - np.linalg.solve(JtJ + mu * np.diag(np.diag(JtJ) + 1e-12), Jtr),
                     evaluate, e, lam)
        if got is None:
            break
        p, (b, r, e), lam = got
    E1 = prob.energy(R, p)
    if E1 < E0:
        prob.pose = np.asarray(p, np.float64)
    history.append({"step": "pose", "energy": min(E0, E1), "pose": prob.pose.tolist(),
                    "evaluations": evals[0]})


def vertex_step(prob, R: np.ndarray, history: list, layer: str = "b") -> None:
    """Minimise E_d + lambda_lap E_lap over `layer`'s offsets (M0: "a", M1: "b") with the images,
    (R, T) and the other layer fixed: Gauss-Newton / Levenberg-Marquardt with the exact bilinear
    image gradient on a deterministic subset of the data points (as the (R, T) step), accepted
    only if the full Eq. 7 energy drops. History step "vertices" (M1) / "m0_vertices" (M0)."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla
    off, o = prob.offsets[layer], prob.opts
    name = "vertices" if layer == "b" else "m0_vertices"
    E0 = prob.energy(R)
    V = len(off.delta)
    if not prob.terms or o.m1_iterations <= 0 or V == 0:
        history.append({"step": name, "energy": E0, "vertices": V})
        return
    subs = subsets(prob, o.m1_samples)
    base = fixed_part(prob, R, layer, subs)
    img = layer_image(prob, R, layer)
    p_fix = np.concatenate([prob.positions(layer, i, s, offsets=False) for i, s in enumerate(subs)])
    Wm = sp.vstack([off.W[i][s] for i, s in enumerate(subs)]).tocsr()
    Jq = np.concatenate([off.J[i][s] for i, s in enumerate(subs)])
    eps = np.concatenate([off.eps[i][s] for i, s in enumerate(subs)])
    lam, L = off.lam, off.L
    ridge = 1e-6 * sp.identity(V)

    def evaluate(d):
        p = p_fix + Jq * (eps + Wm @ d)[:, None]
        r = base + sample_bilinear(img, p)
        return p, r, float((r ** 2).sum()) + lam * float(d @ (L @ d))

    d = off.delta.copy()
    p, r, e = evaluate(d)
    energies, mu = [e], 1e-3
    for _ in range(o.m1_iterations):  # Gauss-Newton / LM
        G = bilinear_gradient(img, p)  # (N, 3, 2)
        s = np.einsum("ncd,nd->nc", G, Jq)  # d r_c / d(offset at q)
        JtJ = sum(Wm.T @ sp.diags(s[:, c] ** 2) @ Wm for c in range(3))
        Jtr = sum(Wm.T @ (s[:, c] * r[:, c]) for c in range(3))
        A = (JtJ + lam * L + ridge).tocsc()
        g = Jtr + lam * (L @ d)
        dj = JtJ.diagonal()
        got = lm_try(lambda m: np.clip(d + spla.spsolve((A + m * sp.diags(dj + 1e-12)).tocsc(), -g),
                                       -o.m1_max_offset, o.m1_max_offset), evaluate, e, mu)
        if got is None:
            break
        d, (p, r, e), mu = got
        energies.append(e)
    old = off.delta
    off.delta = d
    E1 = prob.energy(R)
    if not E1 < E0:
        off.delta = old
    history.append({"step": name, "energy": float(min(E0, E1)), "vertices": V,
                    "subset_energy": [float(v) for v in energies],
                    "E_lap": off.e_lap(), "max_abs_offset": float(np.abs(off.delta).max())})


# --- the optimised meshes (what stages.reflection writes as M0.ply / M1.ply) ---------------------
def optimised_m1(g, mask, offset, pose):
    """M1's points and z-depth after the geometry step (Eq. 7): the vertex offsets move each point
    along the view's ray to depth D1 (1 + offset) (LayerOffsets), then the rigid (R, T) about
    the centre of the initial M1 (decompose.Problem.centre). Returns (H, W, 3) and (H, W)."""
    X1, D1 = g.X1.copy(), g.D1
    sel = mask & (g.D1 > 0)
    c = np.nanmean(X1[sel], axis=0) if sel.any() else np.zeros(3)
    if offset is not None:
        if np.shape(offset) != np.shape(D1):
            raise ValueError(f"offset must be {np.shape(D1)}, got {np.shape(offset)}")
        X1 = g.camera.center + (X1 - g.camera.center) * (1 + offset)[..., None]
        D1 = D1 * (1 + offset)
    pose = np.asarray(pose, np.float64)
    if np.any(pose != 0):
        X1 = (X1 - c) @ rodrigues(pose[:3]).T + c + pose[3:]
    return X1, D1


def optimised_m0(vertices, camera, offset):
    """M0's vertices (world, (V, 3)) after the vertex step (Eq. 7 variables M^0): each moves along
    the view's ray, X -> c + (X - c) (1 + offset(u)), u its pixel in `camera` (bilinear in the
    (H, W) offset map, 0 outside the reflectors), so its projection is unchanged."""
    V = np.asarray(vertices, np.float64)
    if np.shape(offset) != (camera.height, camera.width):
        raise ValueError(f"offset must be ({camera.height}, {camera.width}), got {np.shape(offset)}")
    uv, z = project(camera, V)
    inside = (z > 0) & np.all(uv >= 0, axis=1) & (uv[:, 0] <= camera.width - 1) \
        & (uv[:, 1] <= camera.height - 1)
    o = np.where(inside, sample_bilinear(np.asarray(offset, np.float64)[..., None],
                                         np.where(inside[:, None], uv, 0.0))[:, 0], 0.0)
    c = camera.center
    return (c + (V - c) * (1 + o)[:, None]).astype(np.asarray(vertices).dtype)
