"""Edge-aware geodesic depth interpolation (Xu et al. §4.2.2, Eq. 2, after EpicFlow).

    d_i = sum_{j in A_i} w_g(i, j) / sum_k w_g(i, k) * dhat_i^j,     w_g(i, j) = exp(-d_g(i, j))

A_i: the 4 geodesically nearest pixels j outside the region being interpolated; d_g: geodesic
distance over a colour-edge cost map (crossing a colour edge is expensive, so the interpolation does
not leak across it); dhat_i^j: the depth where pixel i's line of sight meets the plane through pixel
j's 3D point with j's normal.

Colour edges: the paper uses structured-forest edges (Dollár & Zitnick 2015), whose model file is not
available offline. `colour_edge_map` is model-free: the per-channel Sobel gradient magnitude of the
(gamma-encoded) image, normalised by a robust scale, combined with Canny edges (cv2). What the
learned forest adds is telling object boundaries from texture; our model-free stand-in for that is
the oriented half-disc colour gradient of Martin, Fowlkes & Malik 2004 (`boundary_strength`, the
colour/brightness cue of Pb without its learned weights): across an outline the mean colours of the
two half discs differ, across a texture dot smaller than the disc they barely do, so with
`boundary_radius` > 0 each edge pixel is weighted by it and texture becomes cheap to cross. User
strokes (an optional mask of occlusion edges the user drew) are added at full edge strength.
"""
from __future__ import annotations

import numpy as np

K_NEIGHBOURS = 4  # Xu Eq. 2: the 4 closest neighbours outside the refinement mask


def encode_for_edges(image: np.ndarray, blur_sigma: float) -> np.ndarray:
    """(H, W, 3) float32: sqrt of a linear RGB image in [0, 1] (display-like, so dark regions are
    not edge-free), Gaussian-blurred by `blur_sigma` px; the input of every colour-edge detector."""
    import cv2

    img = np.asarray(image, dtype=np.float32)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"image must be (H, W, 3), got {img.shape}")
    enc = np.sqrt(np.clip(img, 0, 1))
    if blur_sigma > 0:
        enc = cv2.GaussianBlur(enc, (0, 0), blur_sigma)
    return enc


def _robust_unit(mag: np.ndarray) -> np.ndarray:
    """`mag` / max(3 x its 90th percentile, half its 99.5th), clipped to [0, 1]: the 90th percentile
    follows the image's contrast, the 99.5th keeps a lone strong edge from saturating a wide band."""
    scale = max(3.0 * float(np.percentile(mag, 90)), 0.5 * float(np.percentile(mag, 99.5)), 1e-3)
    return np.clip(mag / scale, 0.0, 1.0)


def halfdisc_kernels(radius: int, orientations: int = 8) -> list[np.ndarray]:
    """Correlation kernels (2r+1, 2r+1) float32, one per orientation theta = k pi / n: the mean over
    the half disc on one side of the line through the centre at angle theta minus the mean over the
    other half (pixels within half a pixel of the line belong to neither)."""
    if radius < 1 or orientations < 1:
        raise ValueError(f"need radius >= 1 and orientations >= 1, got {radius}, {orientations}")
    yy, xx = np.mgrid[-radius:radius + 1, -radius:radius + 1].astype(np.float64)
    disc = xx ** 2 + yy ** 2 <= radius * radius + 0.5
    out = []
    for k in range(orientations):
        t = np.pi * k / orientations
        side = -np.sin(t) * xx + np.cos(t) * yy   # signed distance to the line
        a, b = disc & (side > 0.5), disc & (side < -0.5)
        out.append((a / a.sum() - b / b.sum()).astype(np.float32))
    return out


def boundary_strength(encoded: np.ndarray, radius: int, orientations: int = 8) -> np.ndarray:
    """(H, W) float32: max over orientations of the Euclidean distance between the mean colours of
    the two half discs of `radius` px around each pixel (Martin, Fowlkes & Malik 2004, colour and
    brightness gradient), on an encoded image (H, W, 3) from `encode_for_edges`."""
    import cv2

    enc = np.asarray(encoded, dtype=np.float32)
    if enc.ndim != 3 or enc.shape[2] != 3:
        raise ValueError(f"encoded image must be (H, W, 3), got {enc.shape}")
    best = np.zeros(enc.shape[:2], np.float32)
    for k in halfdisc_kernels(radius, orientations):
        d = cv2.filter2D(enc, cv2.CV_32F, k, borderType=cv2.BORDER_REFLECT)
        # the squared distance, summed as numpy sums the length-3 axis (the same bits); sqrt
        # is monotonic and correctly rounded, so the root of the maximum is the maximum root
        np.maximum(best, d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1] + d[..., 2] * d[..., 2],
                   out=best)
    return np.sqrt(best)


def colour_edge_map(image: np.ndarray, strokes: np.ndarray | None = None,
                    blur_sigma: float = 1.0, canny: tuple[int, int] = (40, 100),
                    boundary_radius: int = 0) -> np.ndarray:
    """(H, W) float32 edge strength in [0, 1] of a linear RGB image (H, W, 3) in [0, 1].

    max over channels of the Sobel magnitude of sqrt(image) (a display-like encoding, so dark
    regions are not edge-free), robustly normalised (`_robust_unit`); the maximum with Canny edges
    (thresholds `canny` on the 8-bit encoded grey image); with `boundary_radius` r > 0, times the
    robustly normalised `boundary_strength` at radius r (of the unblurred encoding), which keeps
    outlines and fades texture; strokes add 1."""
    import cv2

    enc = encode_for_edges(image, blur_sigma)
    gx = cv2.Sobel(enc, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(enc, cv2.CV_32F, 0, 1, ksize=3)
    edges = _robust_unit(np.sqrt(gx * gx + gy * gy).max(axis=2))
    grey = cv2.cvtColor((enc * 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)
    edges = np.maximum(edges, cv2.Canny(grey, *canny).astype(np.float32) / 255.0)
    if boundary_radius > 0:
        edges = edges * _robust_unit(boundary_strength(encode_for_edges(image, 0.0), int(boundary_radius)))
    return with_strokes(edges, strokes)


def with_strokes(edges: np.ndarray, strokes: np.ndarray | None) -> np.ndarray:
    """`colour_edge_map`'s last step: user strokes (H, W) bool add 1 to an edge map (H, W), so
    that a map computed once without strokes serves callers with different strokes."""
    edges = np.asarray(edges)
    if strokes is not None:
        s = np.asarray(strokes, bool)
        if s.shape != edges.shape:
            raise ValueError(f"strokes must be {edges.shape}, got {s.shape}")
        edges = np.maximum(edges, s.astype(np.float32))
    return edges.astype(np.float32)


def edge_cost(edges: np.ndarray, base: float, scale: float) -> np.ndarray:
    """Per-pixel geodesic cost: base + scale * edge strength (step cost = mean of the two pixels)."""
    e = np.asarray(edges, dtype=np.float64)
    if e.ndim != 2:
        raise ValueError(f"edges must be (H, W), got {e.shape}")
    return base + scale * e


def geodesic_knn(cost: np.ndarray, region: np.ndarray, seeds: np.ndarray, k: int = K_NEIGHBOURS,
                 max_iter: int | None = None, method: str = "dijkstra"
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The k geodesically nearest seed pixels of every region pixel.

    cost (H, W) > 0; region, seeds (H, W) bool, disjoint. Paths run through region pixels (4-
    connected); a step between p and q costs (cost[p] + cost[q]) / 2. Returns (idx (M,) flat pixel
    indices of the region pixels, nearest (M, k) flat indices of seeds, -1 where fewer than k are
    reachable, dist (M, k) geodesic distances, inf where none), nearest first.
    method "dijkstra": multi-label Dijkstra (geodesic_nb, numba); "relax": the vectorised
    label-correcting relaxation (Bellman-Ford over the region) iterated until nothing changes —
    the reference, same fixed point (equal up to the order of exact ties)."""
    if method not in ("dijkstra", "relax"):
        raise ValueError(f"method must be 'dijkstra' or 'relax', got {method!r}")
    cost = np.asarray(cost, dtype=np.float64)
    region, seeds = np.asarray(region, bool), np.asarray(seeds, bool)
    if cost.ndim != 2 or region.shape != cost.shape or seeds.shape != cost.shape:
        raise ValueError(f"cost, region and seeds must be (H, W), got {cost.shape}, {region.shape}, "
                         f"{seeds.shape}")
    if np.any(region & seeds):
        raise ValueError("region and seeds must be disjoint")
    h, w = cost.shape
    idx = np.flatnonzero(region)
    m = len(idx)
    if m == 0:
        return idx, np.zeros((0, k), np.int64), np.zeros((0, k))
    if method == "dijkstra":
        from .geodesic_nb import knn_dijkstra

        lab, dist = knn_dijkstra(cost.ravel(), h, w, idx.astype(np.int64), seeds.ravel(), int(k))
        return idx, lab, dist
    node = np.full(h * w, -1, np.int64)
    node[idx] = np.arange(m)
    ys, xs = np.divmod(idx, w)
    flat_cost = cost.ravel()
    seed_flat = seeds.ravel()
    # neighbour tables: (M, 4) flat pixel index or -1 outside the image
    nb = np.full((m, 4), -1, np.int64)
    for c, (dy, dx) in enumerate(((0, 1), (0, -1), (1, 0), (-1, 0))):
        yy, xx = ys + dy, xs + dx
        ok = (yy >= 0) & (yy < h) & (xx >= 0) & (xx < w)
        nb[ok, c] = yy[ok] * w + xx[ok]
    step = np.where(nb >= 0, 0.5 * (flat_cost[idx][:, None] + flat_cost[np.maximum(nb, 0)]), np.inf)
    nb_node = np.where(nb >= 0, node[np.maximum(nb, 0)], -1)          # region neighbour or -1
    nb_seed = np.where((nb >= 0) & seed_flat[np.maximum(nb, 0)], nb, -1)  # seed neighbour or -1
    dist = np.full((m, k), np.inf)
    lab = np.full((m, k), -1, np.int64)
    # direct seed neighbours as the starting candidates
    seed_d = np.where(nb_seed >= 0, step, np.inf)
    max_iter = max_iter or (2 * (h + w) + m)
    # Label-correcting relaxation on an active frontier: only rows with a neighbour that changed in
    # the previous sweep are recomputed (the result is the same fixed point as relaxing every row).
    active = np.arange(m)
    ncand = k + 4 + 4 * k
    tri = np.tril(np.ones((ncand, ncand), bool), -1)  # [j, i]: column i comes before column j
    for _ in range(max_iter):
        if len(active) == 0:
            break
        a = active
        cand_d = [dist[a], seed_d[a]]
        cand_l = [lab[a], nb_seed[a]]
        for c in range(4):
            nn = nb_node[a, c]
            has = nn >= 0
            src = np.maximum(nn, 0)
            cand_d.append(np.where(has[:, None], dist[src] + step[a, c:c + 1], np.inf))
            cand_l.append(np.where(has[:, None], lab[src], -1))
        cd = np.concatenate(cand_d, 1)
        cl = np.concatenate(cand_l, 1)
        cd[cl < 0] = np.inf
        o = np.argsort(cd, axis=1, kind="stable")
        rows = np.arange(len(a))[:, None]
        cd, cl = cd[rows, o], cl[rows, o]
        # a label already seen in an earlier (closer) column is a duplicate
        dup = ((cl[:, :, None] == cl[:, None, :]) & tri[None]).any(2) | ~np.isfinite(cd)
        o2 = np.argsort(dup, axis=1, kind="stable")[:, :k]
        new_d, new_l = cd[rows, o2], cl[rows, o2]
        bad = dup[rows, o2]
        new_d[bad], new_l[bad] = np.inf, -1
        changed = np.any(new_l != lab[a], 1) | np.any(new_d != dist[a], 1)
        dist[a], lab[a] = new_d, new_l
        ch = a[changed]
        if len(ch) == 0:
            break
        nxt = nb_node[ch].ravel()
        active = np.unique(nxt[nxt >= 0])
    return idx, lab, dist


def plane_induced_depth(rays_i: np.ndarray, points_j: np.ndarray, normals_j: np.ndarray,
                        depth_j: np.ndarray, max_ratio: float = 1.5) -> np.ndarray:
    """dhat_i^j (Eq. 2): z-depth where the ray (z = 1) of pixel i meets the plane through point
    v_j with normal n_j: d = (n_j . v_j) / (n_j . r_i). Falls back to d_j (a fronto-parallel
    plane) at grazing angles or when the intersection is beyond max_ratio x d_j (or below 1 / it).
    Shapes: rays (..., 3), points (..., 3), normals (..., 3), depth_j (...)."""
    if not (rays_i.shape == points_j.shape == normals_j.shape) or depth_j.shape != rays_i.shape[:-1]:
        raise ValueError(f"shape mismatch: {rays_i.shape} {points_j.shape} {normals_j.shape} {depth_j.shape}")
    num = np.sum(normals_j * points_j, -1)
    den = np.sum(normals_j * rays_i, -1)
    with np.errstate(divide="ignore", invalid="ignore"):
        d = num / den
    ok = np.isfinite(d) & (d > depth_j / max_ratio) & (d < depth_j * max_ratio)
    return np.where(ok, d, depth_j)


def interpolate_depth(depth: np.ndarray, points: np.ndarray, normals: np.ndarray, rays: np.ndarray,
                      cost: np.ndarray, region: np.ndarray, k: int = K_NEIGHBOURS
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 2 over `region`: returns (new depth (H, W), filled (H, W) bool). Seeds are the pixels
    outside `region` with depth > 0; region pixels that reach no seed keep their depth.
    depth (H, W); points, normals, rays (H, W, 3) in camera space (rays with z = 1)."""
    depth = np.asarray(depth, dtype=np.float64)
    h, w = depth.shape
    for name, a in (("points", points), ("normals", normals), ("rays", rays)):
        if a.shape != (h, w, 3):
            raise ValueError(f"{name} must be {(h, w, 3)}, got {a.shape}")
    seeds = (~region) & (depth > 0)
    idx, lab, dist = geodesic_knn(cost, region, seeds, k)
    out = depth.copy()
    filled = np.zeros((h, w), bool)
    if len(idx) == 0:
        return out, filled
    has = lab >= 0
    labc = np.maximum(lab, 0)
    P, N, R = points.reshape(-1, 3), normals.reshape(-1, 3), rays.reshape(-1, 3)
    ri = np.broadcast_to(R[idx][:, None, :], (len(idx), k, 3))
    dhat = plane_induced_depth(ri, P[labc], N[labc], depth.ravel()[labc])
    # w_g = exp(-d_g) (Eq. 2); subtract the row minimum first (cancels in the normalisation)
    dmin = np.min(np.where(has, dist, np.inf), axis=1, keepdims=True)
    wgt = np.where(has, np.exp(-(dist - np.where(np.isfinite(dmin), dmin, 0))), 0.0)
    tot = wgt.sum(1)
    ok = tot > 0
    val = (wgt * np.where(has, dhat, 0)).sum(1) / np.where(ok, tot, 1)
    flat = out.ravel()
    flat[idx[ok]] = val[ok]
    filled.ravel()[idx[ok]] = True
    return flat.reshape(h, w), filled
