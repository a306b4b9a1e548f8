"""Two-layer reflection decomposition of one view and one planar reflector (Xu et al. §4.3,
Eqs. 3, 6-13).

Variables. Inside the reflector's beta support we optimise the reflection component
R = beta * I1 (the paper's beta is a binary mask, so its I1 is our R); Eq. 3 is enforced as a hard
constraint, I0 = I - R, and the box constraint of Eq. 7 (I0, I1 in [0, 1]) becomes
0 <= R <= min(I, beta). The stored I1 is R / beta (beta = the reflectance, 1 when unknown).

Flows. `ViewGeom` (decompose_terms.py) holds, per view, the surface points X0 (from the refined depth: M0) and the
mirror-world points X1 (the planar-reflection geometry: M1). w_k'(u, M) = project_k'(X(u)).
The data term Eq. 8 is evaluated at the neighbour's pixels q: the surface layer of view k seen at
q comes from a_q = project_k(X0_k'(q)) and the reflection layer from b_q = project_k(X1_k'(q)) —
the inverse flows w^-1 obtained by "rendering" M0 / M1 at k' (exact for planar reflectors, since
M1 is the mirrored scene). Sampling is bilinear; as a sparse interpolation matrix it makes E_d
linear in the images, so for fixed geometry Eq. 7 is a sparse linear least-squares problem in R
(image step: normal equations, block Jacobi-PCG, active set for the box). The geometry step
(geometry_step.py) refines the rigid transform (R, T) of M1 and, optionally, per-vertex depth
offsets of M0 and M1 (Eq. 7's mesh variables, Eq. 9's cotangent Laplacian). numpy / scipy only
(no torch: its import alone cost seconds per worker).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..config import Options, param
from ..errors import ConfigError
from ..scene import Camera
from .decompose_terms import (DataTerm, ViewGeom, _nearest, _sample_np, bilinear_matrix,
                              depth_consistent, nanmedian0, pose_distance, project, rodrigues,
                              sample_bilinear)


@dataclass(frozen=True)
class DecomposeOptions(Options):
    """Xu et al. §4.3 parameters; the `reflection` stage embeds them as [reflection.decompose]."""

    max_neighbours: int = param(6, "N_k size (§4.3.1: top six)", min=1, max=30)
    min_neighbours: int = param(1, "with fewer neighbours the decomposition is discarded (not "
                                "for mirrors)", min=1, max=30)
    min_overlap: float = param(0.3, "neighbour depth-overlap fraction (§4.3.1: > 30 %)",
                               min=0.0, max=1.0)
    overlap_tol: float = param(0.05, "depth-overlap tolerance x min depth (§4.3.1: 0.05)",
                               min=1e-4, max=1.0)
    grid: tuple[int, int] = param((40, 30), "ARAP warp grid cells across, down (§4.3.1: 40 x 30)",
                                  min=1, max=400)
    w_r: float = param(1.2, "Eq. 5 offset regulariser weight", min=0.0, max=1e4)
    w_a: float = param(0.5, "Eq. 5 ARAP weight", min=0.0, max=1e4)
    gn_iterations: int = param(5, "Gauss-Newton iterations of the grid warp (§4.3.1: 5)",
                               min=0, max=100)
    use_warp: bool = param(True, "refine the initial flow by the ARAP grid warp (Eqs. 4-5)")
    lambda_s: float = param(0.04, "Eq. 7 smoothness weight", min=0.0, max=1e4)
    lambda_p: float = param(0.0, "Eq. 7 prior weight. The paper's 0.01 pulls R = beta I1 towards "
                            "0 when a view has only 2-3 partial neighbours (docs/REFLECTION.md)",
                            min=0.0, max=1e4)
    lambda_mv: float = param(0.05, "Eq. 7 multi-view weight in the second pass (§4.3.3)",
                             min=0.0, max=1e4)
    multiview: bool = param(False, "second pass with multi-view consistency (§4.3.3, Eqs. 11-13). "
                            "Off by default: it decomposes every neighbour too (~7x the time)")
    outer_iterations: int = param(2, "alternations of image and geometry steps per pass "
                                  "(§4.3.3: usually two)", min=0, max=50)
    cg_iterations: int = param(30, "preconditioned CG iterations of an image-step solve (§6.1: "
                               "30 CG iterations on I before the geometry; the image step is a "
                               "sparse linear least-squares problem)", min=1, max=10000)
    resolve_iterations: int = param(15, "CG iterations of each warm-started active-set re-solve",
                                    min=1, max=10000)
    matrix_precision: str = param("float32", "storage of the image step's matrix H: float32 "
                                  "rounds its entries (~6e-8 relative) and halves the bytes the "
                                  "CG's mat-vecs stream for them; the iterates stay float64",
                                  choices=("float32", "float64"))
    optimise_pose: bool = param(True, "refine the rigid transform (R, T) of M1 (Eq. 7)")
    pose_iterations: int = param(5, "Gauss-Newton iterations per (R, T) step", min=0, max=1000)
    pose_samples: int = param(20000, "data points of the (R, T) steps (deterministic stride)",
                              min=100, max=10**8)
    kernels: str = param("numba", "numba = the image step's CG in one numba kernel and the "
                         "ARAP warp's normal equations summed per grid cell; reference = "
                         "scipy / numpy mat-vecs and the warp's Jacobian formed (the same "
                         "iterates up to rounding, so it is not part of the stage's "
                         "fingerprint; `ibr bench speed` times both)",
                         choices=("numba", "reference"), affects_output=False)
    saturation: float = param(0.98, "highlights: pixels with a channel at or above this are left "
                              "out of E_d", min=0.5, max=1.0)
    visibility_tol: float = param(0.05, "relative depth tolerance of the occlusion tests",
                                  min=1e-4, max=1.0)
    lambda_scene: float = param(2.0, "weight of the reflected-scene colour prior in the image "
                                "step (our addition: R = beta I1 initialised and regularised by "
                                "the colour other views see directly, reflection_prior.py); 0 = "
                                "no prior", min=0.0, max=1e4)
    optimise_m1_vertices: bool = param(False, "optimise M1's vertices (Eq. 7 variables M^1 with "
                                       "Eq. 9's cotangent Laplacian): relative depth offsets of a "
                                       "control grid along the view's rays. Off by default: no "
                                       "PSNR gain on the bench (docs/REFLECTION.md)")
    optimise_m0_vertices: bool = param(False, "optimise M0's vertices the same way, through the "
                                       "surface positions of E_d (docs/REFLECTION.md)")
    lambda_lap: float = param(0.04, "weight of E_lap = delta^T L_cot delta for M0's and M1's "
                              "offsets (the paper's lambda_s = 0.04 for E_s)", min=0.0, max=1e6)
    m1_cell_640: int = param(16, "M0 / M1 control-grid spacing in pixels at 640 px width, scaled "
                             "with the view's width (the 40x30 warp grid's cell)", min=2, max=512)
    m1_iterations: int = param(5, "LM iterations per M0 / M1 vertex step", min=0, max=1000)
    m1_samples: int = param(60000, "data points of the vertex steps (deterministic stride)",
                            min=100, max=10**8)
    m1_max_offset: float = param(0.1, "bound of the vertex offsets |delta| (relative depth)",
                                 min=0.0, max=1.0)

    def check(self, prefix: str) -> None:
        if self.min_neighbours > self.max_neighbours:
            raise ConfigError(prefix + "min_neighbours", "must be <= max_neighbours")

    def m1_cell(self, width: int) -> int:
        """The control-grid spacing in pixels of a view `width` pixels wide."""
        return max(2, round(self.m1_cell_640 * width / 640))


def select_neighbours(ref: ViewGeom, others, opts: DecomposeOptions,
                      presorted: bool = False) -> list[tuple[str, float]]:
    """N_k (§4.3.1): render M1_k in the other views (project its points), depth overlap test
    (difference < 0.05 min(depth)) inside beta; keep views with > 30 % overlap, sort by pose
    distance, top six. Returns [(name, overlap fraction)].

    `others` (footprints: name, camera, mask, D1) may be any iterable. `presorted`: it comes
    sorted by pose distance from ref, stably (`by_pose_distance`); the search then stops at the
    sixth view kept, and a lazy iterable builds only the footprints it reaches: the same answer
    at a cost that does not grow with the number of views."""
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
            if presorted and len(out) == opts.max_neighbours:
                break
    out.sort(key=lambda t: t[2])
    return [(nm, fr) for nm, fr, _ in out[:opts.max_neighbours]]


def by_pose_distance(camera, names: list[str], cameras: dict) -> list[str]:
    """`names` sorted by pose distance from `camera`, ties in their given order."""
    return sorted(names, key=lambda n: pose_distance(camera, cameras[n]))


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
                                             w_a=opts.w_a, iterations=opts.gn_iterations,
                                             reference=opts.kernels == "reference")
            info["warp_energy"][nb.name] = energies
            pos = apply_warp(np.nan_to_num(pos, nan=-10), offs, nb.camera.width, nb.camera.height)
        s = _sample_np(nb.image, pos)
        stack.append(np.where(vis[..., None] & ref.mask[..., None], s, np.inf))
    I0 = np.min(np.stack(stack), axis=0)  # Eq. 6
    R = np.where(ref.mask[..., None], np.clip(I - I0, 0, None), 0.0)  # I1 = I - I0
    return R, info


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
        out.append(DataTerm(nb.name, nb.image[q][ok], a[ok], b[ok], nb.X1[q][ok], nb.X0[q][ok]))
    return out


class Problem:
    """Eq. 7 for one view: E_d + lambda_s E_s + lambda_p E_p + lambda_mv E_mv over R = beta I1
    (I0 = I - R) inside the mask and the rigid transform (R, T) of M1.

    For fixed geometry every term is quadratic in R (bilinear sampling is linear in the image;
    the edge-aware weights of Eq. 9 are held fixed within one image step), so the image step is
    a sparse linear least-squares problem: its normal equations H x = g (one matrix, three
    right-hand sides = the colour channels) are solved by Jacobi-preconditioned CG
    (block_pcg.py; Xu et al. §6.1 also use CG, in Ceres), and the box of Eq. 7 is enforced by
    an active-set loop. The geometry step (6 parameters) is Gauss-Newton / Levenberg-Marquardt
    on the data residuals (scipy least_squares)."""

    def __init__(self, ref: ViewGeom, terms: list[DataTerm], opts: DecomposeOptions):
        import scipy.sparse as sp
        self.ref, self.terms, self.opts = ref, terms, opts
        H, W = ref.image.shape[:2]
        self.H, self.W = H, W
        self.I = np.asarray(ref.image, np.float64)
        m = ref.mask
        self.m = m
        self.P = int(m.sum())
        self.flat = np.flatnonzero(m.reshape(-1))
        self.Im = self.I.reshape(-1, 3)[self.flat]  # (P, 3)
        idx = -np.ones(H * W, np.int64)
        idx[self.flat] = np.arange(self.P)
        self.idx = idx.reshape(H, W)
        # finite differences between 4-neighbours that are both in the mask (Eq. 9)
        ea = [(self.idx[:, :-1], self.idx[:, 1:]), (self.idx[:-1, :], self.idx[1:, :])]
        i0 = np.concatenate([a[(a >= 0) & (b >= 0)] for a, b in ea])
        i1 = np.concatenate([b[(a >= 0) & (b >= 0)] for a, b in ea])
        E = len(i0)
        self.D = sp.csr_matrix((np.r_[-np.ones(E), np.ones(E)], (np.r_[np.arange(E), np.arange(E)],
                                                                    np.r_[i0, i1])), shape=(E, self.P))
        # E_d: residual = A x - r, A = S_b - S_a restricted to mask pixels, r = tgt - S_a I
        As, rs, self.Sa_I, self.tgts = [], [], [], []
        for t in terms:
            Sa = bilinear_matrix(t.a, W, H)
            Sb = bilinear_matrix(t.b, W, H)
            SaI = Sa @ self.I.reshape(-1, 3)
            As.append((Sb[:, self.flat] - Sa[:, self.flat]).tocsr())
            rs.append(t.target - SaI)
            self.Sa_I.append(SaI)
            self.tgts.append(t.target)
        self.A = sp.vstack(As).tocsr() if As else sp.csr_matrix((0, self.P))
        self.r = np.concatenate(rs) if rs else np.zeros((0, 3))
        x1 = ref.X1[m & (ref.D1 > 0)]
        self.centre = x1.mean(0) if len(x1) else np.zeros(3)
        self.pose = np.zeros(6)
        self.target0 = None  # aggregated I~0 (Eq. 12), (H, W, 3) or None
        self.target1 = None  # aggregated R~ (Eq. 13)
        self.lambda_mv = 0.0
        self.r_max = 1.0
        self.prior = None  # (P, 3) beta * reflected-scene colour, NaN = unknown
        self.offsets: dict = {}  # layer "a" (M0) / "b" (M1) -> geometry_step.LayerOffsets

    # -- helpers ---------------------------------------------------------------------------------
    def _x(self, R: np.ndarray) -> np.ndarray:
        return np.asarray(R, np.float64).reshape(-1, 3)[self.flat]

    def _R(self, x: np.ndarray) -> np.ndarray:
        out = np.zeros((self.H * self.W, 3))
        out[self.flat] = x
        return out.reshape(self.H, self.W, 3)

    def _weights(self, x):
        """Eq. 9 edge-aware weights e^{-|grad L|} of I0 and R (summed over channels)."""
        w0 = np.exp(-np.abs(self.D @ (self.Im - x)).sum(1))
        w1 = np.exp(-np.abs(self.D @ x).sum(1))
        return w0, w1

    def _shift(self, layer, i, sub):
        off = self.offsets.get(layer)
        return 0.0 if off is None else off.shift(i, sub)

    def positions(self, layer, i, sub=None, offsets=True):
        """a_q (layer "a") or b_q (layer "b") at the current geometry."""
        if layer == "b":
            return self.b_positions(self.pose, i, sub, offsets)
        a = self.terms[i].a if sub is None else self.terms[i].a[sub]
        return a + self._shift("a", i, sub) if offsets else a  # M0 offsets (geometry_step.py)

    def b_positions(self, pose, i, sub=None, offsets=True):
        """b_q with M1 moved by (R, T): R^T (X - c - T) + c projected into the reference (+ the
        first-order shift of M1's vertex offsets, geometry_step.py)."""
        X = self.terms[i].X1 if sub is None else self.terms[i].X1[sub]
        Rm = rodrigues(pose[:3])
        Xm = (X - self.centre - pose[3:]) @ Rm + self.centre
        cam = self.ref.camera
        c = Xm @ cam.R.T + cam.t
        uv = c @ cam.K.T
        return uv[:, :2] / uv[:, 2:3] + (self._shift("b", i, sub) if offsets else 0.0)

    def data_residual(self, R, pose):
        """E_d residuals (N, 3) for the images R and the pose of M1."""
        if not self.terms:
            return np.zeros((0, 3))
        x = self._x(R)
        if not np.any(pose) and not self.offsets:
            return self.A @ x - self.r
        I0, Rm = self.I - self._R(x), self._R(x)  # Eq. 8: I0(a_q) + R(b_q) - I_k'(q)
        return np.concatenate([sample_bilinear(I0, self.positions("a", i))
                               + sample_bilinear(Rm, self.b_positions(pose, i)) - t.target
                               for i, t in enumerate(self.terms)])

    def energy(self, R, pose=None, parts: bool = False):
        pose = self.pose if pose is None else pose
        x = self._x(R)
        Ed = float((self.data_residual(R, pose) ** 2).sum())
        w0, w1 = self._weights(x)
        Es = float((w0[:, None] * (self.D @ (self.Im - x)) ** 2).sum()
                   + (w1[:, None] * (self.D @ x) ** 2).sum())
        Ep = float(((self.Im - x) ** 2).sum() + (x ** 2).sum())
        Emv = 0.0
        if self.lambda_mv > 0 and self.target0 is not None:
            t0, t1 = self._x(self.target0), self._x(self.target1)
            Emv = float(((self.Im - x - t0) ** 2).sum() + ((x - t1) ** 2).sum())
        o = self.opts
        Ec = 0.0
        if self.prior is not None:
            k = np.all(np.isfinite(self.prior), axis=1)[:, None]
            Ec = float(((x - np.where(k, self.prior, 0.0)) ** 2 * k).sum())
        Elap = {k: v.e_lap() for k, v in self.offsets.items()}  # Eq. 9 mesh part
        E = Ed + o.lambda_s * Es + o.lambda_p * Ep + self.lambda_mv * Emv + o.lambda_scene * Ec
        E += sum(self.offsets[k].lam * v for k, v in Elap.items())
        if parts:
            return E, {"E_d": Ed, "E_s": Es, "E_p": Ep, "E_mv": Emv, "E_scene": Ec,
                       "E_lap": Elap.get("b", 0.0), "E_lap_m0": Elap.get("a", 0.0)}
        return E

    # -- image step ------------------------------------------------------------------------------
    def image_step(self, R0: np.ndarray, history: list) -> np.ndarray:
        """Minimise Eq. 7 over R with the geometry fixed: sparse normal equations, box by an
        active-set loop (variables at a violated bound are fixed there and the rest re-solved)."""
        import scipy.sparse as sp
        o = self.opts
        x0 = self._x(R0)
        if np.any(self.pose) or self.offsets:  # sampling at the current geometry
            As, rs = [], []
            for i, t in enumerate(self.terms):
                Sa = bilinear_matrix(self.positions("a", i), self.W, self.H)
                Sb = bilinear_matrix(self.b_positions(self.pose, i), self.W, self.H)[:, self.flat]
                As.append(Sb - Sa[:, self.flat])
                rs.append(t.target - Sa @ self.I.reshape(-1, 3))
            A, r = sp.vstack(As).tocsr(), np.concatenate(rs)
        else:
            A, r = self.A, self.r
        from .block_pcg import block_pcg, block_pcg_reference  # numba: lazily
        w0, w1 = self._weights(x0)
        D = self.D
        lam_mv = self.lambda_mv if self.target0 is not None else 0.0
        # H = A^T A + lambda_s D^T diag(w0 + w1) D + diag(2 lambda_p + 2 lambda_mv [+ prior]),
        # formed once: the active-set re-solves share it
        diag = np.full(self.P, 2 * o.lambda_p + 2 * lam_mv)
        g = A.T @ r + o.lambda_s * (D.T @ (w0[:, None] * (D @ self.Im))) + o.lambda_p * self.Im
        if lam_mv > 0:
            g = g + lam_mv * (self.Im - self._x(self.target0) + self._x(self.target1))
        hi = np.minimum(self.Im, self.r_max)
        if self.prior is not None and o.lambda_scene > 0:
            # the prior is per channel but its mask is (almost) channel-independent: use the
            # pixels known in all channels so that one matrix serves the three channels
            k = np.all(np.isfinite(self.prior), axis=1)
            diag = diag + o.lambda_scene * k
            g = g + o.lambda_scene * np.where(k[:, None], np.nan_to_num(self.prior), 0.0)
        Hm = normal_matrix(A, D, o.lambda_s * (w0 + w1), diag)
        if o.matrix_precision == "float32":  # both solvers read H in its own precision
            Hm = Hm.astype(np.float32)
        solve = block_pcg if o.kernels == "numba" else block_pcg_reference
        x = np.clip(x0, 0, hi)
        free = np.ones_like(x, bool)
        cg = 0
        for it in range(3):  # active set: variables at a violated bound are fixed there
            # re-solves start from the previous solution: fewer iterations (speed)
            info: dict = {}
            x = solve(Hm, g, x, free,
                      iterations=o.cg_iterations if it == 0 else o.resolve_iterations, info=info)
            cg += info["iterations"]
            viol = ((x < 0) | (x > hi)) & free
            if not viol.any():
                break
            free &= ~viol
            x = np.clip(x, 0, hi)
        x = np.clip(x, 0, hi)
        R = self._R(x)
        history.append({"step": "image", "energy": float(self.energy(R)), "unknowns": int(x.size),
                        "cg_iterations": cg})
        return R

    # -- geometry step (geometry_step.py) ------------------------------------------------------
    def pose_step(self, R: np.ndarray, history: list) -> None:
        """(R, T) of M1 by Levenberg-Marquardt on E_d, accepted only if the energy drops."""
        from .geometry_step import pose_step
        pose_step(self, R, history)


def normal_matrix(A, D, edge_w: np.ndarray, diag: np.ndarray):
    """H = A^T A + D^T diag(edge_w) D + diag(diag) (CSR, sorted indices) as one product B^T B of
    the stacked rows B = [A; sqrt(edge_w) D; sqrt(diag) I]: the sum of three sparse matrices with
    different patterns cost as much as the products (two scipy additions a step). edge_w (E,) and
    diag (P,) must be >= 0. The same matrix up to rounding (tested)."""
    import scipy.sparse as sp
    P = A.shape[1]
    if D.shape[1] != P or edge_w.shape != (D.shape[0],) or diag.shape != (P,):
        raise ValueError(f"A {A.shape}, D {D.shape}, edge_w {edge_w.shape}, diag {diag.shape}")
    D = sp.csr_matrix(D)
    wD = sp.csr_matrix((D.data * np.repeat(np.sqrt(edge_w), np.diff(D.indptr)), D.indices,
                        D.indptr), shape=D.shape)
    B = sp.vstack([sp.csr_matrix(A), wD, sp.diags(np.sqrt(diag)).tocsr()], format="csr")
    H = (B.T @ B).tocsr()
    H.sort_indices()
    return H


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
    T0 = nanmedian0(np.stack(stack))  # Eq. 12
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
              R_init: np.ndarray | None = None, stages: tuple[str, ...] = ("init", "opt"),
              R_prior: np.ndarray | None = None) -> dict:
    """`_decompose` on the bounding box of the reflector mask (same result, less work)."""
    if not ref.mask.any():
        return {"R": np.zeros_like(ref.image), "history": [], "pose": [0.0] * 6, "neighbours": []}
    crop, (y0, y1, x0, x1) = crop_view(ref)
    res = _decompose(crop, nbs, opts, beta=beta, mirror=mirror, aggregate_from=aggregate_from,
                     R_init=None if R_init is None else R_init[y0:y1, x0:x1], stages=stages,
                     R_prior=None if R_prior is None else R_prior[y0:y1, x0:x1],
                     m1_cell=opts.m1_cell(ref.camera.width))
    R = np.zeros_like(ref.image)
    R[y0:y1, x0:x1] = res["R"]
    res["R"] = R
    for key in ("m0_offset", "m1_offset"):  # relative depth offsets (geometry_step.py)
        if res.get(key) is not None:
            off = np.zeros(ref.mask.shape)
            off[y0:y1, x0:x1] = res[key]
            res[key] = off
    return res


def _decompose(ref: ViewGeom, nbs: list[ViewGeom], opts: DecomposeOptions, *, beta: float = 1.0,
               mirror: bool = False, aggregate_from: dict[str, np.ndarray] | None = None,
               R_init: np.ndarray | None = None, stages: tuple[str, ...] = ("init", "opt"),
               R_prior: np.ndarray | None = None, m1_cell: int | None = None) -> dict:
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
        if R_prior is not None:  # reflected-scene colour where observed (reflection_prior.py)
            k = np.all(np.isfinite(R_prior), axis=2) & ref.mask
            Rp = np.clip(np.nan_to_num(R_prior), 0, np.minimum(ref.image, beta))
            R = np.where(k[..., None], Rp, R)
            hist[-1]["prior_pixels"] = int(k.sum())
    else:
        R = R_init
    if "opt" not in stages:
        return {"R": R, "history": hist, "pose": [0.0] * 6, "neighbours": [n.name for n in nbs]}
    terms = build_data_terms(ref, nbs, opts)
    prob = Problem(ref, terms, opts)
    prob.r_max = beta
    from .geometry_step import build_offsets, layer_depth, vertex_step
    for layer, on in (("a", opts.optimise_m0_vertices), ("b", opts.optimise_m1_vertices)):
        if on and terms:  # M0's / M1's vertices (Eq. 7 variables M^0,1, Eq. 9 mesh part)
            prob.offsets[layer] = build_offsets(ref, terms, {n.name: n.camera.center for n in nbs},
                                                m1_cell or opts.m1_cell(ref.camera.width),
                                                opts.lambda_lap, layer)
    if R_prior is not None:
        prob.prior = np.asarray(R_prior, np.float64).reshape(-1, 3)[prob.flat]
    if aggregate_from is not None:
        T0, T1 = aggregate(ref, R, nbs, aggregate_from, opts)
        prob.target0, prob.target1 = T0, T1
        prob.lambda_mv = opts.lambda_mv
    E, parts = prob.energy(R, parts=True)
    hist.append({"step": "start", "energy": float(E), **parts})
    for _ in range(opts.outer_iterations):  # alternate image / geometry variables (§4.3.2)
        R = prob.image_step(R, hist)
        if opts.optimise_pose and terms:
            prob.pose_step(R, hist)
        for layer in prob.offsets:  # M0 ("a") then M1 ("b")
            vertex_step(prob, R, hist, layer)
    E, parts = prob.energy(R, parts=True)
    hist.append({"step": "end", "energy": float(E), **parts})
    return {"R": R, "history": hist, "pose": prob.pose.tolist(),
            "neighbours": [t.name for t in terms],
            **{f"m{i}_offset": prob.offsets[k].pixel_offsets(ref.mask.shape,
                                                             layer_depth(ref, k) > 0)
               if k in prob.offsets else None for i, k in ((0, "a"), (1, "b"))}}
