"""Occlusion edges the global mesh has rounded away (an addition to Xu et al. §4.2.1).

Eq. 1 compares *adjacent* pixels. A TSDF-fused global mesh G (2-3 cm voxels) turns a small step
(a picture frame, a poster, a wall panel 1-5 cm in front of the wall) into a ramp a few pixels wide:
neighbouring pixels on the ramp are coplanar to within lambda, so Eq. 1 finds no edge, no
refinement mask is built, and the step is never refined (the paper's COLMAP-based G is sharper).

`rounded_steps` applies the same mutual planar distance to pixel pairs `2s` apart (s in `strides`),
each with its own normal (the one-sided normals of `normals.py`, so a pixel on a plateau takes the
plateau's plane): across a ramp between two *parallel* planes offset by h, dt = h, while on a plane
dt = 0 and on a crease between two walls the normals differ (rejected by `max_angle_deg`).
A candidate must also have a colour edge within s pixels (the step is visible in the image), so
texture-free slopes are left alone. The candidates only enlarge the refinement mask; the edge map
is still Eq. 1 (lambda = 0.01 max(1, d)) on the refined depth.
"""
from __future__ import annotations

import numpy as np

from .depth_edges import LAMBDA_REL
from .normals import dot3


def rounded_steps(depth: np.ndarray, points: np.ndarray, normals: np.ndarray,
                  colour_edges: np.ndarray, lambda_rel: float = LAMBDA_REL,
                  strides: tuple = (2, 3, 4), min_rel: float = 1.0, max_angle_deg: float = 20.0,
                  min_length_px: int = 30) -> np.ndarray:
    """(H, W) bool: colour-edge pixels at a rounded step of `depth` (module doc).

    depth (H, W) z-depth, 0 = none; points/normals (H, W, 3) camera space; colour_edges (H, W)
    bool. Pieces (8-connected) shorter than `min_length_px` pixels are dropped. A pair (i, j) = (p - s, p + s) along x or y is a step when both have depth, their normals
    are within `max_angle_deg`, and Eq. 1's dt exceeds min_rel * lambda (lambda of Eq. 1)."""
    import cv2

    depth = np.asarray(depth, dtype=np.float64)
    h, w = depth.shape
    if points.shape != (h, w, 3) or normals.shape != (h, w, 3) or colour_edges.shape != (h, w):
        raise ValueError(f"shape mismatch: depth {depth.shape}, points {points.shape}, normals "
                         f"{normals.shape}, colour_edges {colour_edges.shape}")
    valid = depth > 0
    cos_max = np.cos(np.radians(max_angle_deg))
    out = np.zeros((h, w), bool)
    for s in strides:
        if 2 * s >= min(h, w):
            continue
        step = np.zeros((h, w), bool)
        for axis in (0, 1):
            a = (slice(None), slice(0, -2 * s)) if axis == 1 else (slice(0, -2 * s), slice(None))
            b = (slice(None), slice(2 * s, None)) if axis == 1 else (slice(2 * s, None), slice(None))
            c = (slice(None), slice(s, -s)) if axis == 1 else (slice(s, -s), slice(None))
            # both planes must see the other point off-plane (min, not Eq. 1's max): for two
            # parallel planes offset by h both are h, for normal noise on one side only one is large
            d = points[a] - points[b]
            dt = np.minimum(np.abs(dot3(d, normals[a])), np.abs(dot3(d, normals[b])))
            lam = lambda_rel * np.maximum(1.0, np.minimum(depth[a], depth[b]))
            par = np.abs(dot3(normals[a], normals[b])) >= cos_max
            step[c] |= valid[a] & valid[b] & par & (dt > min_rel * lam)
        k = np.ones((2 * s + 1, 2 * s + 1), np.uint8)
        out |= cv2.dilate(step.astype(np.uint8), k).astype(bool)
    out &= np.asarray(colour_edges, bool) & valid
    if min_length_px > 1 and out.any():
        # an occlusion edge is a long line; blobs of texture (spots, letters) give short pieces
        n, lab, stats, _ = cv2.connectedComponentsWithStats(out.astype(np.uint8), connectivity=8)
        keep = stats[:, cv2.CC_STAT_AREA] >= min_length_px
        keep[0] = False
        out = keep[lab]
    return out


def canny_edges(image: np.ndarray, thresholds: tuple = (40, 100), blur_sigma: float = 1.0) -> np.ndarray:
    """(H, W) bool Canny edges (OpenCV, no model) of a linear RGB image in [0, 1], on the same
    sqrt-encoded, Gaussian-blurred grey image as `geodesic.colour_edge_map`."""
    import cv2

    from .geodesic import encode_for_edges

    enc = encode_for_edges(image, blur_sigma)
    grey = cv2.cvtColor((enc * 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)
    return cv2.Canny(grey, *thresholds) > 0
