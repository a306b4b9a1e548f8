"""Depth-edge detection (Xu et al. §4.2.1, Eq. 1) and the refinement mask.

Eq. 1: neighbours i, j are separated by a depth edge when their mutual planar distance
    dt_ij = max(|(v_i - v_j) . n_i|, |(v_i - v_j) . n_j|)
exceeds lambda = 0.01 * max(1, min(d_i, d_j)) (metres). A pair with exactly one valid depth
(depth 0 = no surface) is an edge too. The refinement mask is the fronto-parallel square of side
4 cm around every depth-edge pixel, in pixels of the current view: half side = 0.02 m * f / d.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .normals import dot3

LAMBDA_REL = 0.01       # Xu §4.2.1: lambda = 0.01 * max(1, min(d_i, d_j))
LAMBDA_REL_MVS = 0.05   # ours, where G came from multi-view stereo: about twice its depth
                        # noise (~2-3 %), so that noise makes no edge (docs/VIEW_DEPTH.md)
MASK_SIDE_M = 0.04      # Xu §4.2.1: fronto-parallel square patch of side 4 cm


@dataclass
class PairEdges:
    """Depth edges between neighbouring pixels: right (H, W-1), down (H-1, W), and the two
    diagonals of each pixel square: down-right (H-1, W-1) and down-left (H-1, W-1) (pixel (y, x+1)
    to (y+1, x))."""

    right: np.ndarray
    down: np.ndarray
    diag: np.ndarray
    anti: np.ndarray

    def pixels(self) -> np.ndarray:
        """(H, W) bool: pixels on either side of a 4-neighbour depth edge."""
        h, w = self.down.shape[0] + 1, self.right.shape[1] + 1
        out = np.zeros((h, w), bool)
        out[:, :-1] |= self.right
        out[:, 1:] |= self.right
        out[:-1, :] |= self.down
        out[1:, :] |= self.down
        return out

    def between_surfaces(self, valid: np.ndarray) -> "PairEdges":
        """The edges whose two pixels both have depth (`valid` (H, W) bool): occlusion edges and
        creases, without the borders of regions with no depth."""
        v = np.asarray(valid, bool)
        if v.shape != (self.down.shape[0] + 1, self.right.shape[1] + 1):
            raise ValueError(f"valid must be {(self.down.shape[0] + 1, self.right.shape[1] + 1)}, got {v.shape}")
        return PairEdges(self.right & v[:, :-1] & v[:, 1:], self.down & v[:-1, :] & v[1:, :],
                         self.diag & v[:-1, :-1] & v[1:, 1:], self.anti & v[:-1, 1:] & v[1:, :-1])


def planar_distance(pi: np.ndarray, pj: np.ndarray, ni: np.ndarray, nj: np.ndarray) -> np.ndarray:
    """Eq. 1: max(|(v_i - v_j) . n_i|, |(v_i - v_j) . n_j|) for arrays of shape (..., 3)."""
    if not (pi.shape == pj.shape == ni.shape == nj.shape) or pi.shape[-1] != 3:
        raise ValueError(f"expected equal (..., 3) arrays, got {pi.shape} {pj.shape} {ni.shape} {nj.shape}")
    d = pi - pj
    return np.maximum(np.abs(dot3(d, ni)), np.abs(dot3(d, nj)))


def _pair(points, normals, depth, a, b, lam_rel):
    valid = depth > 0
    dt = planar_distance(points[a], points[b], normals[a], normals[b])
    lam = lam_rel * np.maximum(1.0, np.minimum(depth[a], depth[b]))  # Xu Eq. 1 threshold
    both = valid[a] & valid[b]
    return np.where(both, dt > lam, valid[a] ^ valid[b])


def depth_edges(points: np.ndarray, normals: np.ndarray, depth: np.ndarray,
                lambda_rel: float = LAMBDA_REL) -> PairEdges:
    """Eq. 1 depth edges of a depth image. points/normals (H, W, 3) in one frame (camera space),
    depth (H, W) z-depth (0 = none)."""
    depth = np.asarray(depth, dtype=np.float64)
    if depth.ndim != 2 or points.shape != depth.shape + (3,) or normals.shape != points.shape:
        raise ValueError(f"need depth (H, W) and points/normals (H, W, 3), got {depth.shape}, "
                         f"{points.shape}, {normals.shape}")
    s = slice(None)
    right = _pair(points, normals, depth, (s, slice(0, -1)), (s, slice(1, None)), lambda_rel)
    down = _pair(points, normals, depth, (slice(0, -1), s), (slice(1, None), s), lambda_rel)
    diag = _pair(points, normals, depth, (slice(0, -1), slice(0, -1)), (slice(1, None), slice(1, None)),
                 lambda_rel)
    anti = _pair(points, normals, depth, (slice(0, -1), slice(1, None)), (slice(1, None), slice(0, -1)),
                 lambda_rel)
    return PairEdges(right, down, diag, anti)


def refinement_mask(edge_pixels: np.ndarray, depth: np.ndarray, focal_px: float,
                    side_m: float = MASK_SIDE_M, min_half_px: int = 1,
                    max_half_px: int = 64) -> np.ndarray:
    """Xu §4.2.1: union of fronto-parallel squares of side `side_m` centred at each edge pixel,
    in pixels: half side = round(side_m / 2 * f / d_i), clamped to [min_half_px, max_half_px].
    Edge pixels without depth use the smallest depth around them (the near side)."""
    import cv2

    e = np.asarray(edge_pixels, bool)
    depth = np.asarray(depth, dtype=np.float64)
    if e.shape != depth.shape or e.ndim != 2:
        raise ValueError(f"edge_pixels and depth must both be (H, W), got {e.shape}, {depth.shape}")
    if not focal_px > 0 or not side_m > 0:
        raise ValueError(f"focal_px and side_m must be positive, got {focal_px}, {side_m}")
    d = np.where(depth > 0, depth, np.inf)
    d = -cv2.dilate(-np.where(np.isfinite(d), d, 1e9).astype(np.float32), np.ones((3, 3), np.uint8))
    with np.errstate(divide="ignore"):
        half = np.rint(0.5 * side_m * focal_px / np.maximum(d, 1e-6))
    half = np.clip(half, min_half_px, max_half_px).astype(np.int32)
    mask = np.zeros(e.shape, np.uint8)
    for r in np.unique(half[e]):
        src = (e & (half == r)).astype(np.uint8)
        k = np.ones((2 * int(r) + 1, 2 * int(r) + 1), np.uint8)
        mask |= cv2.dilate(src, k)
    return mask.astype(bool)
