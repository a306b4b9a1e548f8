"""Per-pixel 3D points and normals from a z-depth image (Xu et al. §4.2.1: "for each pixel i in the
depth image, we first calculate its vertex position v_i and normal n_i according to its depth d_i").

Conventions (scene.py): OpenCV camera axes, z-depth in metres, 0 = no depth, pixel centre (0, 0).
"""
from __future__ import annotations

import numpy as np

from ..scene import Camera


def _check_depth(depth: np.ndarray) -> np.ndarray:
    d = np.asarray(depth)
    if d.ndim != 2:
        raise ValueError(f"depth must be (H, W), got shape {d.shape}")
    return d.astype(np.float64)


def dot3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Dot products along the last axis of (..., 3) arrays: np.sum(a * b, -1) written out, the
    same sum in the same order (so the same bits), without numpy's per-element reduction loop
    over a length-3 axis, which was a large share of view_depth."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def pixel_rays(K: np.ndarray, height: int, width: int) -> np.ndarray:
    """(H, W, 3) camera-space rays with z = 1 through every pixel centre."""
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"K must be (3, 3), got {K.shape}")
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    x = (u - K[0, 2] - K[0, 1] * (v - K[1, 2]) / K[1, 1]) / K[0, 0]
    y = (v - K[1, 2]) / K[1, 1]
    return np.stack([x, y, np.ones_like(x)], axis=-1)


def points_from_depth(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(H, W, 3) camera-space points v_i = d_i * K^-1 [u, v, 1] (zero where depth is 0)."""
    d = _check_depth(depth)
    return pixel_rays(K, *d.shape) * d[..., None]


def normals_from_points(points: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(H, W, 3) unit normals (camera space, facing the camera) from a grid of points.

    Per axis the one-sided difference with the smaller depth change is used, so a pixel next to an
    occlusion edge takes the tangent of its own surface, not the jump across the edge. Pixels with
    no valid neighbour on an axis, or invalid themselves, get the normal -ray (fronto-parallel)."""
    P = np.asarray(points, dtype=np.float64)
    if P.ndim != 3 or P.shape[2] != 3 or valid.shape != P.shape[:2]:
        raise ValueError(f"points must be (H, W, 3) and valid (H, W), got {P.shape}, {valid.shape}")
    big = np.inf

    def tangent(axis: int) -> np.ndarray:
        fwd = np.zeros_like(P)
        bwd = np.zeros_like(P)
        okf = np.zeros(valid.shape, bool)
        okb = np.zeros(valid.shape, bool)
        sl = [slice(None)] * 2
        a, b = list(sl), list(sl)
        a[axis], b[axis] = slice(1, None), slice(None, -1)
        a, b = tuple(a), tuple(b)
        diff = P[a] - P[b]                       # P[i+1] - P[i]
        pair_ok = valid[a] & valid[b]
        fwd[b], okf[b] = diff, pair_ok           # forward difference at i
        bwd[a], okb[a] = diff, pair_ok           # backward difference at i+1
        cf = np.where(okf, np.abs(fwd[..., 2]), big)
        cb = np.where(okb, np.abs(bwd[..., 2]), big)
        t = np.where((cf <= cb)[..., None], fwd, bwd)
        return t, okf | okb

    tx, okx = tangent(1)
    ty, oky = tangent(0)
    n = np.cross(ty, tx)  # x right, y down: cross(dy, dx) points towards the camera (-z)
    norm = np.sqrt(dot3(n, n))[..., None]
    good = valid & okx & oky & (norm[..., 0] > 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        n = np.where(good[..., None], n / np.where(norm > 0, norm, 1.0), 0.0)
    ray = P / np.maximum(np.sqrt(dot3(P, P))[..., None], 1e-12)
    flip = dot3(n, ray) > 0  # must face the camera
    n[flip] *= -1
    default = -ray
    default[~valid] = (0.0, 0.0, -1.0)
    return np.where(good[..., None], n, default)


def normals_from_depth(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(H, W, 3) camera-space unit normals of a z-depth image (see normals_from_points)."""
    d = _check_depth(depth)
    return normals_from_points(points_from_depth(d, K), d > 0)


def world_normals(normals_cam: np.ndarray, camera: Camera) -> np.ndarray:
    """Rotate (H, W, 3) camera-space normals to world space (n_w = R^T n_c)."""
    n = np.asarray(normals_cam)
    if n.ndim != 3 or n.shape[2] != 3:
        raise ValueError(f"normals must be (H, W, 3), got {n.shape}")
    return n @ camera.R
