"""Stage `global_mesh` (Xu et al. §4.1): the global mesh G of the training views, in the scene
frame of the `poses` stage (stages/poses.py).

Dense geometry: RGB-D TSDF fusion (geometry/fusion.py), or multi-view stereo of the RGB images
fused the same way: PatchMatch with slanted planes and geometric consistency (geometry/patchmatch.py,
COLMAP / ACMM style; the default) or the fronto-parallel plane sweep (geometry/mvs.py) filtered by
geometric consistency. Each view's MVS depth is kept for view_depth's completion. Reflectors (reflectors.json) are replaced
by their plane in every depth map before fusion, so the mirror world never enters G; without
them, reflectors are looked for in the depth (regions behind a plane that the mirrored G
explains, geometry/behind_detect.py and plane_holes.py) and G is fused again without the ones found. The module
only loads, calls and saves; docs/GLOBAL_MESH.md explains the choices.
"""
from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass

import numpy as np

from .. import layout as L
from ..config import StageConfig, param
from ..errors import ConfigError, InputError
from ..executors import LocalExecutor
from ..geometry.behind_detect import BehindOptions
from ..geometry.fusion import FusionOptions
from ..geometry.patchmatch import PatchMatchOptions
from ..geometry.user_reflectors import user_reflectors
from ..runner import Stage, StageContext

log = logging.getLogger("ibr_pipeline.global_mesh")

def dense_mode(ctx) -> str:
    """global_mesh.dense resolved: 'rgbd' when every training view has a depth frame ('auto')."""
    if ctx.config.dense != "auto":
        return ctx.config.dense
    cams = L.registered_cameras(ctx.ws)
    return "rgbd" if all(ctx.scene.view(n).depth for n in cams) else "mvs"


def outputs(ctx: StageContext) -> list[str]:
    out = [L.GLOBAL_MESH, L.GLOBAL_REPORT, L.FOUND_REFLECTORS]
    if ctx.ws.path(L.REGISTERED_CAMERAS).is_file() and dense_mode(ctx) == "mvs":
        out += [L.mvs_depth_file(n) for n in L.registered_cameras(ctx.ws)]
    return out


@dataclass(frozen=True)
class GlobalMeshConfig(StageConfig):
    dense: str = param("auto", "dense geometry: rgbd (TSDF of depth frames), mvs (plane sweep), "
                       "auto = rgbd when every view has depth", choices=("auto", "rgbd", "mvs"))
    fusion: FusionOptions = param(FusionOptions(), "TSDF fusion of the depth frames")
    reflector_fill: bool = param(True, "replace reflector pixels by the reflector plane (else drop them)")
    # MVS matches a screen's highlights at wrong depths, in front of it (llff_room21's TV); fused,
    # they float there and cut holes in its reflection mask (docs/GLOBAL_MESH.md "Reflectors")
    reflector_floaters: bool = param(True, "MVS depth in front of a reflector's polygon that the "
                                     "other views see through (more refute it than confirm it) "
                                     "is taken as the reflector (fusion.reflector_floaters)")
    find_reflectors: str = param("auto", "find reflectors in the MVS depth: regions seen behind a "
                                 "plane, enclosed by it in a view or on the views pooled, in "
                                 "many views, that the mirrored mesh explains "
                                 "(geometry/behind_detect.py, plane_holes.py); they are "
                                 "masked out of G like reflectors.json's. 'auto' = only when no "
                                 "reflectors.json is given", choices=("auto", "on", "off"))
    behind: BehindOptions = param(BehindOptions(), "finding reflectors behind planes "
                                  "(find_reflectors)")
    mvs: str = param("patchmatch", "MVS method: patchmatch (slanted planes, propagation, "
                     "geometric consistency; geometry/patchmatch.py) or sweep (fronto-parallel "
                     "plane sweep, geometry/mvs.py)", choices=("patchmatch", "sweep"))
    patchmatch: PatchMatchOptions = param(PatchMatchOptions(), "PatchMatch MVS (mvs = patchmatch)")
    mvs_scale: float = param(1.0, "MVS working resolution relative to the images (1 = full, as "
                             "COLMAP; 0.5 is ~3x faster and less accurate: docs/GLOBAL_MESH.md)",
                             min=0.05, max=1.0)
    mvs_sources: int = param(4, "MVS source views per reference view", min=1, max=16)
    mvs_depths: int = param(96, "plane sweep: hypotheses (uniform in inverse depth) of the full sweep",
                            min=4, max=512)
    mvs_coarse_levels: int = param(1, "plane sweep pyramid: the full sweep runs this many octaves below the "
                                   "working size, finer levels search a band around it", min=0, max=4)
    mvs_refine_depths: int = param(16, "plane sweep: hypotheses per pixel at each finer pyramid level", min=2, max=128)
    mvs_window: int = param(9, "plane sweep: NCC window (odd)", min=3, max=21)
    mvs_max_cost: float = param(0.5, "plane sweep: reject pixels whose 1 - NCC exceeds this", min=0.0, max=2.0)
    mvs_min_consistent: int = param(1, "plane sweep: source depth maps that must agree (geometric filter)", min=0, max=16)
    mvs_consistency_tol: float = param(0.02, "plane sweep geometric filter: relative depth tolerance", min=1e-4, max=0.5)
    mvs_consistency_px: float = param(1.0, "plane sweep geometric filter: round-trip reprojection tolerance (px)",
                                      min=0.1, max=20.0)
    mvs_depth_min: float = param(0.3, "MVS depth range of a view with too few scene points (scene "
                                 "units, global/poses.json)", min=1e-3, max=1e4)
    mvs_depth_max: float = param(8.0, "MVS depth range of a view with too few scene points",
                                 min=1e-3, max=1e4)
    device: str = param("cpu", "torch device for MVS", choices=("cpu", "cuda"), affects_output=False)
    threads: int = param(1, "threads for torch (MVS on CPU)", min=1, max=256,
                         affects_output=False)
    progress: bool = param(True, "show progress bars", affects_output=False)

    def check(self, prefix: str) -> None:
        if self.mvs_window % 2 == 0:
            raise ConfigError(prefix + "mvs_window", f"must be odd, got {self.mvs_window}")
        if self.mvs_depth_min >= self.mvs_depth_max:
            raise ConfigError(prefix + "mvs_depth_min", "must be below mvs_depth_max")


def inputs(ctx: StageContext) -> list[str]:
    keys = [L.SCENE, L.REGISTERED_CAMERAS, L.POSES_REPORT, L.SCENE_REFLECTORS]
    if not ctx.ws.path(L.REGISTERED_CAMERAS).is_file():
        return keys
    for n in L.registered_cameras(ctx.ws):
        v = ctx.scene.view(n)
        keys.append(v.image)
        if v.depth:
            keys.append(v.depth)
    for r in L.scene_reflectors(ctx.ws):
        keys += list(r.masks.values())
    return keys


# --- steps ----------------------------------------------------------------------------------------
def _depth_frames(ctx, cams, depth_views, reflectors, view_masks, stats):
    """Yield (depth with reflectors applied, camera, colour) per registered view."""
    from ..geometry.fusion import apply_reflectors
    from ..io.images import read_depth_png, read_image

    ws, cfg = ctx.ws, ctx.config
    for name, cam in cams.items():
        d = read_depth_png(ws.path(depth_views[name]))
        c = cam.resized(d.shape[1], d.shape[0])
        if reflectors:
            d, n = apply_reflectors(c, d, reflectors, cfg.reflector_fill, view_masks.get(name))
            stats["reflector_pixels"] += n
        yield d, c, read_image(ws.path(ctx.scene.view(name).image), ctx.scene.image_encoding)


def _auto_voxel(ctx, cams, depth_views, mvs_depths, metric: bool) -> float:
    """`voxel_size = 0`: `fusion.auto_voxel_size` of the depth that will be fused (up to 16 depth
    frames spread over the capture, or every MVS depth map)."""
    from ..geometry.fusion import auto_voxel_size
    from ..io.images import read_depth_png

    if mvs_depths is not None:
        samples = list(mvs_depths.values())
    else:
        names = list(cams)[::max(1, len(cams) // 16)]
        samples = [(read_depth_png(ctx.ws.path(depth_views[n])), cams[n]) for n in names]
    try:
        v = auto_voxel_size(samples, metric)
    except ValueError:
        raise InputError(f"{ctx.ws.input_root}: no depth in any frame (global_mesh.fusion.voxel_size = 0 "
                         "needs some to choose the voxel size)") from None
    log.info("global_mesh: voxel size %.4g %s (auto: 2 depth-pixel footprints at the median depth)",
             v, "m" if metric else "scene units (normalised frame)")
    return v


def _mvs_depths(ctx, cams, ranges, report) -> dict:
    """{name: (depth at working size, camera at working size)} filtered by geometric consistency."""
    import cv2
    from tqdm import tqdm

    from ..geometry import mvs
    from ..io.images import read_image

    ws, cfg, scene = ctx.ws, ctx.config, ctx.scene
    imgs, wcams = {}, {}
    for n, cam in cams.items():
        w, h = max(8, round(cam.width * cfg.mvs_scale)), max(8, round(cam.height * cfg.mvs_scale))
        im = read_image(ws.path(scene.view(n).image))
        imgs[n] = cv2.resize(im, (w, h), interpolation=cv2.INTER_AREA) if (w, h) != im.shape[1::-1] else im
        wcams[n] = cam.resized(w, h)

    def filtered(raw):  # geometric consistency (forward-backward) filter
        out = {}
        for n, (d, src) in raw.items():
            others = [s for s in src if s in raw]
            if cfg.mvs_min_consistent > 0 and others:
                cnt = mvs.geometric_consistency(wcams[n], d, [wcams[s] for s in others],
                                                [raw[s][0] for s in others], rel_tol=cfg.mvs_consistency_tol,
                                                reproj_px=cfg.mvs_consistency_px,
                                                device=cfg.device)
                d = np.where(cnt >= min(cfg.mvs_min_consistent, len(others)), d, 0).astype(np.float32)
            out[n] = (d, wcams[n])
        return out

    sources, view_range = {}, {}
    for n in cams:
        # the scene points' depth percentiles in this view, widened (poses stage)
        lo, hi = view_range[n] = tuple(ranges.get(n, (cfg.mvs_depth_min, cfg.mvs_depth_max)))
        src = mvs.select_sources(wcams[n], wcams, k=cfg.mvs_sources, scene_depth=float(np.sqrt(lo * hi)))
        if src:
            sources[n] = src
        else:
            log.warning("global_mesh: view %s has no MVS source view; skipped", n)
    show = cfg.progress and ctx.progress
    import torch
    prev_threads = torch.get_num_threads()
    torch.set_num_threads(cfg.threads)  # threads beyond the free cores only spin-wait
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        if cfg.mvs == "patchmatch":  # photometric, geometric passes and the final filter
            from ..geometry.patchmatch import patchmatch_views
            jobs = ctx.jobs if str(cfg.device).startswith("cpu") else 1  # one GPU: one process
            with LocalExecutor(max(1, min(jobs, len(sources)))) as ex:
                res = patchmatch_views(imgs, wcams, sources, view_range, cfg.patchmatch,
                                       device=cfg.device, progress=show,
                                       map_fn=None if ex.jobs == 1 else _pool_map(ex, cfg.threads))
            report["timings"]["mvs_workers"] = ex.jobs  # how it ran, like the seconds
            out = {n: (r.depth.astype(np.float32), wcams[n]) for n, r in res.items()}
            report["timings"]["mvs_s_per_view"] = (time.perf_counter() - t0) / max(len(out), 1)
            report["timings"]["mvs_cpu_s_per_view"] = (time.process_time() - c0) / max(len(out), 1)
        else:
            raw = {}
            for n in tqdm(sources, desc="global_mesh: MVS", unit="view", disable=not show, leave=False):
                src, (lo, hi) = sources[n], view_range[n]
                r = mvs.plane_sweep(imgs[n], wcams[n], [imgs[s] for s in src], [wcams[s] for s in src],
                                    lo, hi, num_depths=cfg.mvs_depths, window=cfg.mvs_window,
                                    device=cfg.device, max_cost=cfg.mvs_max_cost,
                                    coarse_levels=cfg.mvs_coarse_levels,
                                    refine_depths=cfg.mvs_refine_depths,
                                    refine_levels=0 if cfg.mvs_coarse_levels > 0 else 1)
                raw[n] = (r.depth, src)
            report["timings"]["mvs_s_per_view"] = (time.perf_counter() - t0) / max(len(raw), 1)
            report["timings"]["mvs_cpu_s_per_view"] = (time.process_time() - c0) / max(len(raw), 1)
            t0, c0 = time.perf_counter(), time.process_time()
            out = filtered(raw)
            report["timings"]["mvs_filter_s_per_view"] = (time.perf_counter() - t0) / max(len(raw), 1)
            report["timings"]["mvs_filter_cpu_s_per_view"] = (time.process_time() - c0) / max(len(raw), 1)
    except ValueError as e:
        raise InputError(f"{ws.input_root}: MVS: {e}") from None
    finally:
        torch.set_num_threads(prev_threads)
    report["mvs_valid_fraction"] = float(np.mean([np.mean(d > 0) for d, _ in out.values()])) if out else 0.0
    return out



def run(ctx: StageContext) -> None:
    from ..geometry.fusion import apply_reflectors, reflector_floaters, tsdf_fuse
    from ..io.images import read_image
    from ..io.mesh import write_ply

    t_start = time.perf_counter()
    ws, cfg, scene = ctx.ws, ctx.config, ctx.scene
    cams = L.registered_cameras(ws)
    frame = L.poses_report(ws)
    depth_views = {v.name: v.depth for v in scene.views if v.depth and v.name in cams}
    dense = dense_mode(ctx)
    if dense == "rgbd" and len(depth_views) != len(cams):
        missing = next(n for n in cams if n not in depth_views)
        raise InputError(f"{ws.path(scene.view(missing).image)}: no depth frame for this image "
                         f"({len(depth_views)} depth frames for {len(cams)} views; "
                         "global_mesh.dense is rgbd)")
    report: dict = {"dense": dense, "units": frame.get("units"), "timings": {}}
    ranges = {n: tuple(r) for n, r in frame.get("depth_ranges", {}).items()}
    depths = _mvs_depths(ctx, cams, ranges, report) if dense == "mvs" else None
    if depths is not None:  # view_depth completes G's holes with them; outlines are fitted to them
        for n, (d, _) in depths.items():
            with ws.atomic_write(L.mvs_depth_file(n)) as f:
                np.save(f, d.astype(np.float32))
        for n in cams:
            if n not in depths:  # a view MVS skipped: no depth
                with ws.atomic_write(L.mvs_depth_file(n)) as f:
                    np.save(f, np.zeros((8, 8), np.float32))
    reflectors = user_reflectors(ws, scene, dense)
    view_masks: dict = {}
    for r in reflectors:
        for vn, key in r.masks.items():
            view_masks.setdefault(vn, {})[r.name] = read_image(ws.path(key))[..., 0] > 0.5
    for r in reflectors:
        if r.outline is not None:
            log.info("global_mesh: reflector %s placed from its outline in %s: plane %s",
                     r.name, r.outline[0], ", ".join(f"{c:.4f}" for c in r.plane))
    voxel = cfg.fusion.voxel_size or _auto_voxel(ctx, cams, depth_views, depths,
                                                 frame.get("units") == "metres")
    report["voxel_size"] = {"value": voxel, "auto": not cfg.fusion.voxel_size}
    # depth_max = 0: the far end of the scene's depth ranges (a length of this scene, not metres)
    far = cfg.fusion.depth_max or (max(hi for _, hi in ranges.values()) if ranges else 1e6)
    report["depth_max"] = {"value": far, "auto": not cfg.fusion.depth_max}
    fopts = dataclasses.replace(cfg.fusion, voxel_size=voxel, depth_max=far)

    refuted_by: dict = {}  # reflector name -> reflector_floaters: a second fusion reuses them

    def fuse(refls):
        stats = {"reflector_pixels": 0}
        if dense == "rgbd":
            frames = _depth_frames(ctx, cams, depth_views, refls, view_masks, stats)
        else:
            for r in refls:
                if cfg.reflector_floaters and r.name not in refuted_by:
                    refuted_by[r.name] = reflector_floaters(depths, r)
            floaters = {r.name: refuted_by[r.name] for r in refls if r.name in refuted_by}
            stats["floater_pixels"] = sum(int(m.sum()) for f in floaters.values() for m in f.values())
            if stats["floater_pixels"]:
                log.info("global_mesh: %d MVS pixels in front of %s, seen through by more views "
                         "than see them, taken as the reflector (reflector_floaters)",
                         stats["floater_pixels"],
                         ", ".join(k for k, f in floaters.items() if any(m.any() for m in f.values())))

            def _mvs_frames():
                for n, (d, c) in depths.items():
                    if refls:
                        # masks are image-sized: resize to the working size
                        vm = {k: _resize_mask(m, c.size) for k, m in view_masks.get(n, {}).items()}
                        refuted = {k: f[n] for k, f in floaters.items() if n in f}
                        d, k = apply_reflectors(c, d, refls, cfg.reflector_fill, vm,
                                                refuted=refuted)
                        stats["reflector_pixels"] += k
                    yield d, c, read_image(ws.path(scene.view(n).image), scene.image_encoding)
            frames = _mvs_frames()
        try:
            mesh, fstats = tsdf_fuse(frames, fopts, progress=cfg.progress and ctx.progress,
                                     total=len(cams))
        except ValueError as e:
            raise InputError(f"{ws.input_root}: {e} (global/poses.json gives the scene's depth "
                             "ranges)") from None
        if len(mesh.faces) == 0:
            raise InputError(f"{ws.input_root}: fusion produced an empty mesh (no usable depth)")
        return mesh, fstats, stats

    mesh, fstats, stats = fuse(reflectors)
    found, cands = [], []
    if cfg.find_reflectors == "on" or (cfg.find_reflectors == "auto" and not reflectors):
        t0 = time.perf_counter()
        found, cands = _find_reflectors(ctx, cams, depths or _depth_maps(ctx, cams, depth_views),
                                        mesh, reflectors)
        report["timings"]["find_reflectors_s"] = time.perf_counter() - t0
        report["found_reflectors"] = [{k: c[k] for k in ("name", "kept", "reason")} for c in cands]
        if found:  # G again, without what MVS saw in them
            mesh, fstats, stats = fuse(reflectors + tuple(found))
    if not reflectors and not found:
        log.warning("global_mesh: no reflectors.json and no reflector found in the depth: what "
                    "depth/MVS sees in mirrors (the mirror world) is fused into the global mesh "
                    "as if it were real geometry")
    ws.write_json(L.FOUND_REFLECTORS, {"format": "ibr_pipeline.found_reflectors/1",
                                       "reflectors": [r.to_dict() for r in found],
                                       "candidates": cands})
    report["timings"]["fusion_ms_per_frame"] = fstats["ms_per_frame"]
    report["fusion"] = fstats
    report.update(counts={"views": len(cams), "depth_frames": len(depth_views),
                          "reflectors": len(reflectors), "found_reflectors": len(found),
                          "reflector_pixels": stats["reflector_pixels"],
                          "floater_pixels": stats.get("floater_pixels", 0),
                          "mesh_vertices": len(mesh.vertices), "mesh_faces": len(mesh.faces)},
                  mirror_world="masked by reflectors.json" if reflectors else
                  f"masked in {len(found)} reflector(s) found behind planes" if found else
                  "NOT masked: no reflectors.json and none found, mirror-world geometry may be "
                  "in the mesh")
    # tsdf_fuse returns the mesh in io.mesh.canonical_order (open3d's marching cubes emits it in a
    # thread-dependent order): identical inputs write identical bytes, so a forced rerun leaves
    # every later stage up to date (tests/test_determinism.py)
    write_ply(ws.path(L.GLOBAL_MESH), mesh, comment="ibr_pipeline global_mesh")
    report["timings"]["total_s"] = time.perf_counter() - t_start
    ws.write_json(L.GLOBAL_REPORT, report)
    log.info("global_mesh: %d views, %s mesh %d faces, %.1f s", len(cams), dense, len(mesh.faces),
             report["timings"]["total_s"])


def _depth_maps(ctx, cams, depth_views) -> dict:
    """{name: (depth frame, camera at its size)}: the RGB-D frames as the MVS maps are held."""
    from ..io.images import read_depth_png
    out = {}
    for n, cam in cams.items():
        d = read_depth_png(ctx.ws.path(depth_views[n])).astype(np.float32)
        out[n] = (d, cam.resized(d.shape[1], d.shape[0]))
    return out


def _find_reflectors(ctx, cams, depths, mesh, given=()) -> tuple[list, list[dict]]:
    """Reflectors found in the MVS depth (geometry/behind_detect.py), each candidate verified on
    G fused without them; one that is a `given` reflector already is dropped as that. Returns
    (scene.Reflector list, every candidate with its evidence)."""
    from ..geometry.behind_detect import find_candidates, same_reflector, verify_candidate
    from ..geometry.raycast import build_scene
    from ..io.images import read_image
    from ..scene import Reflector
    ws, scene = ctx.ws, ctx.scene
    show = ctx.config.progress and ctx.progress
    o = ctx.config.behind
    cands = find_candidates(cams, {n: d for n, (d, _) in depths.items()}, min_views=o.min_views,
                            progress=show, behind=o.behind, enclosed=o.enclosed, border=o.border,
                            min_area=o.min_area, max_area=o.max_area, pooled=o.pooled)
    for c in cands:
        same = next((r.name for r in given if same_reflector(c, r.plane, r.polygon)), None)
        if c["kept"] and same is not None:
            c.update(kept=False, reason=f"{c['reason']}; the given reflector {same}")
    found = []
    if any(c["kept"] for c in cands):
        rc = build_scene(mesh.vertices, mesh.faces)
        bounds = (mesh.vertices.min(0), mesh.vertices.max(0))
        class Images(dict):  # read on first use: a candidate scores at most 12 views
            def __missing__(self, n):
                self[n] = read_image(ws.path(scene.view(n).image), scene.image_encoding)
                return self[n]
        imgs = Images()
        g_depth: dict = {}  # G's depth in each view, once for all candidates
        for c in cands:
            if not c["kept"]:
                continue
            ok, why, score = verify_candidate(c, cams, imgs, rc, bounds, threshold=o.threshold,
                                              mirror_ratio=o.mirror_ratio,
                                              max_views=o.max_views, g_depth=g_depth)
            c.update(kept=ok, reason=f"{c['reason']}; {why}", score=score)
            if ok:
                found.append(Reflector(c["name"], tuple(c["plane"]), beta=1.0,
                                       polygon=tuple(map(tuple, c["polygon"])), material="mirror"))
    for c in cands:
        log.info("global_mesh: %s %s (best seen in %s): %s", c["name"],
                 "found" if c["kept"] else "dropped", c["view"], c["reason"])
    return found, cands


def _with_threads(threads: int, fn, *args):
    """fn(*args) with torch at `threads` threads: a worker computes a view exactly as the
    serial run does (its pool pins every library to its share of the cores first)."""
    import torch
    torch.set_num_threads(threads)
    return fn(*args)


def _pool_map(ex: LocalExecutor, threads: int):
    """patchmatch_views' map_fn over the executor's workers; a failed view stops the stage."""
    return lambda fn, argsets: ex.results(_with_threads, [(threads, fn, *a) for a in argsets])


def _resize_mask(mask: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    import cv2
    return cv2.resize(mask.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0


STAGE = Stage(name="global_mesh", help="the global mesh of the training views (RGB-D TSDF "
              "fusion or MVS), reflectors masked (Xu §4.1)",
              config=GlobalMeshConfig, version="10", run=run, inputs=inputs, outputs=outputs)
