"""Per-view depth refinement (Xu et al. §4.2.1-4.2.2) as plain functions on arrays.

`detect` : normals from depth, Eq. 1 depth edges, the 4 cm refinement mask (§4.2.1).
`masked_mvs` : step one of §4.2.2 — multi-view depth inside the mask only (torch plane sweep from
    `geometry.mvs` in place of COLMAP PatchMatch), keeping a pixel only when the photometric estimate
    agrees with the geometric (multi-view) evidence within 5 % (`near_consistency`), G's depth where
    the two agree within 1.5 lambda, and none within the NCC window radius of an edge of the MVS
    depth (`edge_guard`), which Eq. 2 then fills along colour edges.
`refine` : step two, Eq. 2 — every remaining mask pixel gets the exp(-d_g)-weighted plane-induced
    depths of its 4 geodesically nearest pixels outside the remaining mask.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..scene import Camera
from . import depth_edges as de
from . import geodesic as geo
from .normals import normals_from_points, pixel_rays, points_from_depth

MVS_AGREE_REL = 0.05  # Xu §4.2.2: discard when photometric and geometric depth differ by > 5 %


@dataclass
class Detection:
    points: np.ndarray   # (H, W, 3) camera space
    normals: np.ndarray  # (H, W, 3) camera space
    edges: de.PairEdges
    edge_pixels: np.ndarray  # (H, W) bool
    mask: np.ndarray         # (H, W) bool


def detect(depth: np.ndarray, camera: Camera, lambda_rel: float = de.LAMBDA_REL,
           mask_side_m: float = de.MASK_SIDE_M, mask_min_half_px: int = 1,
           with_mask: bool = True) -> Detection:
    """§4.2.1 on a z-depth image seen by `camera` (0 = no depth); `with_mask` False: the
    refinement mask is not computed (all False)."""
    depth = np.asarray(depth, dtype=np.float64)
    if depth.shape != (camera.height, camera.width):
        raise ValueError(f"depth shape {depth.shape} does not match camera {camera.width}x{camera.height}")
    P = points_from_depth(depth, camera.K)
    N = normals_from_points(P, depth > 0)
    e = de.depth_edges(P, N, depth, lambda_rel)
    ep = e.pixels()
    f = float(np.sqrt(camera.K[0, 0] * camera.K[1, 1]))
    mask = (de.refinement_mask(ep, depth, f, mask_side_m, mask_min_half_px) if with_mask and ep.any()
            else np.zeros_like(ep))
    return Detection(P, N, e, ep, mask)


def search_band(depth: np.ndarray, mask: np.ndarray, radius: int, margin: float = 0.1
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-pixel MVS depth range: [min, max] of the valid initial depth within `radius` pixels,
    widened by `margin` (relative). Returns (dmin, dmax, usable mask)."""
    import cv2

    depth = np.asarray(depth, dtype=np.float32)
    k = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    big = np.float32(1e6)
    lo = -cv2.dilate(-np.where(depth > 0, depth, big), k)
    hi = cv2.dilate(np.where(depth > 0, depth, 0).astype(np.float32), k)
    ok = mask & (hi > 0) & (lo < big)
    dmin = np.where(ok, lo * (1 - margin), 1.0)
    dmax = np.where(ok, hi * (1 + margin), 2.0)
    return dmin.astype(np.float64), dmax.astype(np.float64), ok


@dataclass
class MVSResult:
    depth: np.ndarray      # (H, W) accepted depth, 0 elsewhere
    accepted: np.ndarray   # (H, W) bool
    computed: int          # pixels swept
    stats: dict = field(default_factory=dict)


def near_consistency(ref_cam: Camera, ref_depth: np.ndarray, src_cams: list, src_depths: list,
                     rel_tol: float = MVS_AGREE_REL, radius: int = 1) -> np.ndarray:
    """(H, W) int: for each pixel with depth, how many source depth maps have, within `radius`
    pixels of the point's projection, a depth within `rel_tol` (relative) of the point's depth in
    that source (0 where `ref_depth` is 0).

    The geometric check of step one (§4.2.2) against G rendered into the sources. A strict
    round trip (`mvs.geometric_consistency`) rejects the correct MVS depth exactly where G's edge is
    misplaced (G is wrong in the sources too: a 2 cm TSDF moves edges by 1-2 voxels); the
    `radius` window tolerates that misplacement, while depths near no G surface (wrong matches,
    the virtual depth seen in a mirror) are still rejected."""
    ref_depth = np.asarray(ref_depth, dtype=np.float64)
    if ref_depth.ndim != 2 or len(src_cams) != len(src_depths) or radius < 0:
        raise ValueError(f"need (H, W) depth, as many cameras as depth maps and radius >= 0, got "
                         f"{ref_depth.shape}, {len(src_cams)}, {len(src_depths)}, {radius}")
    h, w = ref_depth.shape
    ys, xs = np.nonzero(ref_depth > 0)
    count = np.zeros((h, w), np.int64)
    if len(ys) == 0:
        return count
    cam = ref_cam.resized(w, h)
    z = ref_depth[ys, xs]
    Xc = np.stack([xs * z, ys * z, z], -1) @ np.linalg.inv(cam.K).T
    Xw = (Xc - cam.cam_from_world[:3, 3]) @ cam.cam_from_world[:3, :3]  # R^T (X - t)
    for sc, sd in zip(src_cams, src_depths):
        sd = np.asarray(sd, np.float64)
        sc = sc.resized(sd.shape[1], sd.shape[0])
        Xs = Xw @ sc.cam_from_world[:3, :3].T + sc.cam_from_world[:3, 3]
        zs = Xs[:, 2]
        ps = Xs @ sc.K.T
        good = zs > 1e-6
        zz = np.where(good, zs, 1.0)
        iu = np.where(good, np.rint(ps[:, 0] / zz), -1e6).clip(-1e6, 1e6).astype(np.int64)
        iv = np.where(good, np.rint(ps[:, 1] / zz), -1e6).clip(-1e6, 1e6).astype(np.int64)
        agree = np.zeros(len(z), bool)
        for dy in range(-radius, radius + 1):
            for dx in range(-radius, radius + 1):
                u, v = iu + dx, iv + dy
                ins = good & (u >= 0) & (u < sd.shape[1]) & (v >= 0) & (v < sd.shape[0])
                ds = np.zeros(len(z))
                ds[ins] = sd[v[ins], u[ins]]
                agree |= ins & (ds > 0) & (np.abs(ds - zs) <= rel_tol * zs)
        count[ys, xs] += agree
    return count


def edge_guard(depth: np.ndarray, radius: int, camera: Camera,
               lambda_rel: float = de.LAMBDA_REL) -> np.ndarray:
    """(H, W) bool: pixels within `radius` px of an Eq. 1 edge *inside* the MVS depth `depth`
    (both pixels of the pair have an MVS depth; 0 = none). An NCC window of radius r that straddles
    an occlusion edge takes the textured side's depth ("foreground fattening"), so an edge between
    two MVS depths may sit up to r px off the true one; edges between an MVS depth and a pixel
    without one are not guarded (there the MVS depth is the correction of G)."""
    import cv2

    depth = np.asarray(depth, dtype=np.float64)
    valid = depth > 0
    P = points_from_depth(depth, camera.K)
    e = de.depth_edges(P, normals_from_points(P, valid), depth, lambda_rel).between_surfaces(valid)
    if radius <= 0 or not (e.right.any() or e.down.any()):
        return np.zeros(depth.shape, bool)
    return cv2.dilate(e.pixels().astype(np.uint8), np.ones((2 * radius + 1,) * 2, np.uint8)) > 0


def masked_mvs(image: np.ndarray, camera: Camera, depth_init: np.ndarray, mask: np.ndarray,
               src_images: list, src_cams: list, src_depths: list, num_depths: int = 32,
               window: int = 7, band_radius: int = 8, min_consistent: int = 1,
               agree_rel: float = MVS_AGREE_REL, device: str = "cpu", check: str = "near",
               check_radius: int = 1, min_change: float = 1.5, guard_px: int = 3,
               lambda_rel: float = de.LAMBDA_REL, protect: np.ndarray | None = None,
               trust_g: np.ndarray | None = None, distrust_g: np.ndarray | None = None) -> MVSResult:
    """Step one of Xu §4.2.2 inside `mask` (see module doc).

    1. photometric: `mvs.plane_sweep` over a per-pixel band around the initial depth;
    2. geometric (Xu: discard when photometric and geometric differ by > 5 %): at least
       `min_consistent` sources agree within `agree_rel` — `check` "near": `near_consistency`
       (G in the sources, `check_radius` px tolerance), "roundtrip": the strict forward-backward
       `mvs.geometric_consistency` (it rejects the corrections where G itself is wrong);
    3. where the kept MVS depth differs from G's by at most `min_change` x Eq. 1's lambda, G's
       depth is kept (G is the more precise of the two on surfaces: MVS noise is 5-13 mm here);
    4. `edge_guard`: kept pixels within `guard_px` (the NCC window radius) of an Eq. 1 edge inside
       the kept depth are dropped, so Eq. 2 re-interpolates them along colour edges — except
       pixels of step 3 (G's depth, confirmed by the MVS) inside `protect` (H, W) bool, the caller's
       "G is reliable here" region (the stage: farther than the guard from G's own edges and
       rounded steps). Without that, MVS noise edges wiped out most of the confirmed G depth and
       Eq. 2 refilled it from the seeds outside the mask, across texture.
    `trust_g` (H, W) bool, optional: mask pixels where the caller trusts G outright (the stage: the
    same far-from-G's-edges region). They are not swept and are accepted with G's depth: far from
    its edges G is exact to ~1.5 mm, while the 5 % check passes MVS depths several centimetres
    off (5 % of 2 m is 10 cm) that Eq. 2 then spread to their neighbours as seeds.
    `distrust_g` (H, W) bool, optional: pixels that would keep G's depth (trusted, or confirmed by
    step 3) are not accepted there, so Eq. 2 re-interpolates them (the stage: around G's rounded
    steps, whose ramp lies within 1.5 lambda of both plateaus for a step of up to 3 lambda).
    `depth` holds the result on `accepted` pixels (0 elsewhere)."""
    from . import mvs

    h, w = depth_init.shape
    if mask.shape != (h, w) or image.shape[:2] != (h, w):
        raise ValueError(f"image {image.shape}, mask {mask.shape} and depth {depth_init.shape} differ")
    if check not in ("near", "roundtrip"):
        raise ValueError(f"check must be 'near' or 'roundtrip', got {check!r}")
    for name, a in (("protect", protect), ("trust_g", trust_g), ("distrust_g", distrust_g)):
        if a is not None and a.shape != (h, w):
            raise ValueError(f"{name} must be {(h, w)}, got {a.shape}")
    # trusted pixels are not swept; those outside distrust_g are accepted with G's depth
    trusted = (mask & trust_g & (depth_init > 0)) if trust_g is not None else np.zeros((h, w), bool)
    distrust = distrust_g if distrust_g is not None else np.zeros((h, w), bool)
    kept_trusted = trusted & ~distrust
    dmin, dmax, ok = search_band(depth_init, mask & ~trusted, band_radius)
    out = np.zeros((h, w))
    if not ok.any() or not src_images:
        out[kept_trusted] = depth_init[kept_trusted]
        n = int(kept_trusted.sum())
        return MVSResult(out, kept_trusted, 0, {"sources": len(src_images), "trusted_g": n,
                                                "distrusted_g": int((trusted & distrust).sum()),
                                                "accepted": n})
    sw = mvs.plane_sweep(image, camera, src_images, src_cams, dmin, dmax, num_depths=num_depths,
                         window=window, mask=ok, device=device)
    photo = np.where(ok & sw.valid, sw.depth, 0.0)
    if check == "near":
        n_ok = near_consistency(camera, photo, src_cams, src_depths, agree_rel, check_radius)
    else:
        n_ok = mvs.geometric_consistency(camera, photo, src_cams, src_depths, rel_tol=agree_rel,
                                         device=device)
    accepted = (photo > 0) & (n_ok >= min_consistent)
    out[accepted] = photo[accepted]
    lam = lambda_rel * np.maximum(1.0, depth_init)  # Eq. 1's lambda
    keep_g = accepted & (np.abs(out - depth_init) <= min_change * lam)
    out[keep_g] = depth_init[keep_g]
    out[trusted] = depth_init[trusted]   # for the guard's edges: the trusted pixels' final depth
    guard = edge_guard(out, guard_px, camera, lambda_rel) & accepted
    if protect is not None:
        guard &= ~(keep_g & protect)
    accepted &= ~guard
    drop = accepted & keep_g & distrust     # G's depth confirmed by the MVS, but distrusted
    accepted = (accepted & ~drop) | kept_trusted
    out[~accepted] = 0.0
    return MVSResult(out, accepted, int(ok.sum()),
                     {"photometric_valid": int((photo > 0).sum()), "trusted_g": int(kept_trusted.sum()),
                      "consistent": int(((photo > 0) & (n_ok >= min_consistent)).sum()),
                      "kept_g": int(keep_g.sum()), "guard_dropped": int(guard.sum()),
                      "distrusted_g": int(drop.sum() + (trusted & distrust).sum()),
                      "accepted": int(accepted.sum()), "sources": len(src_images)})


def refine(depth: np.ndarray, camera: Camera, image: np.ndarray, region: np.ndarray,
           strokes: np.ndarray | None = None, cost_base: float = 0.05, cost_edge: float = 5.0,
           k: int = geo.K_NEIGHBOURS, boundary_radius: int = 0,
           base_edges: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eq. 2 over `region` of `depth` (camera `camera`, colour `image`; `boundary_radius`: see
    `geodesic.colour_edge_map`; `base_edges`: that map of `image` without strokes, computed
    already). Returns (refined depth, filled (H, W) bool, colour edge map)."""
    depth = np.asarray(depth, dtype=np.float64)
    P = points_from_depth(depth, camera.K)
    N = normals_from_points(P, depth > 0)
    edges = (geo.colour_edge_map(image, strokes, boundary_radius=boundary_radius)
             if base_edges is None else geo.with_strokes(base_edges, strokes))
    cost = geo.edge_cost(edges, cost_base, cost_edge)
    rays = pixel_rays(camera.K, *depth.shape)
    new, filled = geo.interpolate_depth(depth, P, N, rays, cost, region, k)
    return new, filled, edges
