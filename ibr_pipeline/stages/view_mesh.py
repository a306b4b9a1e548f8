"""Stage `view_mesh` (Xu et al. §4.2.3), per view: the refined depth as a pixel-grid mesh (two
triangles per pixel square, cut along Eq. 1 occlusion edges), quadric-simplified with
fast-simplification (border preserved, so the cuts survive) to no more vertices than the view needs,
after a planar pre-merge of blocks of pixel squares (geometry/grid_faces.py: ~5x less input).
Mathematics: geometry/grid_mesh.py.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

from .. import layout as L
from ..config import StageConfig, param
from ..runner import Stage, StageContext
from ..geometry import depth_edges as de
from .common import eq1_lambda, registered_views


@dataclass(frozen=True)
class ViewMeshConfig(StageConfig):
    max_vertices_640x480: int = param(20000, "vertex budget per view, scaled by pixel count from "
                                      "640x480 (Xu §4.2.3: < 40 000 vertices on average; 20 000 = "
                                      "~10k triangles at 320x240, the renderer's frame-time "
                                      "budget)",
                                      min=100, max=10_000_000)
    min_vertices: int = param(200, "never simplify below this many vertices", min=3, max=1_000_000)
    tol_score: float = param(0.002, "adaptive target: accept a coarser mesh while its mean relative "
                             "depth error (misses count 5 per cent) grows by at most this", min=0.0, max=0.05)
    lambda_rel: float = param(de.LAMBDA_REL, "Eq. 1 threshold for the cuts (Xu §4.2.1: 0.01), where G "
                              "was fused from depth frames", min=1e-4, max=0.5)
    lambda_rel_mvs: float = param(de.LAMBDA_REL_MVS, "Eq. 1 threshold for the cuts where G came from "
                                  "multi-view stereo (ours, as view_depth.lambda_rel_mvs)",
                                  min=1e-4, max=0.5)
    agg: float = param(7.0, "fast-simplification aggressiveness", min=0.0, max=10.0)
    premerge_tol: float = param(1e-3, "planar pre-merge before the simplification (ours, "
                                "geometry/grid_faces.py): blocks of pixel squares whose depth is "
                                "planar within this relative deviation (1e-3: a tenth of Eq. 1's "
                                "lambda) become a few triangles; 0 = the paper's full pixel grid",
                                min=0.0, max=0.01)


def run(ctx: StageContext, view: str) -> None:
    import numpy as np

    from ..errors import InputError
    from ..geometry.grid_mesh import grid_mesh, simplify_adaptive
    from ..geometry.normals import normals_from_points, points_from_depth
    from ..io.images import read_image
    from ..io.mesh import Mesh, write_ply

    t0, c0 = time.perf_counter(), time.process_time()
    ws, cfg = ctx.ws, ctx.config
    cam = L.registered_cameras(ws)[view]
    vd = ws.view_dir(view)
    p = ws.path(f"{vd}/{L.DEPTH}")
    try:
        depth = np.load(p).astype(np.float64)
    except (OSError, ValueError) as e:
        raise InputError(f"{p}: cannot read depth ({e})") from None
    if depth.shape != (cam.height, cam.width) or not np.all(np.isfinite(depth)):
        raise InputError(f"{p}: depth must be finite {cam.height}x{cam.width}, got {depth.shape}")
    edges_png = read_image(ws.path(f"{vd}/{L.EDGES}"))
    if edges_png.shape[:2] != depth.shape:
        raise InputError(f"{ws.path(f'{vd}/edges.png')}: size differs from depth.npy")
    P = points_from_depth(depth, cam.K)
    N = normals_from_points(P, depth > 0)
    pairs = de.depth_edges(P, N, depth, eq1_lambda(ctx, view))  # cuts: Eq. 1 pairs of the refined depth
    # the grid mesh's own depth is known exactly (vertices at the pixel centres): no ray cast of
    # its ~600 k triangles at 640x480 for the base score (that ray cast was the stage's largest cost)
    v, f, grid_depth, premerge = grid_mesh(depth, cam, pairs, return_depth=True,
                                           premerge_tol=cfg.premerge_tol)
    budget = max(cfg.min_vertices, int(round(cfg.max_vertices_640x480 * cam.width * cam.height / (640 * 480))))
    res = simplify_adaptive(v, f, cam, depth, budget, cfg.min_vertices, cfg.tol_score, cfg.agg,
                            mesh_depth=grid_depth)
    write_ply(ws.path(f"{vd}/{L.MESH}"), Mesh(res.vertices, res.faces), comment=f"view_mesh {view}")
    ws.write_json(f"{vd}/{L.MESH_REPORT}", {
        "view": view, "edge_pixels": int((edges_png.mean(axis=2) > 0.5).sum()),
        "grid_faces": premerge["grid_faces"],
        "input_vertices": res.grid_vertices, "input_faces": res.grid_faces,  # after the pre-merge
        "vertices": int(len(res.vertices)), "faces": int(len(res.faces)), "budget_vertices": budget,
        "premerge": premerge, "steps": res.steps, "ms": round(1000 * (time.perf_counter() - t0), 1),
        "cpu_ms": round(1000 * (time.process_time() - c0), 1)})


def view_inputs(ctx: StageContext, view: str) -> list[str]:
    vd = ctx.ws.view_dir(view)
    keys = [f"{vd}/{L.DEPTH}", f"{vd}/{L.EDGES}"]
    if ctx.ws.exists(L.mvs_depth_file(view)):  # its presence picks Eq. 1's lambda (eq1_lambda)
        keys.append(L.mvs_depth_file(view))
    return keys


STAGE = Stage(name="view_mesh", help="quadric-simplified per-view meshes cut along occlusion edges",
              config=ViewMeshConfig, version="5", run=run, per_view=True,
              inputs=(L.REGISTERED_CAMERAS,),
              view_inputs=view_inputs,
              view_outputs=("{view_dir}/" + L.MESH, "{view_dir}/" + L.MESH_REPORT),
              views=registered_views)
