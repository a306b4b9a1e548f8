"""Accuracy / completeness / F-score of a reconstructed mesh against ground truth (Knapitsch et al.
2017, Tanks and Temples: precision = share of reconstructed surface within tau of the truth,
recall = share of the true, *observed* surface within tau of the reconstruction, F = harmonic mean).

The observed true surface is given as points (back-projected ground-truth depth of the capture
views): parts of the room no camera saw cannot be expected in the reconstruction.
"""
from __future__ import annotations

import numpy as np

from ..scene import Camera


def sample_surface(vertices: np.ndarray, faces: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """(n, 3) points sampled uniformly (area-weighted) on a triangle mesh."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"expected (V, 3) vertices and (F, 3) faces, got {v.shape}, {f.shape}")
    if len(f) == 0:
        return np.zeros((0, 3))
    tri = v[f]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    rng = np.random.default_rng(seed)
    idx = rng.choice(len(f), size=n, p=area / area.sum())
    a, b = rng.random((2, n))
    flip = a + b > 1
    a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
    t = tri[idx]
    return t[:, 0] + a[:, None] * (t[:, 1] - t[:, 0]) + b[:, None] * (t[:, 2] - t[:, 0])


def distance_to_mesh(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(N,) unsigned distance of each point to the mesh surface (open3d RaycastingScene)."""
    import open3d as o3d

    from .raycast import build_scene
    if len(faces) == 0:
        return np.full(len(points), np.inf)
    scene = build_scene(vertices, faces)
    q = o3d.core.Tensor(np.ascontiguousarray(points, dtype=np.float32))
    return scene.compute_distance(q).numpy().astype(np.float64)


def observed_points(cameras: list[Camera], depths: list[np.ndarray], stride: int = 2,
                    max_points: int = 200000, seed: int = 0) -> np.ndarray:
    """World points of ground-truth depth maps (every `stride`-th pixel), subsampled."""
    pts = []
    for cam, d in zip(cameras, depths):
        d = np.asarray(d, np.float64)
        cam = cam if cam.size == (d.shape[1], d.shape[0]) else cam.resized(d.shape[1], d.shape[0])
        uv = cam.pixel_grid()[::stride, ::stride].reshape(-1, 2)
        z = d[::stride, ::stride].reshape(-1)
        ok = np.isfinite(z) & (z > 0)
        pts.append(cam.unproject(uv[ok], z[ok]))
    allp = np.concatenate(pts) if pts else np.zeros((0, 3))
    if len(allp) > max_points:
        allp = allp[np.random.default_rng(seed).choice(len(allp), max_points, replace=False)]
    return allp


def fscore(pred_vertices, pred_faces, gt_vertices, gt_faces, gt_points: np.ndarray,
           tau: float = 0.05, n_samples: int = 100000, exclude=None) -> dict:
    """{'precision', 'recall', 'fscore', 'tau', 'excluded'}.

    exclude: optional function (N, 3) -> (N,) bool of reconstructed points to leave out of the
    precision (e.g. mirror-world regions, reported separately by the caller)."""
    pred = sample_surface(pred_vertices, pred_faces, n_samples)
    excluded = 0
    if exclude is not None and len(pred):
        drop = exclude(pred)
        excluded = int(drop.sum())
        pred = pred[~drop]
    if len(pred) == 0:
        return {"precision": 0.0, "recall": 0.0, "fscore": 0.0, "tau": tau, "excluded": excluded}
    p = float(np.mean(distance_to_mesh(pred, gt_vertices, gt_faces) <= tau))
    r = float(np.mean(distance_to_mesh(gt_points, pred_vertices, pred_faces) <= tau))
    f = 0.0 if p + r == 0 else 2 * p * r / (p + r)
    return {"precision": p, "recall": r, "fscore": f, "tau": tau, "excluded": excluded,
            "excluded_fraction": excluded / max(n_samples, 1)}
