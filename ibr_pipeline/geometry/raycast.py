"""Thin helpers around open3d's `RaycastingScene` (CPU BVH ray casting).

`t_hit` from open3d is the ray parameter: a range in metres only when the direction is a unit
vector (`camera_rays` returns unit directions). Shadow/visibility tests use unnormalised
directions with `tfar < 1` so that the segment ends just before its target.
"""
from __future__ import annotations

import numpy as np

from ..scene import Camera
from .normals import dot3


def build_scene(vertices: np.ndarray, triangles: np.ndarray):
    """An open3d RaycastingScene over one triangle mesh ((V, 3) float, (F, 3) int)."""
    import open3d as o3d

    vertices = np.ascontiguousarray(vertices, dtype=np.float32)
    triangles = np.ascontiguousarray(triangles, dtype=np.uint32)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or triangles.ndim != 2 or triangles.shape[1] != 3:
        raise ValueError(f"expected (V, 3) vertices and (F, 3) triangles, got "
                         f"{vertices.shape} and {triangles.shape}")
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices), o3d.core.Tensor(triangles))
    return scene


def pixel_directions(camera: Camera, uv: np.ndarray | None = None) -> np.ndarray:
    """World-space directions (N, 3) through the (N, 2) pixel positions `uv` (default: every
    pixel centre, N = H*W, row-major), scaled so that their z in the camera is 1 (a ray
    parameter along them is a z-depth)."""
    uv = camera.pixel_grid().reshape(-1, 2) if uv is None else np.asarray(uv, np.float64)
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise ValueError(f"uv must be (N, 2), got {uv.shape}")
    # R^T K^-1 [u, v, 1] for each row, as one (3, 3) map applied to u, v plus a constant
    M = camera.R.T @ np.linalg.inv(camera.K)
    # elementwise, not a (N, 2) @ (2, 3) product: BLAS was slow on it under load
    return uv[:, :1] * M[:, 0] + uv[:, 1:] * M[:, 1] + M[:, 2]


def camera_rays(camera: Camera, uv: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """World-space ray origins (N, 3) and unit directions (N, 3) through the (N, 2) pixel
    positions `uv` (default: every pixel centre, N = H*W, row-major)."""
    d_world = pixel_directions(camera, uv)
    d_world /= np.sqrt(np.einsum("ij,ij->i", d_world, d_world))[:, None]
    origins = np.broadcast_to(camera.center, d_world.shape).copy()
    return origins, d_world


def hit_depth(t_hit: np.ndarray, directions: np.ndarray, camera: Camera) -> np.ndarray:
    """z-depth (scene.py convention) of hits at ranges `t_hit` along unit `directions` from the
    camera centre; 0 where the ray missed (open3d's t_hit is a range, not a depth)."""
    z = t_hit * (directions @ camera.viewing_direction)
    return np.where(np.isfinite(z) & (z > 0), z, 0.0)


def render_depth(scene, camera: Camera) -> np.ndarray:
    """(H, W) z-depth image of a prebuilt scene (`build_scene`) seen by `camera`, 0 = miss."""
    o, d = camera_rays(camera)
    return hit_depth(cast(scene, o, d)["t_hit"], d, camera).reshape(camera.height, camera.width)


def cast(scene, origins: np.ndarray, directions: np.ndarray) -> dict[str, np.ndarray]:
    """Cast (N, 3) rays; returns t_hit (inf on miss), primitive_ids (-1 on miss), primitive_uvs."""
    import open3d as o3d

    if origins.shape != directions.shape or origins.ndim != 2 or origins.shape[1] != 3:
        raise ValueError(f"origins and directions must both be (N, 3), got {origins.shape}, "
                         f"{directions.shape}")
    rays = np.concatenate([origins, directions], axis=1).astype(np.float32)
    ans = scene.cast_rays(o3d.core.Tensor(rays))
    t = ans["t_hit"].numpy().astype(np.float64)
    prim = ans["primitive_ids"].numpy().astype(np.int64)
    prim[~np.isfinite(t)] = -1
    return {"t_hit": t, "primitive_ids": prim, "primitive_uvs": ans["primitive_uvs"].numpy()}


def occluded(scene, origins: np.ndarray, targets: np.ndarray, eps: float = 1e-3) -> np.ndarray:
    """(N,) bool: is the open segment origin -> target blocked by any triangle?"""
    d = targets - origins
    rays = np.concatenate([origins, d], axis=1).astype(np.float32)
    import open3d as o3d

    length = float(np.sqrt(dot3(d, d).max())) if len(d) else 1.0
    return scene.test_occlusions(o3d.core.Tensor(rays), tnear=0.0,
                                 tfar=float(1.0 - eps / max(length, 1e-9))).numpy().astype(bool)
