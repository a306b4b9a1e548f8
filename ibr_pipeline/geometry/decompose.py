"""Two-layer reflection decomposition of one view and one planar reflector (Xu et al. §4.3,
Eqs. 3, 6-13).

Variables. Inside the reflector's beta support we optimise the reflection component
R = beta * I1 (the paper's beta is a binary mask, so its I1 is our R); Eq. 3 is enforced as a hard
constraint, I0 = I - R, and the box constraint of Eq. 7 (I0, I1 in [0, 1]) becomes
0 <= R <= min(I, beta). The stored I1 is R / beta (beta = the reflectance, 1 when unknown).

Flows. `ViewGeom` holds, per view, the surface points X0 (from the refined depth: M0) and the
mirror-world points X1 (the planar-reflection geometry: M1). w_k'(u, M) = project_k'(X(u)).
The data term Eq. 8 is evaluated at the neighbour's pixels q: the surface layer of view k seen at
q comes from a_q = project_k(X0_k'(q)) and the reflection layer from b_q = project_k(X1_k'(q)) —
the inverse flows w^-1 obtained by "rendering" M0 / M1 at k' (exact for planar reflectors, since
M1 is the mirrored scene). Sampling is bilinear (torch grid_sample), so E_d is differentiable in
the images and in the rigid transform (R, T) of M1.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..scene import Camera


@dataclass
class ViewGeom:
    """One view seen at working resolution, for one reflector."""

    name: str
    camera: Camera
    image: np.ndarray  # (H, W, 3) linear [0, 1]
    depth: np.ndarray  # (H, W) z-depth of the surface (M0), 0 = none
    mask: np.ndarray  # (H, W) bool, beta support of the reflector
    X0: np.ndarray  # (H, W, 3) surface points (NaN where none)
    X1: np.ndarray  # (H, W, 3) mirror-world points inside mask (NaN elsewhere)
    D1: np.ndarray  # (H, W) z-depth of X1 in this camera (0 = none)

    def __post_init__(self) -> None:
        H, W = self.camera.height, self.camera.width
        for name, shape in (("image", (H, W, 3)), ("depth", (H, W)), ("mask", (H, W)),
                            ("X0", (H, W, 3)), ("X1", (H, W, 3)), ("D1", (H, W))):
            a = getattr(self, name)
            if np.shape(a) != shape:
                raise ValueError(f"ViewGeom {self.name}: {name} must be {shape}, got {np.shape(a)}")
            if name == "image" and not np.all(np.isfinite(a)):
                raise ValueError(f"ViewGeom {self.name}: image has non-finite values")


@dataclass(frozen=True)
class DecomposeOptions:
    """Xu et al. §4.3 parameters (defaults as in the paper)."""

    max_neighbours: int = 6  # §4.3.1: top six
    min_overlap: float = 0.3  # §4.3.1: > 30 % depth overlap
    overlap_tol: float = 0.05  # §4.3.1: depth difference < 0.05 * min(depth)
    grid: tuple[int, int] = (40, 30)  # §4.3.1: 40 x 30 grid
    w_r: float = 1.2  # Eq. 5
    w_a: float = 0.5  # Eq. 5
    gn_iterations: int = 5  # §4.3.1: 5 Gauss-Newton iterations
    use_warp: bool = True  # refine w by the ARAP grid warp in the initialisation
    lambda_s: float = 0.04  # Eq. 7
    lambda_p: float = 0.01  # Eq. 7
    lambda_mv: float = 0.05  # Eq. 7 after aggregation (0 in the first pass)
    outer_iterations: int = 2  # §4.3.3: "usually two iterations"
    image_iterations: int = 60  # L-BFGS-B iterations of one image step
    pose_iterations: int = 10  # L-BFGS iterations of one (R, T) step
    optimise_pose: bool = True
    saturation: float = 0.98  # highlights: pixels with a channel >= this are left out of E_d
    visibility_tol: float = 0.05  # relative depth tolerance of the occlusion tests


def project(camera: Camera, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(..., 3) world points -> (..., 2) pixel positions and (...) z-depth (NaN propagates)."""
    X = np.asarray(X, np.float64)
    if X.shape[-1] != 3:
        raise ValueError(f"points must be (..., 3), got {X.shape}")
    shp = X.shape[:-1]
    flat = X.reshape(-1, 3)
    cam = flat @ camera.R.T + camera.t
    z = cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (cam @ camera.K.T)[:, :2] / z[:, None]
    return uv.reshape(shp + (2,)), z.reshape(shp)


def _nearest(img: np.ndarray, pos: np.ndarray, fill=0):
    H, W = img.shape[:2]
    x = np.rint(np.nan_to_num(pos[..., 0], nan=-1)).astype(np.int64)
    y = np.rint(np.nan_to_num(pos[..., 1], nan=-1)).astype(np.int64)
    inside = (x >= 0) & (x < W) & (y >= 0) & (y < H)
    out = np.full(pos.shape[:-1] + img.shape[2:], fill, dtype=img.dtype)
    out[inside] = img[y[inside], x[inside]]
    return out, inside


def depth_consistent(depth_map: np.ndarray, pos: np.ndarray, z: np.ndarray, tol: float) -> np.ndarray:
    """Occlusion test: the map's depth at `pos` (nearest pixel) equals z within tol * min."""
    d, inside = _nearest(depth_map, pos, 0.0)
    ok = inside & (d > 0) & np.isfinite(z) & (z > 0)
    return ok & (np.abs(d - z) < tol * np.minimum(d, np.where(ok, z, 1.0)))


def pose_distance(a: Camera, b: Camera) -> float:
    """Camera-pose distance used to sort neighbours: centre distance (m) + rotation angle (rad)."""
    cosang = (np.trace(a.R @ b.R.T) - 1) / 2
    return float(np.linalg.norm(a.center - b.center) + math.acos(np.clip(cosang, -1, 1)))


def select_neighbours(ref: ViewGeom, others: list[ViewGeom], opts: DecomposeOptions) -> list[tuple[str, float]]:
    """N_k (§4.3.1): render M1_k in the other views (project its points), depth overlap test
    (difference < 0.05 min(depth)) inside beta; keep views with > 30 % overlap, sort by pose
    distance, top six. Returns [(name, overlap fraction)]."""
    sel = ref.mask & (ref.D1 > 0)
    n = int(sel.sum())
    if n == 0:
        return []
    out = []
    for o in others:
        if o.name == ref.name:
            continue
        pos, z = project(o.camera, ref.X1[sel])
        ok = depth_consistent(np.where(o.mask, o.D1, 0.0), pos, z, opts.overlap_tol)
        frac = ok.mean()
        if frac > opts.min_overlap:
            out.append((o.name, float(frac), pose_distance(ref.camera, o.camera)))
    out.sort(key=lambda t: t[2])
    return [(nm, fr) for nm, fr, _ in out[:opts.max_neighbours]]


def _sample_np(img: np.ndarray, pos: np.ndarray) -> np.ndarray:
    import cv2

    p = np.nan_to_num(pos, nan=-10).astype(np.float32)
    return cv2.remap(img.astype(np.float32), p[..., 0], p[..., 1], cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)


def surface_flow(ref: ViewGeom, nb: ViewGeom, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """w_k'(u, M0): positions (H, W, 2) of ref's surface points in nb, and where they are visible."""
    pos, z = project(nb.camera, ref.X0)
    return pos, depth_consistent(nb.depth, pos, z, tol)


def init_layers(ref: ViewGeom, nbs: list[ViewGeom], opts: DecomposeOptions,
                mirror: bool = False) -> tuple[np.ndarray, dict]:
    """§4.3.1 initialisation: R = I - I0 with I0 = min over k and the neighbours of
    I_k'(F_k'(w_k'(u, M0))) (Eq. 6), F the ARAP grid warp of Eq. 5. Mirrors: I0 = 0, R = I."""
    from .grid_warp import apply_warp, solve_grid_warp

    I = ref.image
    info: dict = {"warp_energy": {}}
    if mirror:
        return np.where(ref.mask[..., None], I, 0.0), info
    stack = [I]
    H, W = I.shape[:2]
    for nb in nbs:
        pos, vis = surface_flow(ref, nb, opts.visibility_tol)
        if opts.use_warp and vis.sum() > 100:
            gx, gy = opts.grid
            offs, energies = solve_grid_warp(I, nb.image, pos, vis, gx=gx, gy=gy, w_r=opts.w_r,
                                             w_a=opts.w_a, iterations=opts.gn_iterations)
            info["warp_energy"][nb.name] = energies
            pos = apply_warp(np.nan_to_num(pos, nan=-10), offs, nb.camera.width, nb.camera.height)
        s = _sample_np(nb.image, pos)
        stack.append(np.where(vis[..., None] & ref.mask[..., None], s, np.inf))
    I0 = np.min(np.stack(stack), axis=0)  # Eq. 6
    R = np.where(ref.mask[..., None], np.clip(I - I0, 0, None), 0.0)  # I1 = I - I0
    return R, info


@dataclass
class DataTerm:
    """Eq. 8 at one neighbour: its pixels q (in its beta), target colours I_k'(q), positions a_q
    (surface layer) and b_q (reflection layer) in the reference view, all valid."""

    name: str
    target: np.ndarray  # (N, 3)
    a: np.ndarray  # (N, 2)
    b: np.ndarray  # (N, 2)
    X1: np.ndarray  # (N, 3) mirror-world points of q (for the (R, T) step)


def build_data_terms(ref: ViewGeom, nbs: list[ViewGeom], opts: DecomposeOptions) -> list[DataTerm]:
    out = []
    sat_ref = np.any(ref.image >= opts.saturation, axis=2)
    mask_ok = ref.mask & ~sat_ref
    for nb in nbs:
        q = nb.mask & (nb.D1 > 0) & ~np.any(nb.image >= opts.saturation, axis=2)
        a, za = project(ref.camera, nb.X0[q])
        b, zb = project(ref.camera, nb.X1[q])
        ok = depth_consistent(ref.depth, a, za, opts.visibility_tol)
        ok &= depth_consistent(np.where(mask_ok, ref.D1, 0.0), b, zb, opts.visibility_tol)
        ok &= _nearest(mask_ok, a, False)[0]
        if ok.sum() < 10:
            continue
        out.append(DataTerm(nb.name, nb.image[q][ok], a[ok], b[ok], nb.X1[q][ok]))
    return out


def _grid(pos, W, H):
    import torch
    g = torch.empty_like(pos)
    g[:, 0] = 2 * pos[:, 0] / (W - 1) - 1
    g[:, 1] = 2 * pos[:, 1] / (H - 1) - 1
    return g.view(1, 1, -1, 2)


def _gs(img, pos, W, H):
    """Bilinear samples (N, 3) of a (1, 3, H, W) tensor at (N, 2) pixel positions."""
    import torch.nn.functional as F
    return F.grid_sample(img, _grid(pos, W, H), mode="bilinear", padding_mode="border",
                         align_corners=True)[0, :, 0].T


def _rodrigues(w):
    import torch
    th = torch.sqrt((w * w).sum() + 1e-12)
    k = w / th
    Kx = torch.zeros(3, 3, dtype=w.dtype)
    Kx[0, 1], Kx[0, 2], Kx[1, 0] = -k[2], k[1], k[2]
    Kx[1, 2], Kx[2, 0], Kx[2, 1] = -k[0], -k[1], k[0]
    return torch.eye(3, dtype=w.dtype) + torch.sin(th) * Kx + (1 - torch.cos(th)) * Kx @ Kx


class Problem:
    """Eq. 7 for one view: E_d + lambda_s E_s + lambda_p E_p + lambda_mv E_mv over R = beta I1
    (I0 = I - R) and the rigid transform (R, T) of M1."""

    def __init__(self, ref: ViewGeom, terms: list[DataTerm], opts: DecomposeOptions):
        import torch

        self.torch = torch
        torch.set_num_threads(1)  # one worker per view: the runner parallelises over views
        self.ref, self.terms, self.opts = ref, terms, opts
        H, W = ref.image.shape[:2]
        self.H, self.W = H, W
        self.I = torch.tensor(ref.image.transpose(2, 0, 1)[None], dtype=torch.float64)
        self.mask = torch.tensor(ref.mask[None, None], dtype=torch.float64)
        self.tq = [(torch.tensor(t.target), torch.tensor(t.a), torch.tensor(t.b),
                    torch.tensor(t.X1)) for t in terms]
        cam = ref.camera
        self.K = torch.tensor(cam.K)
        self.Rc = torch.tensor(cam.R)
        self.tc = torch.tensor(cam.t)
        x1 = ref.X1[ref.mask & (ref.D1 > 0)]
        self.centre = torch.tensor(x1.mean(0) if len(x1) else np.zeros(3))
        self.pose = torch.zeros(6, dtype=torch.float64)  # axis-angle, translation of M1
        self.target0 = None  # aggregated I~0 (Eq. 12), tensor or None
        self.target1 = None  # aggregated I~1 (Eq. 13, as R~)
        self.lambda_mv = 0.0

    def b_positions(self, pose, i):
        """b_q with M1 moved by (R, T): the point of M1_k rendered at q is T^-1 applied to q's
        mirror-world point (linearisation: M1_k is locally the mirrored scene)."""
        torch = self.torch
        X = self.tq[i][3]
        Rm = _rodrigues(pose[:3]) if float(pose[:3].abs().sum()) > 0 or pose.requires_grad else \
            torch.eye(3, dtype=torch.float64)
        Xm = (X - self.centre - pose[3:]) @ Rm + self.centre  # R^T (X - c - T) + c
        cam = Xm @ self.Rc.T + self.tc
        uv = cam @ self.K.T
        return uv[:, :2] / uv[:, 2:3]

    def energy(self, Rimg, pose, parts: bool = False):
        torch = self.torch
        I0 = self.I - Rimg
        Ed = torch.zeros((), dtype=torch.float64)
        for i, (tgt, a, _b, _x) in enumerate(self.tq):
            b = self.b_positions(pose, i)
            pred = _gs(I0, a, self.W, self.H) + _gs(Rimg, b, self.W, self.H)  # Eq. 8
            Ed = Ed + ((pred - tgt) ** 2).sum()
        Es = torch.zeros((), dtype=torch.float64)
        for L in (I0, Rimg):  # Eq. 9, image part: e^{-|grad|} |grad|^2 (weights held fixed)
            for dim in (2, 3):
                g = torch.diff(L, dim=dim)
                m = torch.minimum(torch.narrow(self.mask, dim, 0, g.shape[dim]),
                                  torch.narrow(self.mask, dim, 1, g.shape[dim]))
                w = torch.exp(-g.detach().abs().sum(1, keepdim=True))
                Es = Es + (m * w * g ** 2).sum()
        Ep = ((I0 * self.mask) ** 2).sum() + ((Rimg * self.mask) ** 2).sum()  # Eq. 10
        Emv = torch.zeros((), dtype=torch.float64)
        if self.lambda_mv > 0 and self.target0 is not None:  # Eq. 11
            Emv = (((I0 - self.target0) * self.mask) ** 2).sum() + \
                (((Rimg - self.target1) * self.mask) ** 2).sum()
        o = self.opts
        E = Ed + o.lambda_s * Es + o.lambda_p * Ep + self.lambda_mv * Emv
        if parts:
            return E, {"E_d": float(Ed), "E_s": float(Es), "E_p": float(Ep), "E_mv": float(Emv)}
        return E

    def image_step(self, R0: np.ndarray, history: list) -> np.ndarray:
        """Minimise Eq. 7 over R with the geometry fixed: L-BFGS-B with the box of Eq. 7."""
        from scipy.optimize import minimize
        torch = self.torch
        m = self.ref.mask
        idx = np.nonzero(np.broadcast_to(m[None], (3,) + m.shape).reshape(-1))[0]
        I = self.ref.image.transpose(2, 0, 1).reshape(-1)
        # 0 <= R (I1 >= 0); R <= I (I0 >= 0); R <= beta (I1 <= 1): beta folded by the caller
        hi = np.minimum(I[idx], self.r_max)
        full = torch.tensor(np.asarray(R0, np.float64).transpose(2, 0, 1).reshape(-1))

        def fun(x):
            v = full.clone()
            v[idx] = torch.tensor(x)
            v.requires_grad_(True)
            E = self.energy(v.view(1, 3, self.H, self.W), self.pose)
            E.backward()
            return float(E.detach()), v.grad[idx].numpy().copy()

        x0 = np.clip(full.numpy()[idx], 0, hi)
        res = minimize(fun, x0, jac=True, method="L-BFGS-B", bounds=list(zip(np.zeros_like(hi), hi)),
                       options={"maxiter": self.opts.image_iterations})
        out = full.numpy().copy()
        out[idx] = res.x
        R = out.reshape(3, self.H, self.W).transpose(1, 2, 0)
        history.append({"step": "image", "energy": float(res.fun), "iterations": int(res.nit)})
        return R

    def pose_step(self, R: np.ndarray, history: list) -> None:
        """Minimise Eq. 7 over the rigid transform (R, T) of M1 with the images fixed."""
        torch = self.torch
        Rimg = torch.tensor(R.transpose(2, 0, 1)[None])
        pose = self.pose.clone().requires_grad_(True)
        optim = torch.optim.LBFGS([pose], lr=0.5, max_iter=self.opts.pose_iterations,
                                  line_search_fn="strong_wolfe")

        def closure():
            optim.zero_grad()
            E = self.energy(Rimg, pose)
            E.backward()
            return E

        E0 = float(self.energy(Rimg, self.pose))
        optim.step(closure)
        E1 = float(self.energy(Rimg, pose.detach()))
        if E1 < E0:
            self.pose = pose.detach()
        history.append({"step": "pose", "energy": min(E0, E1), "pose": self.pose.tolist()})


def aggregate(ref: ViewGeom, R: np.ndarray, nbs: list[ViewGeom], nb_R: dict[str, np.ndarray],
              opts: DecomposeOptions) -> tuple[np.ndarray, np.ndarray]:
    """§4.3.3: I~0 = median over k and N_k of I0_k'(w_k'(u, M0)) (Eq. 12); R~ by the composition
    rule (Eq. 13): I - I~0 where I - I~0 - R < 0, else R. Holes (no neighbour) keep I0."""
    I = ref.image
    I0 = I - R
    stack = [I0]
    for nb in nbs:
        if nb.name not in nb_R:
            continue
        pos, vis = surface_flow(ref, nb, opts.visibility_tol)
        s = _sample_np(nb.image - nb_R[nb.name], pos)
        stack.append(np.where(vis[..., None], s, np.nan))
    T0 = np.nanmedian(np.stack(stack), axis=0)  # Eq. 12
    T0 = np.where(ref.mask[..., None], T0, I)
    T1 = np.where(I - T0 - R < 0, I - T0, R)  # Eq. 13
    return T0, np.where(ref.mask[..., None], np.clip(T1, 0, None), 0.0)


def crop_view(g: ViewGeom, margin: int = 2) -> tuple[ViewGeom, tuple[int, int, int, int]]:
    """The view cropped to its mask's bounding box (+ margin); the camera's principal point is
    shifted so that projections stay exact. Returns the crop and (y0, y1, x0, x1)."""
    ys, xs = np.nonzero(g.mask)
    H, W = g.mask.shape
    y0, y1 = max(0, ys.min() - margin), min(H, ys.max() + 1 + margin)
    x0, x1 = max(0, xs.min() - margin), min(W, xs.max() + 1 + margin)
    K = g.camera.K.copy()
    K[0, 2] -= x0
    K[1, 2] -= y0
    cam = Camera(K, g.camera.cam_from_world, x1 - x0, y1 - y0)
    s = np.s_[y0:y1, x0:x1]
    return ViewGeom(g.name, cam, g.image[s], g.depth[s], g.mask[s], g.X0[s], g.X1[s], g.D1[s]), \
        (y0, y1, x0, x1)


def decompose(ref: ViewGeom, nbs: list[ViewGeom], opts: DecomposeOptions, *, beta: float = 1.0,
              mirror: bool = False, aggregate_from: dict[str, np.ndarray] | None = None,
              R_init: np.ndarray | None = None, stages: tuple[str, ...] = ("init", "opt")) -> dict:
    """`_decompose` on the bounding box of the reflector mask (same result, less work)."""
    if not ref.mask.any():
        return {"R": np.zeros_like(ref.image), "history": [], "pose": [0.0] * 6, "neighbours": []}
    crop, (y0, y1, x0, x1) = crop_view(ref)
    res = _decompose(crop, nbs, opts, beta=beta, mirror=mirror, aggregate_from=aggregate_from,
                     R_init=None if R_init is None else R_init[y0:y1, x0:x1], stages=stages)
    R = np.zeros_like(ref.image)
    R[y0:y1, x0:x1] = res["R"]
    res["R"] = R
    return res


def _decompose(ref: ViewGeom, nbs: list[ViewGeom], opts: DecomposeOptions, *, beta: float = 1.0,
               mirror: bool = False, aggregate_from: dict[str, np.ndarray] | None = None,
               R_init: np.ndarray | None = None, stages: tuple[str, ...] = ("init", "opt")) -> dict:
    """One per-view decomposition pass. Returns {"R": (H, W, 3) reflection component beta*I1,
    "history": energy log, "pose": (6,) (R, T) of M1, "neighbours": names used}.

    With `aggregate_from` (neighbour name -> its R from the previous pass) this is the second pass
    of §4.3.3 with lambda_mv = 0.05 (Eqs. 11-13)."""
    if not 0 < beta <= 1:
        raise ValueError(f"beta must be in (0, 1], got {beta}")
    hist: list = []
    if mirror:  # special case (§4.3.3): textureless mirror, I1 = I, I0 = 0
        R, _ = init_layers(ref, nbs, opts, mirror=True)
        return {"R": R, "history": hist, "pose": [0.0] * 6, "neighbours": [n.name for n in nbs]}
    if R_init is None:
        R, info = init_layers(ref, nbs, opts)
        hist.append({"step": "init", "warp_energy": info["warp_energy"]})
    else:
        R = R_init
    if "opt" not in stages:
        return {"R": R, "history": hist, "pose": [0.0] * 6, "neighbours": [n.name for n in nbs]}
    terms = build_data_terms(ref, nbs, opts)
    prob = Problem(ref, terms, opts)
    prob.r_max = beta
    if aggregate_from is not None:
        import torch
        T0, T1 = aggregate(ref, R, nbs, aggregate_from, opts)
        prob.target0 = torch.tensor(T0.transpose(2, 0, 1)[None])
        prob.target1 = torch.tensor(T1.transpose(2, 0, 1)[None])
        prob.lambda_mv = opts.lambda_mv
    E, parts = prob.energy(__import__("torch").tensor(R.transpose(2, 0, 1)[None]), prob.pose, parts=True)
    hist.append({"step": "start", "energy": float(E), **parts})
    for _ in range(opts.outer_iterations):  # alternate image / geometry variables (§4.3.2)
        R = prob.image_step(R, hist)
        if opts.optimise_pose and terms:
            prob.pose_step(R, hist)
    import torch
    E, parts = prob.energy(torch.tensor(R.transpose(2, 0, 1)[None]), prob.pose, parts=True)
    hist.append({"step": "end", "energy": float(E), **parts})
    return {"R": R, "history": hist, "pose": prob.pose.tolist(),
            "neighbours": [t.name for t in terms]}
