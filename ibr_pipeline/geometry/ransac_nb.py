"""Plane RANSAC (Fischler & Bolles 1981) for reflector candidates: hypotheses from 3 random
points, each scored by its inlier count over all points, in one fused numba loop.

open3d's `PointCloud.segment_plane` does the same but spends ~8 ns per point and hypothesis (it
collects every hypothesis's inlier indices): on llff_horns, 30 planes x 1000 hypotheses over
114k samples of G took 27 CPU s, a quarter of the whole `reflectors` stage. Counting in one
pass over coordinate columns does it in a small fraction of that. `count_inliers_np` is the
numpy reference with the same arithmetic, tested against the kernel
(tests/reflection/test_ransac_nb.py).
"""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def _count_inliers(x, y, z, planes, dist, counts):
    n = x.shape[0]
    for m in range(planes.shape[0]):
        a, b, c, d = planes[m, 0], planes[m, 1], planes[m, 2], planes[m, 3]
        if a == 0.0 and b == 0.0 and c == 0.0:  # degenerate sample: no plane
            counts[m] = -1
            continue
        k = 0
        for i in range(n):
            if abs(a * x[i] + b * y[i] + c * z[i] + d) < dist:
                k += 1
        counts[m] = k


def _points(points: np.ndarray) -> np.ndarray:
    P = np.asarray(points, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {P.shape}")
    return P


def _columns(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    P = _points(points)
    return (np.ascontiguousarray(P[:, 0]), np.ascontiguousarray(P[:, 1]),
            np.ascontiguousarray(P[:, 2]))


def _planes(planes: np.ndarray) -> np.ndarray:
    Q = np.ascontiguousarray(planes, dtype=np.float64)
    if Q.ndim != 2 or Q.shape[1] != 4:
        raise ValueError(f"planes must be (M, 4), got {Q.shape}")
    return Q


def count_inliers(points: np.ndarray, planes: np.ndarray, dist: float) -> np.ndarray:
    """points (N, 3), planes (M, 4) as (n, d) with n.x + d the signed distance (n unit, or zero
    for no plane). Returns (M,) int64: points with |n.x + d| < dist; -1 for a zero normal."""
    x, y, z = _columns(points)
    Q = _planes(planes)
    counts = np.empty(len(Q), np.int64)
    _count_inliers(x, y, z, Q, float(dist), counts)
    return counts


def count_inliers_np(points: np.ndarray, planes: np.ndarray, dist: float) -> np.ndarray:
    """`count_inliers` in numpy, the same arithmetic in the same order (the reference)."""
    x, y, z = _columns(points)
    Q = _planes(planes)
    out = np.empty(len(Q), np.int64)
    for m, (a, b, c, d) in enumerate(Q):
        out[m] = -1 if a == b == c == 0.0 else int(np.count_nonzero(np.abs(a * x + b * y + c * z + d) < dist))
    return out


def hypotheses(points: np.ndarray, samples: np.ndarray) -> np.ndarray:
    """Planes (M, 4) through the point triples points[samples] (samples (M, 3) indices), unit
    normals; zero rows where a triple is degenerate (repeated or collinear points)."""
    P = _points(points)
    S = np.asarray(samples)
    if S.ndim != 2 or S.shape[1] != 3:
        raise ValueError(f"samples must be (M, 3), got {S.shape}")
    p0, p1, p2 = P[S[:, 0]], P[S[:, 1]], P[S[:, 2]]
    nrm = np.cross(p1 - p0, p2 - p0)
    length = np.linalg.norm(nrm, axis=1)
    scale = np.maximum(np.linalg.norm(p1 - p0, axis=1) * np.linalg.norm(p2 - p0, axis=1), 1e-300)
    ok = length > 1e-9 * scale  # sine of the triangle's angle at p0 above 1e-9
    out = np.zeros((len(S), 4))
    out[ok, :3] = nrm[ok] / length[ok, None]
    out[ok, 3] = -np.einsum("ij,ij->i", out[ok, :3], p0[ok])
    return out


def best_plane(points: np.ndarray, dist: float, iterations: int,
               rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """One RANSAC plane: `iterations` hypotheses from 3 points drawn by `rng`, the one with most
    inliers (the first of equals). Returns (plane (4,), indices of its inliers); an empty index
    array when no hypothesis is a plane or there are fewer than 3 points."""
    P = _points(points)
    if len(P) < 3:
        return np.zeros(4), np.zeros(0, np.int64)
    Q = hypotheses(P, rng.integers(0, len(P), size=(int(iterations), 3)))
    counts = count_inliers(P, Q, dist)
    m = int(np.argmax(counts))
    if counts[m] <= 0:
        return np.zeros(4), np.zeros(0, np.int64)
    a, b, c, d = Q[m]
    x, y, z = _columns(P)
    return Q[m], np.flatnonzero(np.abs(a * x + b * y + c * z + d) < dist)
