"""Per-view surface meshes from refined depth (Xu et al. §4.2.3).

"We initialize a triangle mesh by converting each pixel square into two triangles. We then apply
[Garland and Heckbert 1997] to simplify the mesh ... we preserve mesh edges along depth occlusion
edges by increasing their quadric error by a factor of 400-500."

fast-simplification (Garland-Heckbert quadrics) has no per-edge weights, so the occlusion edges are
preserved by construction instead: a triangle that has a side across an Eq. 1 depth edge is not
created (the grid is cut there and never stretched across the edge), and the simplification runs with
`preserve_border=True`, so every vertex on a cut (and on the image frame) survives. The diagonal of
each pixel square is chosen so that it does not cross an edge where the other one would not.
The simplification target adapts to content: the mesh is simplified through a halving sequence of
targets, each step from the previous result, and the smallest mesh whose depth (ray cast into the
view) stays within the error tolerance of the refined depth is kept: a flat wall ends with few
triangles, a cluttered view with many.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..scene import Camera
from .depth_edges import PairEdges
from .grid_faces import grid_faces, quadtree_faces


def reindex(n_vertices: int, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(sorted indices of the vertices some face uses, faces re-indexed onto them); a boolean
    scatter, ~6x faster than np.unique's sort on a 600 k-face pixel grid."""
    used = np.zeros(n_vertices, bool)
    used[np.asarray(faces).reshape(-1)] = True
    used = np.flatnonzero(used)
    remap = np.full(n_vertices, -1, np.int64)
    remap[used] = np.arange(len(used))
    return used, remap[faces]


def compact(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drop vertices no face uses; returns (vertices, re-indexed faces)."""
    used, f = reindex(len(vertices), faces)
    return vertices[used], f


# Sub-pixel offsets (pixels) of the re-cast rays: along no grid-edge direction (horizontal,
# vertical, the two diagonals), so a ray that slipped through a shared vertex lands inside a
# triangle next to it; far above float32 resolution, far below any depth change that matters.
SLIP_OFFSETS = ((0.01, 0.004), (-0.01, -0.004), (0.004, -0.01), (-0.004, 0.01))


class DepthRenderer:
    """z-depth images of world-space meshes seen by one camera, by open3d ray casting through the
    pixel centres (the rays are built once, for the several meshes of simplify_adaptive).

    A ray through a pixel centre that is exactly a mesh vertex (every vertex of a pixel-grid
    mesh; the border vertices that simplification preserves) can slip between the triangles
    (seen on view_mesh's 640x480 grids; tests/view_depth); missed pixels are re-cast at tiny
    sub-pixel offsets (SLIP_OFFSETS), so a pixel counts as covered when its centre lies on the
    closed mesh. Only misses next to a hit are re-cast (a slipped ray's neighbours are covered),
    so a mesh covering a small part of the view costs no more.

    `method` "auto": a mesh wholly in front of the camera is scan-converted instead
    (geometry/rasterize.py: same depths, no slipped rays, ~10x faster); "raycast": always open3d
    (the benchmark's independent measurement)."""

    def __init__(self, camera: Camera, method: str = "auto"):
        if method not in ("auto", "raycast"):
            raise ValueError(f"method must be 'auto' or 'raycast', got {method!r}")
        self.camera, self.method = camera, method
        self._rays = None

    def _build_rays(self) -> None:
        import open3d as o3d

        from . import raycast

        o, d = raycast.camera_rays(self.camera)
        self._rays = o3d.core.Tensor(np.concatenate([o, d], axis=1).astype(np.float32))
        self._zdir = d @ self.camera.viewing_direction  # depth = range * zdir
        self._uv = self.camera.pixel_grid().reshape(-1, 2)

    def render(self, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
        from scipy.ndimage import binary_dilation

        from . import raycast

        cam = self.camera
        if len(faces) == 0:
            return np.zeros((cam.height, cam.width))
        if self.method == "auto":
            from .rasterize import try_raster_depth

            out = try_raster_depth(vertices, faces, cam)
            if out is not None:
                return out
        if self._rays is None:
            self._build_rays()
        scene = raycast.build_scene(vertices, faces)
        t = scene.cast_rays(self._rays)["t_hit"].numpy().astype(np.float64)
        z = t * self._zdir
        out = np.where(np.isfinite(z) & (z > 0), z, 0.0)
        near_hit = binary_dilation((out > 0).reshape(cam.height, cam.width), np.ones((3, 3), bool))
        near_hit = near_hit.reshape(-1)
        for off in SLIP_OFFSETS:
            miss = np.flatnonzero((out == 0) & near_hit)
            if len(miss) == 0:
                break
            o, d = raycast.camera_rays(cam, self._uv[miss] + off)
            out[miss] = raycast.hit_depth(raycast.cast(scene, o, d)["t_hit"], d, cam)
        return out.reshape(cam.height, cam.width)


def render_depth(vertices: np.ndarray, faces: np.ndarray, camera: Camera,
                 method: str = "raycast") -> np.ndarray:
    """(H, W) z-depth of a world-space mesh seen by `camera` (0 = miss); see DepthRenderer
    (open3d ray casting by default: the benchmark's measurement, independent of the rasteriser
    that simplify_adaptive uses)."""
    return DepthRenderer(camera, method).render(vertices, faces)


def depth_error(mesh_depth: np.ndarray, ref_depth: np.ndarray, region: np.ndarray | None = None,
                miss_rel: float = 0.05) -> dict:
    """Error of a mesh's rendered depth against a reference over the reference's valid pixels
    (optionally within `region`): median and mean absolute error of the pixels both cover, coverage,
    and `score` = mean of min(|dd| / d, miss_rel) with misses counted as miss_rel."""
    if mesh_depth.shape != ref_depth.shape:
        raise ValueError(f"depth shapes differ: {mesh_depth.shape} vs {ref_depth.shape}")
    ref_ok = ref_depth > 0 if region is None else (ref_depth > 0) & region
    n = int(ref_ok.sum())
    if n == 0:
        return {"pixels": 0, "coverage": float("nan"), "median_m": float("nan"),
                "mean_m": float("nan"), "score": float("nan")}
    hit = ref_ok & (mesh_depth > 0)
    err = np.abs(mesh_depth - ref_depth)
    rel = np.where(hit, np.minimum(err / np.maximum(ref_depth, 1e-9), miss_rel), miss_rel)[ref_ok]
    e = err[hit]
    return {"pixels": n, "coverage": float(hit.sum() / n),
            "median_m": float(np.median(e)) if len(e) else float("nan"),
            "mean_m": float(e.mean()) if len(e) else float("nan"), "score": float(rel.mean())}


@dataclass
class SimplifyResult:
    vertices: np.ndarray
    faces: np.ndarray
    grid_vertices: int
    grid_faces: int
    steps: list  # [{target, vertices, faces, score}] tried, in order


def simplify_adaptive(vertices: np.ndarray, faces: np.ndarray, camera: Camera,
                      ref_depth: np.ndarray | None, max_vertices: int, min_vertices: int = 200,
                      tol_score: float = 0.002, agg: float = 7.0,
                      mesh_depth: np.ndarray | None = None) -> SimplifyResult:
    """Quadric simplification (fast-simplification, preserve_border=True) to at most
    `max_vertices`, then through halving targets while the rendered depth's score (`depth_error`)
    stays within `tol_score` of the grid mesh's score (i.e. the mean relative depth error grows by
    at most tol_score); the last mesh within tolerance is returned. `ref_depth` None: the
    reference is the input mesh's own depth in `camera`. `mesh_depth`: that depth when the caller
    knows it exactly (a pixel-grid mesh: `grid_mesh_depth`), else it is ray cast once."""
    import fast_simplification as fs

    if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"expected (V, 3) vertices and (F, 3) faces, got {vertices.shape}, {faces.shape}")
    nv0, nf0 = len(vertices), len(faces)
    steps = []
    if nf0 == 0:
        return SimplifyResult(vertices, faces, nv0, nf0, steps)
    if mesh_depth is not None and mesh_depth.shape != (camera.height, camera.width):
        raise ValueError(f"mesh_depth {mesh_depth.shape} does not match camera {camera.width}x{camera.height}")
    renderer = DepthRenderer(camera)
    grid_depth = renderer.render(vertices, faces) if mesh_depth is None else mesh_depth
    if ref_depth is None:
        ref_depth = grid_depth
    base = depth_error(grid_depth, ref_depth)["score"]

    def simp(v, f, target_faces):
        if target_faces >= len(f):
            return v, f
        v2, f2 = fs.simplify(v.astype(np.float32), f.astype(np.int32), target_count=int(target_faces),
                             agg=agg, preserve_border=True)
        return compact(np.asarray(v2, np.float64), np.asarray(f2, np.int64))

    # a triangle mesh has ~2 faces per vertex
    v, f = simp(vertices, faces, 2 * max_vertices) if nv0 > max_vertices else (vertices, faces)
    best = (v, f)
    target = len(f)
    while True:
        score = depth_error(renderer.render(v, f), ref_depth)["score"]
        steps.append({"target_faces": int(target), "vertices": int(len(v)), "faces": int(len(f)),
                      "score": round(float(score), 6)})
        if score > base + tol_score and len(steps) > 1:
            break
        best = (v, f)
        target = len(f) // 2
        if len(v) <= min_vertices or target < 2 * min_vertices:
            break
        v2, f2 = simp(v, f, target)
        if len(f2) > 0.9 * len(f):  # the border-preserving simplification cannot go further
            break
        v, f = v2, f2
    return SimplifyResult(best[0], best[1], nv0, nf0, steps)


def grid_mesh(depth: np.ndarray, camera: Camera, edges: PairEdges,
              return_depth: bool = False, premerge_tol: float = 0.0):
    """World-space (vertices (V, 3), faces (F, 3)) of the cut pixel-grid mesh of a depth image;
    with `return_depth` also the mesh's own (H, W) depth in `camera` (see grid_mesh_depth) and the
    pre-merge report. `premerge_tol` > 0: planar blocks merged first (grid_faces.quadtree_faces; the depth
    returned is then the grid's, which the merged mesh matches within ~2 premerge_tol)."""
    from .normals import points_from_depth

    depth = np.asarray(depth, dtype=np.float64)
    if depth.shape != (camera.height, camera.width):
        raise ValueError(f"depth {depth.shape} does not match camera {camera.width}x{camera.height}")
    if premerge_tol > 0:
        faces, grid_used, report = quadtree_faces(depth, edges, premerge_tol)
        grid_used = np.flatnonzero(grid_used)
    else:
        faces = grid_faces(depth > 0, edges)
        report = {"grid_faces": int(len(faces)), "leaves": {}, "merged_fraction": 0.0}
    used, f = reindex(depth.size, faces)
    P = points_from_depth(depth, camera.K).reshape(-1, 3)[used]
    v = (P - camera.t) @ camera.R
    if not return_depth:
        return v, f
    # the unmerged grid mesh's own depth (exact, see grid_mesh_depth); merged blocks render within
    # ~2 premerge_tol of it
    return v, f, grid_mesh_depth(depth, grid_used if premerge_tol > 0 else used), report


def grid_mesh_depth(depth: np.ndarray, used: np.ndarray) -> np.ndarray:
    """The depth a pixel-grid mesh shows in its own camera, without ray casting: its vertices are
    the pixel centres, so the ray of pixel p meets the mesh exactly at vertex p when some face uses
    it (no other triangle can be in front: each one projects onto its own pixel square), and
    misses it otherwise. `used`: flat pixel indices of the used vertices."""
    out = np.zeros(depth.size)
    out[used] = np.asarray(depth, np.float64).reshape(-1)[used]
    return out.reshape(depth.shape)
