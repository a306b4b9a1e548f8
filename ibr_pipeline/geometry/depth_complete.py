"""Depth completion where the global mesh G leaves a view empty (ours, for RGB-only captures).

Xu et al. start from a complete MVS mesh of the room (§4.1); an RGB-only capture's fused mesh
misses what the fusion could not confirm (textureless walls, far background, thin objects), and a
view without depth there renders as hole fill. `complete_depth` fills those pixels in two steps:

1. the view's own multi-view-stereo depth, where it has one (the depth maps G was fused from,
   `global_mesh`), agreeing with nothing else to check it against but already filtered for
   multi-view consistency; its speckles (`speckle_px`: small regions no neighbour continues,
   wrong matches on textureless surfaces) are dropped first;
2. (optional, `planes`) piecewise planes over colour segments: a segment of the image
   (Felzenszwalb & Huttenlocher 2004) whose known depths a single 3-D plane explains takes that
   plane where it has none — the superpixel planar prior of TAPA-MVS (Romanoni & Matteucci 2019)
   for the textureless regions PatchMatch leaves empty (ceiling panels, walls, doors), where the
   membrane below would bend the surface towards whatever the hole's border touches;
3. edge-aware propagation from the pixels with depth (Xu §4.2.2's cost map: colour edges are
   expensive to cross, so a hole takes the depth of the surface it belongs to): the membrane
   (weighted Laplace) interpolation of inverse depth over the hole with the known depths as the
   boundary, link weights exp(-cost) of Eq. 2's geodesic step cost. Unlike Eq. 2's k nearest
   seeds, which switch abruptly between seeds inside a hole hundreds of pixels wide and cut the
   per-view mesh there, it is smooth, reproduces a plane exactly and never extrapolates beyond
   the boundary's depths (a harmonic function takes its extremes on the boundary).

Pixels no seed reaches keep 0. Pure functions: (H, W) arrays in, arrays out.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from ..config import Options, param
from ..scene import Camera
from . import geodesic as geo


def complete_depth(depth: np.ndarray, camera: Camera, image: np.ndarray, mvs_depth: np.ndarray | None = None,
                   cost_edge: float = 15.0, boundary_radius: int = 0, strokes: np.ndarray | None = None,
                   planes: "PlaneOptions | None" = None, speckle_px: int = 0,
                   base_edges: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """(completed depth (H, W) float64, {"mvs", "planes", "interpolated": (H, W) bool}: which
    empty pixels of `depth` (<= 0) each step filled). `mvs_depth` (any size of the same aspect,
    0 = none) is resized to the view with nearest-neighbour sampling; `planes` None = no
    segment-plane step; `base_edges`: `geodesic.colour_edge_map` of `image` without strokes, when
    the caller computed it already."""
    d = np.asarray(depth, dtype=np.float64)
    if d.ndim != 2:
        raise ValueError(f"depth must be (H, W), got {d.shape}")
    h, w = d.shape
    if camera.size != (w, h):
        raise ValueError(f"camera is {camera.width}x{camera.height}, depth {w}x{h}")
    if np.asarray(image).shape[:2] != (h, w):
        raise ValueError(f"image must be {h}x{w}, got {np.asarray(image).shape[:2]}")
    out = np.where(np.isfinite(d) & (d > 0), d, 0.0)
    from_mvs = np.zeros((h, w), bool)
    if mvs_depth is not None:
        m = view_mvs(mvs_depth, w, h, speckle_px)
        from_mvs = (out <= 0) & np.isfinite(m) & (m > 0)
        out[from_mvs] = m[from_mvs]
    from_planes = np.zeros((h, w), bool)
    if planes is not None and (out <= 0).any():
        out, from_planes = segment_planes(out, image, planes)
    holes = out <= 0
    interp = np.zeros((h, w), bool)
    if holes.any() and (~holes).any():
        edges = (geo.colour_edge_map(image, strokes, boundary_radius=boundary_radius)
                 if base_edges is None else geo.with_strokes(base_edges, strokes))
        inv, reached = membrane_fill(np.where(holes, 0.0, 1.0 / np.where(holes, 1.0, out)), holes,
                                     edge_weights(edges, cost_edge))
        interp = holes & reached & (inv > 0)
        out[interp] = 1.0 / inv[interp]
    return out, {"mvs": from_mvs, "planes": from_planes, "interpolated": interp}


@dataclass(frozen=True)
class PlaneOptions(Options):
    """Segment-plane completion (`view_depth.planes`). Pixel counts are given at 320x240 (the
    stage scales them with the pixel count), tolerances relative (scale-free)."""

    segment_scale: float = param(200.0, "Felzenszwalb's k: larger = larger segments", min=1.0,
                                 max=100000.0)
    min_segment_px: int = param(40, "smallest segment, pixels at 320x240 (Felzenszwalb's "
                                "min_size)", min=1, max=100000)
    min_inliers: int = param(20, "known pixels on a segment's plane, at least (pixels at "
                             "320x240)", min=3, max=100000)
    inlier_share: float = param(0.6, "... and at least this share of the segment's known pixels",
                                min=0.0, max=1.0)
    tol_rel: float = param(0.03, "inlier: |1/z - plane| <= tol_rel / z (our MVS depth is noisy at "
                           "2-3 %)", min=0.001, max=0.5)
    hypotheses: int = param(64, "RANSAC samples per segment", min=1, max=10000)
    seed: int = param(0, "seed of the RANSAC samples", min=0, max=2**31 - 1)

    def scaled(self, area: float) -> "PlaneOptions":
        """The pixel counts for an image `area` times the pixels of 320x240."""
        return dataclasses.replace(self, min_segment_px=max(1, round(self.min_segment_px * area)),
                                   min_inliers=max(3, round(self.min_inliers * area)))


def segment_planes(depth: np.ndarray, image: np.ndarray, opts: PlaneOptions
                   ) -> tuple[np.ndarray, np.ndarray]:
    """(depth with the empty pixels (<= 0) of planar segments filled, filled (H, W) bool).

    A plane in camera space is affine in the image in inverse depth (1/z = a u + b v + c), so the
    fit is linear: RANSAC over 3-pixel samples, then least squares on the inliers. A segment is
    filled only where its plane explains `inlier_share` of its known pixels, and only with
    inverse depths within [0.8, 1.25] x the inliers' range, so a plane fitted to a strip of
    known pixels does not run off to infinity across the rest of the segment. (Not
    planes.ransac_planes: its inlier distance is absolute, in scene units, over 3-D points; here
    the tolerance is relative to the depth and the fit is a linear solve per sample.)"""
    from skimage.segmentation import felzenszwalb

    d = np.asarray(depth, np.float64)
    img = np.asarray(image)
    if d.ndim != 2 or img.shape[:2] != d.shape:
        raise ValueError(f"depth (H, W) and image (H, W[, C]) disagree: {d.shape}, {img.shape}")
    h, w = d.shape
    seg = felzenszwalb(img, scale=opts.segment_scale, sigma=0.8, min_size=opts.min_segment_px,
                       channel_axis=-1 if img.ndim == 3 else None).ravel()
    flat = d.ravel()
    known = flat > 0
    order = np.argsort(seg, kind="stable")
    bounds = np.flatnonzero(np.diff(seg[order])) + 1
    u = (np.arange(h * w) % w).astype(np.float64)
    v = (np.arange(h * w) // w).astype(np.float64)
    rng = np.random.default_rng(opts.seed)
    out = flat.copy()
    filled = np.zeros(h * w, bool)
    for pix in np.split(order, bounds):
        kn, un = pix[known[pix]], pix[~known[pix]]
        if len(un) == 0 or len(kn) < max(3, opts.min_inliers):
            continue
        A = np.stack([u[kn], v[kn], np.ones(len(kn))], 1)
        y = 1.0 / flat[kn]
        samples = np.stack([rng.choice(len(kn), 3, replace=False) for _ in range(opts.hypotheses)])
        M = A[samples]                                   # (n, 3, 3)
        ok = np.abs(np.linalg.det(M)) > 1e-9
        if not ok.any():
            continue
        p = np.linalg.solve(M[ok], y[samples[ok]][..., None])[..., 0]   # (n, 3)
        inl = np.abs(A @ p.T - y[:, None]) <= opts.tol_rel * y[:, None]  # (k, n)
        best = inl[:, int(inl.sum(0).argmax())]
        if best.sum() < max(opts.min_inliers, opts.inlier_share * len(kn)):
            continue
        plane = np.linalg.lstsq(A[best], y[best], rcond=None)[0]
        pred = np.stack([u[un], v[un], np.ones(len(un))], 1) @ plane
        lo, hi = y[best].min(), y[best].max()
        take = (pred > 0.8 * lo) & (pred < 1.25 * hi)
        out[un[take]] = 1.0 / pred[take]
        filled[un[take]] = True
    return out.reshape(h, w), filled.reshape(h, w)


def edge_weights(edges: np.ndarray, cost_edge: float) -> tuple[np.ndarray, np.ndarray]:
    """Weights of the 4-neighbour links (right (H, W-1), down (H-1, W)) from a colour edge map in
    [0, 1]: exp(-d) with d the extra cost Eq. 2's geodesic step pays across the edge (w = exp(-d_g)
    for one step, relative to a flat one), so a full-strength colour edge all but cuts the link."""
    e = np.asarray(edges, np.float64)
    if e.ndim != 2:
        raise ValueError(f"edges must be (H, W), got {e.shape}")
    c = cost_edge * e
    right = np.exp(-0.5 * (c[:, 1:] + c[:, :-1]))
    down = np.exp(-0.5 * (c[1:] + c[:-1]))
    return right, down


def membrane_fill(values: np.ndarray, unknown: np.ndarray, weights: tuple[np.ndarray, np.ndarray]
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Edge-aware membrane interpolation: the `unknown` pixels of `values` (H, W) minimise
    sum w_pq (x_p - x_q)^2 over 4-neighbour links with the known pixels fixed (a weighted discrete
    Laplace equation, Dirichlet boundary; Levin et al. 2004's colourisation applied to inverse
    depth, in which a plane is affine in the image and so reproduced exactly). Returns (filled
    values, reached (H, W) bool: unknown pixels connected to a known one)."""
    import scipy.ndimage as nd
    import scipy.sparse as sp
    import scipy.sparse.linalg as spl

    v = np.asarray(values, np.float64)
    unk = np.asarray(unknown, bool)
    h, w = v.shape
    right, down = weights
    if unk.shape != (h, w) or right.shape != (h, w - 1) or down.shape != (h - 1, w):
        raise ValueError(f"values, unknown (H, W) and weights ((H, W-1), (H-1, W)) disagree: "
                         f"{v.shape}, {unk.shape}, {right.shape}, {down.shape}")
    # only components of the unknown region that touch a known pixel can be solved
    lab, n = nd.label(unk)
    touch = nd.binary_dilation(~unk) & unk
    ok_labels = np.unique(lab[touch])
    solve = np.isin(lab, ok_labels[ok_labels > 0])
    out = np.where(unk, 0.0, v)
    idx = -np.ones((h, w), np.int64)
    m = int(solve.sum())
    if m == 0:
        return out, solve
    idx[solve] = np.arange(m)
    rows, cols, vals = [], [], []
    diag = np.zeros(m)
    rhs = np.zeros(m)
    for wt, (a_sl, b_sl) in ((right, ((slice(None), slice(0, w - 1)), (slice(None), slice(1, w)))),
                             (down, ((slice(0, h - 1), slice(None)), (slice(1, h), slice(None))))):
        ia, ib = idx[a_sl], idx[b_sl]
        wt = wt + 1e-9  # a fully cut link must not leave a pixel without any equation
        for i_p, i_q, val_q in ((ia, ib, v[b_sl]), (ib, ia, v[a_sl])):
            sel = i_p >= 0
            np.add.at(diag, i_p[sel], wt[sel])
            both = sel & (i_q >= 0)
            rows.append(i_p[both])
            cols.append(i_q[both])
            vals.append(-wt[both])
            known = sel & (i_q < 0)   # a neighbour of a solved pixel is solved or known
            np.add.at(rhs, i_p[known], wt[known] * val_q[known])
    A = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(m, m)) + sp.diags(diag)
    x = spl.spsolve(A.tocsc(), rhs)
    out[solve] = x
    return out, solve


def view_mvs(mvs_depth: np.ndarray, w: int, h: int, speckle_px: int = 0) -> np.ndarray:
    """An MVS depth map (any size of the view's aspect, 0 = none) on the view's w x h pixels
    (nearest-neighbour), its speckles (`remove_speckles`, at most `speckle_px`) dropped."""
    m = _resize_nearest(np.asarray(mvs_depth, np.float64), w, h)
    return remove_speckles(m, speckle_px) if speckle_px > 0 else m


def mvs_in_front(g_depth: np.ndarray, mvs_depth: np.ndarray, rel: float, min_px: int
                 ) -> tuple[np.ndarray, np.ndarray]:
    """(depth (H, W) float64, front (H, W) bool): G's depth with the view's own MVS depth taken
    where it lies in front of G's by more than `rel` (relative), in 4-connected regions of at
    least `min_px` such pixels (`front`). A surface the view sees in front of G hides G's there,
    so G lacks it: the fusion did not confirm it (too few views, at the capture's border). A
    wrong match behind G (a reflection's virtual depth, a textureless wall) is never taken.
    `mvs_depth` as in `complete_depth` (resized; `view_mvs` drops its speckles)."""
    import cv2
    g = np.asarray(g_depth, np.float64)
    if g.ndim != 2:
        raise ValueError(f"g_depth must be (H, W), got {g.shape}")
    h, w = g.shape
    m = _resize_nearest(np.asarray(mvs_depth, np.float64), w, h)
    front = np.isfinite(m) & (m > 0) & np.isfinite(g) & (g > 0) & (m < g * (1.0 - rel))
    if min_px > 1 and front.any():
        n, lab, stats, _ = cv2.connectedComponentsWithStats(front.astype(np.uint8), connectivity=4)
        front = np.isin(lab, 1 + np.flatnonzero(stats[1:, cv2.CC_STAT_AREA] >= min_px)) & front
    return np.where(front, m, np.where(np.isfinite(g) & (g > 0), g, 0.0)), front


def remove_speckles(depth: np.ndarray, max_px: int, rel: float = 0.02) -> np.ndarray:
    """depth (H, W) with its speckles zeroed: connected regions of at most `max_px` pixels whose
    neighbours differ by at most `rel` in relative depth (OpenCV's filterSpeckles, the stereo
    matchers' filter, on log depth in steps of rel / 4)."""
    import cv2
    d = np.asarray(depth, np.float64)
    ok = np.isfinite(d) & (d > 0)
    if not ok.any():
        return np.where(ok, d, 0.0)
    q = np.zeros(d.shape, np.int16)
    step = rel / 4
    logd = np.log(d[ok])
    q[ok] = np.clip(np.round((logd - logd.min()) / step) + 1, 1, 32000).astype(np.int16)
    cv2.filterSpeckles(q, 0, int(max_px), 4)
    return np.where(ok & (q > 0), d, 0.0)


def _resize_nearest(a: np.ndarray, w: int, h: int) -> np.ndarray:
    if a.ndim != 2:
        raise ValueError(f"mvs_depth must be (h, w), got {a.shape}")
    if a.shape == (h, w):
        return a
    if abs(a.shape[1] / a.shape[0] - w / h) > 0.02 * (w / h):
        raise ValueError(f"mvs_depth is {a.shape[1]}x{a.shape[0]}, not the aspect of {w}x{h}")
    # pixel centres: source pixel of target pixel x is floor((x + 0.5) * sw / w)
    ys = np.minimum(((np.arange(h) + 0.5) * a.shape[0] / h).astype(int), a.shape[0] - 1)
    xs = np.minimum(((np.arange(w) + 0.5) * a.shape[1] / w).astype(int), a.shape[1] - 1)
    return a[ys[:, None], xs[None, :]]
