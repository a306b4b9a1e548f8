"""z-depth of a triangle mesh seen by one pinhole camera, by scan conversion (numba).

view_mesh's adaptive simplification (Xu et al. §4.2.3, geometry/grid_mesh.py) renders each
candidate mesh into its own view to score it. open3d's BVH ray casting of 307 k pixel rays costs
~50 ms per render at 640x480 plus the re-casts of rays that slip through shared vertices; a
per-triangle scan conversion does the same job in a few ms (a mesh of a few thousand triangles
covering the image touches each pixel about once) and has no slipped rays: a pixel centre on an
edge or a vertex counts as inside every triangle that has it (inclusive test, EDGE_SLACK_PX), the
z-buffer keeps the nearest. Depth is perspective-correct: over a planar triangle 1/z is affine in the image
coordinates, so 1/z is interpolated with the screen-space barycentrics — at a pixel centre this is
exactly the depth where that pixel's ray meets the triangle's plane (what a ray cast returns).
Both faces of a triangle are drawn (no culling), as ray casting does.

Why not a library: open3d ray casting (above); moderngl/EGL would need a GL context per worker
process, and the runner fans views out over processes and Dask workers; the kernel is ~40 lines.
A mesh with a vertex at or behind the camera plane is not drawn (try_raster_depth says None).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from ..scene import Camera

# slack of the inclusive inside test, in pixels of distance to a triangle's edge: pixel centres on
# an edge or a vertex count as inside, also after the float32 round trip of fast-simplification
# moved the vertex by ~1e-5 px (the ray cast's re-cast offsets are 0.01 px)
EDGE_SLACK_PX = 1e-3


@njit(cache=True)
def _raster(uv, z, faces, h, w, out):
    for t in range(faces.shape[0]):
        i0, i1, i2 = faces[t, 0], faces[t, 1], faces[t, 2]
        x0, y0, x1, y1, x2, y2 = uv[i0, 0], uv[i0, 1], uv[i1, 0], uv[i1, 1], uv[i2, 0], uv[i2, 1]
        area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
        if abs(area) < 1e-12:
            continue
        iz0, iz1, iz2 = 1.0 / z[i0], 1.0 / z[i1], 1.0 / z[i2]
        xa = max(int(math.ceil(min(x0, min(x1, x2)) - EDGE_SLACK_PX)), 0)
        xb = min(int(math.floor(max(x0, max(x1, x2)) + EDGE_SLACK_PX)), w - 1)
        ya = max(int(math.ceil(min(y0, min(y1, y2)) - EDGE_SLACK_PX)), 0)
        yb = min(int(math.floor(max(y0, max(y1, y2)) + EDGE_SLACK_PX)), h - 1)
        inv = 1.0 / area
        # b_k >= -slack_k  <=>  the pixel is at most EDGE_SLACK_PX outside the edge opposite k
        s0 = EDGE_SLACK_PX * math.hypot(x2 - x1, y2 - y1) / abs(area)
        s1 = EDGE_SLACK_PX * math.hypot(x0 - x2, y0 - y2) / abs(area)
        s2 = EDGE_SLACK_PX * math.hypot(x1 - x0, y1 - y0) / abs(area)
        for y in range(ya, yb + 1):
            for x in range(xa, xb + 1):
                b0 = ((x1 - x) * (y2 - y) - (x2 - x) * (y1 - y)) * inv
                b1 = ((x2 - x) * (y0 - y) - (x0 - x) * (y2 - y)) * inv
                b2 = 1.0 - b0 - b1
                if b0 >= -s0 and b1 >= -s1 and b2 >= -s2:
                    iz = b0 * iz0 + b1 * iz1 + b2 * iz2
                    if iz > 0.0:
                        d = 1.0 / iz
                        if d < out[y, x]:
                            out[y, x] = d


def try_raster_depth(vertices: np.ndarray, faces: np.ndarray, camera: Camera) -> np.ndarray | None:
    """(H, W) z-depth of a world-space mesh at the pixel centres (0 = not covered), or None when a
    vertex is at or behind the camera plane (then only a ray cast is right)."""
    vertices, faces = np.asarray(vertices, np.float64), np.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"expected (V, 3) vertices and (F, 3) faces, got {vertices.shape}, {faces.shape}")
    uv, z = camera.project(vertices)
    if len(z) and not np.min(z) > 1e-9:
        return None
    out = np.full((camera.height, camera.width), np.inf)
    if len(faces):
        _raster(uv, z, faces.astype(np.int64), camera.height, camera.width, out)
    out[~np.isfinite(out)] = 0.0
    return out


def raster_depth(vertices: np.ndarray, faces: np.ndarray, camera: Camera) -> np.ndarray:
    """try_raster_depth for a mesh that must be wholly in front of the camera."""
    out = try_raster_depth(vertices, faces, camera)
    if out is None:
        raise ValueError("raster_depth: a vertex is at or behind the camera plane (use a ray cast)")
    return out
