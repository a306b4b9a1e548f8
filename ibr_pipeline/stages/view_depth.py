"""Stage `view_depth` (Xu et al. §4.2.1-4.2.2), per view: render the global mesh G into the view
(taking the view's own MVS depth where it lies well in front of G: a surface the fusion missed),
detect depth edges (Eq. 1), build the 4 cm refinement mask, refine inside it (masked multi-view
stereo, then Eq. 2 geodesic interpolation over a colour-edge cost map), complete what G leaves
empty (the view's MVS depth, then edge-aware interpolation), write depth/normals/edges.

Optional user strokes (Xu §4.2.2 "we also allow users to specify edges"): `input/strokes/<image
stem>.png`, an 8-bit grey image of the view's size, white (> 127) = an occlusion edge the
interpolation must not cross. Mathematics: geometry/{normals,depth_edges,geodesic,depth_refine}.py.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from .. import layout as L
from ..cache import ProcessCache, file_key
from ..config import StageConfig, param
from ..runner import Stage, StageContext
from ..geometry import depth_edges as de
from ..geometry.depth_complete import PlaneOptions
from .common import eq1_lambda, registered_views

OUTPUTS = (L.DEPTH_INIT, L.DEPTH, L.NORMAL, L.EDGES, L.REFINE_MASK, L.DEPTH_REPORT)


@dataclass(frozen=True)
class ViewDepthConfig(StageConfig):
    lambda_rel: float = param(de.LAMBDA_REL, "Eq. 1 threshold: lambda = lambda_rel * max(1, min(d_i, d_j)) "
                              "(Xu §4.2.1: 0.01), where G was fused from depth frames", min=1e-4, max=0.5)
    lambda_rel_mvs: float = param(de.LAMBDA_REL_MVS, "Eq. 1 threshold where G came from multi-view "
                                  "stereo (the view has global/mvs depth; ours: MVS depth is noisier "
                                  "than 1 %, docs/VIEW_DEPTH.md)", min=1e-4, max=0.5)
    mask_side_m: float = param(0.04, "side of the fronto-parallel refinement square around each "
                               "depth-edge pixel, metres (Xu §4.2.1: 4 cm)", min=0.001, max=1.0)
    mask_min_half_px: int = param(1, "smallest half side of the mask square, pixels", min=0, max=32)
    mvs: bool = param(True, "step one of §4.2.2: masked multi-view stereo (plane sweep) before Eq. 2")
    sources: int = param(4, "neighbour views for the masked MVS", min=1, max=16)
    num_depths: int = param(24, "plane-sweep hypotheses per pixel in the search band", min=4, max=256)
    window: int = param(7, "NCC window of the plane sweep, pixels (odd)", min=3, max=21)
    mvs_agree_rel: float = param(0.05, "keep an MVS depth only where the photometric and geometric "
                                 "estimates agree within this fraction (Xu §4.2.2: 5 per cent)", min=0.001, max=1.0)
    mvs_min_consistent: int = param(1, "source views that must agree (geometric stage)", min=1, max=16)
    mvs_check: str = param("near", "geometric check of the MVS depth against G in the source views: "
                           "'near' = G agrees within mvs_agree_rel somewhere within "
                           "mvs_check_radius px of the projection (tolerates G's misplaced edges); "
                           "'roundtrip' = a strict forward-backward check", choices=("near", "roundtrip"))
    mvs_check_radius: int = param(1, "pixel tolerance of the 'near' check (pixels at 320x240, "
                                  "scaled with the image width)", min=0, max=8)
    mvs_min_change: float = param(1.5, "keep G's depth where the MVS depth differs from it by at most "
                                  "this many Eq. 1 lambdas (MVS is noisier than G on surfaces); "
                                  "0 = off", min=0.0, max=100.0)
    mvs_edge_guard: int = param(3, "drop MVS depths within this many pixels (at 320x240, scaled "
                                "with the image width) of an Eq. 1 edge of the MVS depth, where NCC "
                                "windows straddle two surfaces; 0 = off", min=0, max=32)
    neighbours: int = param(4, "Eq. 2: geodesically nearest pixels outside the mask (Xu: 4)", min=1, max=16)
    cost_base: float = param(0.05, "geodesic cost per pixel step on a flat colour region", min=1e-4, max=10.0)
    cost_edge: float = param(15.0, "extra geodesic cost per pixel step across a full-strength colour "
                             "edge (w = exp(-d_g), Eq. 2)", min=0.0, max=1000.0)
    edge_boundary_radius: int = param(4, "Eq. 2 cost map: weight colour edges by the oriented "
                                      "half-disc gradient of this radius (pixels at 320x240, scaled "
                                      "with the width), so texture is cheap to cross and outlines are "
                                      "not: our stand-in for the paper's structured-forest "
                                      "boundaries (geometry/geodesic.py); 0 = plain Sobel + Canny",
                                      min=0, max=32)
    edge_barrier: bool = param(False, "Eq. 2 cost map: add the Eq. 1 depth edges of G after the MVS "
                               "step as barriers, like user strokes (our addition). Off by default: "
                               "it also pins the edge to G's misplaced one (docs/VIEW_DEPTH.md)")
    rounded_steps: bool = param(True, "also refine steps G has rounded into ramps "
                                "(geometry/depth_rounded.py; our addition to Xu §4.2.1)")
    rounded_strides: tuple[int, ...] = param((2, 3, 4), "half distances s of the rounded-step test, "
                                             "pixels at 320x240 on a 2 cm-voxel G (scaled with width "
                                             "x voxel: ramp_scale)")
    g_trust: str = param("far", "where G's depth is trusted inside the mask (ours): 'far' = kept "
                         "without a sweep farther than g_trust_px from G's own Eq. 1 edges and "
                         "rounded steps; 'confirmed' = kept only where the MVS confirms it, and "
                         "then safe from mvs_edge_guard; 'none' = neither (docs/VIEW_DEPTH.md)",
                         choices=("far", "confirmed", "none"))
    g_trust_px: int = param(0, "the distance of g_trust 'far', pixels at 320x240 on a 2 cm-voxel G "
                            "(scaled: ramp_ratio); 0 = automatic, 6 px below 480 px wide, else 4 "
                            "(g_trust_auto)", min=0, max=64)
    ramp_zone_px: int = param(8, "within this distance of a rounded step (pixels at 320x240 on a "
                              "2 cm-voxel G, scaled: ramp_ratio) G's depth is not kept even where "
                              "the MVS confirms it, so Eq. 2 re-interpolates the ramp from the "
                              "plateaus (ours); 0 = off", min=0, max=64)
    rounded_min_rel: float = param(1.0, "rounded-step test threshold, fraction of Eq. 1's lambda",
                                   min=0.1, max=10.0)
    complete: bool = param(True, "fill the pixels G leaves empty (ours, for RGB-only captures): "
                           "the view's own MVS depth, then edge-aware membrane interpolation of "
                           "the rest over Eq. 2's colour-edge cost map (geometry/depth_complete.py)")
    complete_planes: bool = param(True, "completion of views with an MVS depth map: before the "
                                  "membrane, fill colour segments whose known depths one plane "
                                  "explains with that plane (ours, after TAPA-MVS's superpixel "
                                  "planes; geometry/depth_complete.py)")
    planes: PlaneOptions = param(PlaneOptions(), "the segment planes of complete_planes")
    mvs_speckle_px: int = param(20, "completion: drop MVS depth regions of at most this many "
                                "pixels (at 320x240) that no neighbour continues; 0 = off",
                                min=0, max=100000)
    mvs_front_rel: float = param(0.1, "take the view's own MVS depth (global/mvs) where it lies in "
                                 "front of G's by more than this fraction: a surface the fusion "
                                 "missed (docs/VIEW_DEPTH.md); 0 = off", min=0.0, max=0.9)
    mvs_front_px: int = param(200, "mvs_front_rel: smallest region taken (pixels at 320x240)",
                              min=1, max=1000000)
    strokes_dir: str = param("strokes", "input sub-folder with optional occlusion-edge strokes "
                             "(<image stem>.png, white = edge)")
    device: str = param("cpu", "torch device for the plane sweep", choices=("cpu", "cuda"),
                        affects_output=False)
    threads: int = param(1, "torch / OpenCV threads inside one view (views already run in parallel "
                         "with --jobs: more threads per worker oversubscribe the cores)", min=1,
                         max=64, affects_output=False)
    progress: bool = param(False, "progress bars inside a view (the runner shows one per view)",
                           affects_output=False)

    def check(self, prefix: str) -> None:
        from ..errors import ConfigError, escapes
        if self.window % 2 == 0:
            raise ConfigError(prefix + "window", f"must be odd, got {self.window}")
        why = escapes(self.strokes_dir)
        if why:
            raise ConfigError(prefix + "strokes_dir", f"{self.strokes_dir!r} {why}: it names a "
                              "sub-folder of the input folder")


def _strokes_key(ctx: StageContext, view: str) -> str:
    return f"input/{ctx.config.strokes_dir}/{Path(view).with_suffix('').as_posix()}.png"


def _sources(ctx: StageContext, view: str) -> list[str]:
    from ..geometry.mvs import select_sources
    if not ctx.config.mvs:
        return []
    cams = L.registered_cameras(ctx.ws)
    return select_sources(cams[view], cams, k=ctx.config.sources, exclude=(view,))


G_VOXEL_TUNED = 0.02  # the rounded-step strides were tuned on a 2 cm-voxel G at 320x240


def _ramp_width(width: int, g_voxel: float) -> float:
    """Width x G's voxel relative to the 2 cm G at 320x240 (unrounded)."""
    return width / 320 * g_voxel / G_VOXEL_TUNED


def ramp_scale(width: int, g_voxel: float) -> int:
    """Integer factor for the rounded-step strides: a TSDF rounds a step into a ramp about two
    voxels wide, i.e. `voxel * f / z` pixels, so the strides follow width x voxel relative to the
    2 cm G at 320x240 they were tuned on (1 for global_mesh's automatic 1 cm at 640x480 too)."""
    return max(1, int(round(_ramp_width(width, g_voxel))))


def ramp_ratio(width: int, g_voxel: float) -> float:
    """Unrounded width x G's voxel relative to the 2 cm G at 320x240: the factor for the trust
    distance and the ramp zone. Unlike `ramp_scale` (integer strides, at least 1) it
    goes below 1 for a G finer than 1 cm at 640x480, whose edges are misplaced and rounded over
    proportionally fewer pixels: a 5 mm G at 640x480 gives 0.5. It is exactly 1 for the two
    configurations the distances were tuned on (2 cm at 320x240, 1 cm at 640x480)."""
    return round(_ramp_width(width, g_voxel), 3)


def g_trust_auto(width: int) -> int:
    """Automatic g_trust_px: 6 px below 480 px wide, 4 px from 480 (the best of a throw-away sweep of
    3-10 px on every 4th view of the sample and full-size mirror_room benches; docs/VIEW_DEPTH.md)."""
    return 6 if width < 480 else 4


def _g_voxel(ws) -> float:
    """G's TSDF voxel size from global/report.json, else the 2 cm the distances were tuned on; also
    2 cm when G is in SfM units (no depth, no scale), where the voxel is no length in metres."""
    import json
    try:
        rep = json.loads(ws.path(L.GLOBAL_REPORT).read_text())
        if rep.get("units") == "sfm":
            return G_VOXEL_TUNED
        v = rep["voxel_size"]["value"]
        return float(v) if v > 0 else G_VOXEL_TUNED
    except (OSError, KeyError, TypeError, ValueError):
        return G_VOXEL_TUNED


def pixel_scale(width: int) -> int:
    """Integer factor for the pixel-valued parameters, given at the sample's 320x240: 1 up to
    479 px wide, 2 at 640, 4 at 1280."""
    return max(1, int(round(width / 320)))


def view_inputs(ctx: StageContext, view: str) -> list[str]:
    scene = ctx.scene
    keys = [scene.view(view).image] + [scene.view(s).image for s in _sources(ctx, view)]
    if ctx.ws.exists(_strokes_key(ctx, view)):
        keys.append(_strokes_key(ctx, view))
    if ctx.ws.exists(L.mvs_depth_file(view)):  # completion reads it; its presence picks lambda
        keys.append(L.mvs_depth_file(view))
    return keys


_G = ProcessCache(1)         # (mesh, BVH) of the current global mesh
_G_DEPTH = ProcessCache(12)  # G's depth per camera: a view's MVS sources are its neighbours in
                             # the capture order, which are the next views' sources too: ~3 of 4
                             # renders are reused (12 x 2.4 MB at 640x480)
_IMAGES = ProcessCache(12)   # decoded images, for the same reason (12 x 3.7 MB at 640x480)


def _image(path):
    """The image at `path` (linear, as read_image), decoded once per worker process while it stays
    among the last 12 used; read-only, as the G depths."""
    from ..io.images import read_image

    def read():
        img = read_image(path)
        img.setflags(write=False)
        return img
    return _IMAGES.get(file_key(path), read)


def _global_scene(path):
    """(file key, mesh, open3d ray-casting scene) of the global mesh, kept per worker process so
    the views one worker handles load G and build its BVH once."""
    from ..errors import InputError
    from ..geometry.raycast import build_scene
    from ..io.mesh import read_ply

    def load():
        mesh = read_ply(path)
        if len(mesh.faces) == 0:
            raise InputError(f"{path}: the global mesh has no triangles")
        _G_DEPTH.clear()
        return mesh, build_scene(mesh.vertices, mesh.faces)
    key = file_key(path)
    return (key, *_G.get(key, load))


def _g_depth(g_key, scene, camera):
    """G (file key g_key, ray-casting scene) ray cast into `camera` (render_depth), kept per
    worker process: a view renders G into itself and into its MVS sources, and neighbouring views
    share sources."""
    from ..geometry.raycast import render_depth

    def cast():
        d = render_depth(scene, camera)
        d.setflags(write=False)
        return d
    key = (g_key, camera.width, camera.height, camera.K.tobytes(), camera.R.tobytes(),
           camera.t.tobytes())
    return _G_DEPTH.get(key, cast)


def run(ctx: StageContext, view: str) -> None:
    import cv2
    import torch

    prev = torch.get_num_threads(), cv2.getNumThreads()
    torch.set_num_threads(ctx.config.threads)
    cv2.setNumThreads(ctx.config.threads)
    try:
        _run(ctx, view)
    finally:
        torch.set_num_threads(prev[0])
        cv2.setNumThreads(prev[1])


def _run(ctx: StageContext, view: str) -> None:
    import numpy as np

    from ..errors import InputError
    from ..geometry import depth_refine as dr
    from ..geometry import geodesic as geo
    from ..geometry.normals import world_normals
    from ..io.images import read_image, write_image

    t0, c0 = time.perf_counter(), time.process_time()
    ws, cfg = ctx.ws, ctx.config
    lam = eq1_lambda(ctx, view)
    cams = L.registered_cameras(ws)
    cam = cams[view]
    image = _image(ws.path(ctx.scene.view(view).image))
    if image.shape[:2] != (cam.height, cam.width):
        raise InputError(f"{ws.path(ctx.scene.view(view).image)}: image is {image.shape[1]}x"
                         f"{image.shape[0]}, its camera says {cam.width}x{cam.height}")
    g_key, mesh, scene = _global_scene(ws.path(L.GLOBAL_MESH))
    strokes = None
    if ws.exists(_strokes_key(ctx, view)):
        s = read_image(ws.path(_strokes_key(ctx, view)))
        if s.shape[:2] != image.shape[:2]:
            raise InputError(f"{ws.path(_strokes_key(ctx, view))}: strokes must be {cam.width}x{cam.height}")
        strokes = s.mean(axis=2) > 0.5
    timings = {}
    # 1. initial depth: G ray cast into the view (Xu §4.2)
    t = time.perf_counter()
    g_init = depth0 = _g_depth(g_key, scene, cam)
    timings["render_ms"] = 1000 * (time.perf_counter() - t)
    px = pixel_scale(cam.width)
    # the view's MVS depth (RGB-only captures), read once for steps 1b and 5: on the view's
    # pixels, speckles dropped (None: no MVS map, i.e. G came from depth frames)
    mvs_v = None
    if (cfg.mvs_front_rel > 0 or cfg.complete) and ws.exists(L.mvs_depth_file(view)):
        from ..geometry.depth_complete import view_mvs
        raw = np.load(ws.path(L.mvs_depth_file(view)))
        if raw.any():
            mvs_v = view_mvs(raw, cam.width, cam.height, cfg.mvs_speckle_px * px * px)
    # 1b. (ours, RGB-only captures) the view's own MVS depth where it lies well in front of G: a
    # surface the fusion missed (docs/VIEW_DEPTH.md step 1b); G's depth stays in depth_init.npy
    front = np.zeros(depth0.shape, bool)
    if cfg.mvs_front_rel > 0 and mvs_v is not None:
        from ..geometry.depth_complete import mvs_in_front
        depth0, front = mvs_in_front(depth0, mvs_v, cfg.mvs_front_rel, int(cfg.mvs_front_px * px * px))
    # pixel-valued parameters of our additions (rounded-step strides, MVS edge guard and check
    # radius) were tuned at 320x240: scaled with the width so that they cover the same image
    # fraction at other sizes (at 640x480 the 2 cm TSDF ramps span twice as many pixels); the
    # rounded-step strides follow the ramps themselves: width x G's voxel size (ramp_scale)
    g_voxel = _g_voxel(ws)
    rs, rr = ramp_scale(cam.width, g_voxel), ramp_ratio(cam.width, g_voxel)
    # 2. Eq. 1 depth edges and the 4 cm refinement mask (§4.2.1)
    t = time.perf_counter()
    det = dr.detect(depth0, cam, lam, cfg.mask_side_m, cfg.mask_min_half_px)
    mask = det.mask & (depth0 > 0)
    rounded = rounded_all = np.zeros_like(mask)
    if cfg.rounded_steps:
        import cv2

        from ..geometry.depth_edges import refinement_mask
        from ..geometry.depth_rounded import canny_edges, rounded_steps
        strides = tuple(rs * int(s) for s in cfg.rounded_strides)
        rounded_all = rounded_steps(depth0, det.points, det.normals, canny_edges(image), lam,
                                    strides, cfg.rounded_min_rel)
        rounded = rounded_all & ~mask
        if rounded.any():
            f = float(np.sqrt(cam.K[0, 0] * cam.K[1, 1]))
            s = max(strides)
            extra = refinement_mask(rounded, depth0, f, cfg.mask_side_m, cfg.mask_min_half_px)
            extra |= cv2.dilate(rounded.astype(np.uint8), np.ones((2 * s + 1, 2 * s + 1), np.uint8)) > 0
            mask |= extra & (depth0 > 0)
    timings["edges_ms"] = 1000 * (time.perf_counter() - t)
    # 3. step one of §4.2.2: masked MVS, photometric vs geometric agreement within 5 %
    t = time.perf_counter()
    depth1 = depth0.copy()
    mvs_stats = {"enabled": cfg.mvs}
    accepted = np.zeros_like(mask)
    src = _sources(ctx, view)
    if cfg.mvs and src and mask.any():
        src_imgs = [_image(ws.path(ctx.scene.view(s).image)) for s in src]
        src_cams = [cams[s] for s in src]
        src_depths = [_g_depth(g_key, scene, c) for c in src_cams]
        import scipy.ndimage as nd
        protect = trust = ramp = None
        if cfg.g_trust != "none":  # G is reliable away from its own edges and ramps
            dist_g = nd.distance_transform_edt(~(det.edge_pixels | rounded_all))
            protect = dist_g > px * cfg.mvs_edge_guard
            if cfg.g_trust == "far":   # G misplaces an edge by about its ramp width (ramp_ratio);
                # the borders of G's holes (grazing faces, unseen areas) are no misplaced edge
                surf = det.edges.between_surfaces(depth0 > 0).pixels()
                trust = nd.distance_transform_edt(~(surf | rounded_all)) > rr * (cfg.g_trust_px or g_trust_auto(cam.width))
        if cfg.ramp_zone_px > 0 and rounded_all.any():  # G's ramps are what is wrong there
            ramp = nd.distance_transform_edt(~rounded_all) <= rr * cfg.ramp_zone_px
        half = int(np.ceil(0.5 * cfg.mask_side_m * cam.K[0, 0] / max(float(np.median(depth0[mask])), 0.1)))
        res = dr.masked_mvs(image, cam, depth0, mask, src_imgs, src_cams, src_depths,
                            num_depths=cfg.num_depths, window=cfg.window, band_radius=max(2, half + 1),
                            min_consistent=cfg.mvs_min_consistent, agree_rel=cfg.mvs_agree_rel,
                            device=cfg.device, check=cfg.mvs_check,
                            check_radius=px * cfg.mvs_check_radius,
                            min_change=cfg.mvs_min_change, guard_px=px * cfg.mvs_edge_guard,
                            lambda_rel=lam, protect=protect,
                            trust_g=trust, distrust_g=ramp)
        accepted = res.accepted
        depth1[accepted] = res.depth[accepted]
        mvs_stats.update(res.stats, sources_used=src)
    timings["mvs_ms"] = 1000 * (time.perf_counter() - t)
    # 4. Eq. 2 over the remaining mask pixels
    t = time.perf_counter()
    region = mask & ~accepted
    barrier = strokes
    if cfg.edge_barrier:  # G's own occlusion edges as automatic strokes (see the config help)
        e = dr.detect(depth1, cam, lam, with_mask=False).edge_pixels
        barrier = e if strokes is None else (strokes | e)
    # the colour edge map without strokes, shared by Eq. 2 and the completion (their strokes differ)
    base_edges = geo.colour_edge_map(image, None, boundary_radius=px * cfg.edge_boundary_radius)
    depth2, filled, _ = dr.refine(depth1, cam, image, region, barrier, cfg.cost_base, cfg.cost_edge,
                                  cfg.neighbours, boundary_radius=px * cfg.edge_boundary_radius,
                                  base_edges=base_edges)
    timings["interp_ms"] = 1000 * (time.perf_counter() - t)
    # 5. completion where G is empty (ours): the view's MVS depth, then edge-aware interpolation
    t = time.perf_counter()
    completed = {"mvs": 0, "planes": 0, "interpolated": 0}
    empty_before = float((depth2 <= 0).mean())
    if cfg.complete and (depth2 <= 0).any():
        from ..geometry.depth_complete import complete_depth
        # segment planes where G came from our MVS (RGB-only captures: the textureless regions
        # PatchMatch leaves empty); over an RGB-D G's holes they added false cuts at segment
        # borders (docs/VIEW_DEPTH.md)
        planes = cfg.planes.scaled(px * px) if cfg.complete_planes and mvs_v is not None else None
        depth2, which = complete_depth(depth2, cam, image, mvs_v, cfg.cost_edge,
                                       px * cfg.edge_boundary_radius, strokes, planes,
                                       base_edges=base_edges)
        completed = {k: int(v.sum()) for k, v in which.items()}
    timings["complete_ms"] = 1000 * (time.perf_counter() - t)
    if not np.all(np.isfinite(depth2)):
        raise RuntimeError("refined depth has non-finite values")
    final = dr.detect(depth2, cam, lam, with_mask=False)  # edges.png: Eq. 1 on the result
    normal_w = world_normals(final.normals, cam).astype(np.float32)   # = normals_from_depth(depth2)
    vd = ws.view_dir(view)
    with ws.atomic_write(f"{vd}/{L.DEPTH_INIT}") as f:
        np.save(f, g_init.astype(np.float32))
    with ws.atomic_write(f"{vd}/{L.DEPTH}") as f:
        np.save(f, depth2.astype(np.float32))
    with ws.atomic_write(f"{vd}/{L.NORMAL}") as f:
        np.save(f, normal_w)
    write_image(ws.path(f"{vd}/{L.EDGES}"), (final.edge_pixels * 255).astype(np.uint8))
    write_image(ws.path(f"{vd}/{L.REFINE_MASK}"), (mask * 255).astype(np.uint8))
    ms = 1000 * (time.perf_counter() - t0)
    ws.write_json(f"{vd}/{L.DEPTH_REPORT}", {
        "view": view, "size": [cam.width, cam.height], "lambda_rel": lam, "pixel_scale": px,
        "ramp_scale": rs,
        "edge_pixels_init": int(det.edge_pixels.sum()), "edge_pixels": int(final.edge_pixels.sum()),
        "mask_pixels": int(mask.sum()), "rounded_step_pixels": int(rounded.sum()), "mvs_accepted": int(accepted.sum()),
        "mvs_in_front": int(front.sum()),
        "interpolated": int(filled.sum()),
        "refined_fraction": float((accepted.sum() + filled.sum()) / max(int(mask.sum()), 1)),
        "valid_fraction": float((depth2 > 0).mean()), "empty_in_g": empty_before,
        "completed": completed, "strokes": strokes is not None,
        "mvs": mvs_stats, "timings_ms": {k: round(v, 1) for k, v in timings.items()},
        "ms": round(ms, 1), "cpu_ms": round(1000 * (time.process_time() - c0), 1)})


STAGE = Stage(name="view_depth", help="depth edges (Eq. 1) and masked geodesic depth refinement per view",
              config=ViewDepthConfig, version="10", run=run, per_view=True,
              inputs=(L.REGISTERED_CAMERAS, L.GLOBAL_MESH), view_inputs=view_inputs,
              view_outputs=tuple("{view_dir}/" + o for o in OUTPUTS), views=registered_views)
