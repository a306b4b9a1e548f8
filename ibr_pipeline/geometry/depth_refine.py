"""Per-view depth refinement (Xu et al. §4.2.1-4.2.2) as plain functions on arrays.

`detect` : normals from depth, Eq. 1 depth edges, the 4 cm refinement mask (§4.2.1).
`masked_mvs` : step one of §4.2.2 — multi-view depth inside the mask only (torch plane sweep from
    `geometry.mvs` in place of COLMAP PatchMatch), keeping a pixel only when the photometric estimate
    agrees with the geometric (multi-view) evidence within 5 %.
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
           mask_side_m: float = de.MASK_SIDE_M, mask_min_half_px: int = 1) -> Detection:
    """§4.2.1 on a z-depth image seen by `camera` (0 = no depth)."""
    depth = np.asarray(depth, dtype=np.float64)
    if depth.shape != (camera.height, camera.width):
        raise ValueError(f"depth shape {depth.shape} does not match camera {camera.width}x{camera.height}")
    P = points_from_depth(depth, camera.K)
    N = normals_from_points(P, depth > 0)
    e = de.depth_edges(P, N, depth, lambda_rel)
    ep = e.pixels()
    f = float(np.sqrt(camera.K[0, 0] * camera.K[1, 1]))
    mask = de.refinement_mask(ep, depth, f, mask_side_m, mask_min_half_px) if ep.any() else np.zeros_like(ep)
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


def masked_mvs(image: np.ndarray, camera: Camera, depth_init: np.ndarray, mask: np.ndarray,
               src_images: list, src_cams: list, src_depths: list, num_depths: int = 32,
               window: int = 7, band_radius: int = 8, min_consistent: int = 1,
               agree_rel: float = MVS_AGREE_REL, device: str = "cpu") -> MVSResult:
    """Step one of Xu §4.2.2 inside `mask` (see module doc). The photometric stage is
    `mvs.plane_sweep` over a per-pixel band around the initial depth; the geometric stage is the
    forward-backward check `mvs.geometric_consistency` against the source views' depth maps
    (here: G rendered into them) with relative tolerance `agree_rel`: a pixel is kept when at least
    `min_consistent` sources agree with its photometric depth within 5 % (Xu's threshold)."""
    from . import mvs

    h, w = depth_init.shape
    if mask.shape != (h, w) or image.shape[:2] != (h, w):
        raise ValueError(f"image {image.shape}, mask {mask.shape} and depth {depth_init.shape} differ")
    dmin, dmax, ok = search_band(depth_init, mask, band_radius)
    out = np.zeros((h, w))
    if not ok.any() or not src_images:
        return MVSResult(out, np.zeros((h, w), bool), 0, {"sources": len(src_images)})
    sw = mvs.plane_sweep(image, camera, src_images, src_cams, dmin, dmax, num_depths=num_depths,
                         window=window, mask=ok, device=device)
    photo = np.where(ok & sw.valid, sw.depth, 0.0)
    n_ok = mvs.geometric_consistency(camera, photo, src_cams, src_depths, rel_tol=agree_rel,
                                     device=device)
    accepted = (photo > 0) & (n_ok >= min_consistent)
    out[accepted] = photo[accepted]
    return MVSResult(out, accepted, int(ok.sum()),
                     {"photometric_valid": int((photo > 0).sum()), "accepted": int(accepted.sum()),
                      "sources": len(src_images)})


def refine(depth: np.ndarray, camera: Camera, image: np.ndarray, region: np.ndarray,
           strokes: np.ndarray | None = None, cost_base: float = 0.05, cost_edge: float = 5.0,
           k: int = geo.K_NEIGHBOURS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eq. 2 over `region` of `depth` (camera `camera`, colour `image`). Returns (refined depth,
    filled (H, W) bool, colour edge map)."""
    depth = np.asarray(depth, dtype=np.float64)
    P = points_from_depth(depth, camera.K)
    N = normals_from_points(P, depth > 0)
    edges = geo.colour_edge_map(image, strokes)
    cost = geo.edge_cost(edges, cost_base, cost_edge)
    rays = pixel_rays(camera.K, *depth.shape)
    new, filled = geo.interpolate_depth(depth, P, N, rays, cost, region, k)
    return new, filled, edges
