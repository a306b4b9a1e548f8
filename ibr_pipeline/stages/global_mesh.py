"""Stage `global_mesh` (Xu et al. §4.1): a pose for every input image and a global mesh G.

Poses: taken from the input (COLMAP model / cameras.json) unless `force_sfm`; otherwise pycolmap
SfM (geometry/sfm.py). Scale: with depth frames the SfM model is scaled to metres from the depth at
its keypoints and refined by ICP (geometry/align.py); without, `scale` or "sfm" units.
Dense geometry: RGB-D TSDF fusion (geometry/fusion.py), or our plane-sweep MVS (geometry/mvs.py)
filtered by geometric consistency and fused the same way. Reflectors (reflectors.json) are replaced
by their plane in every depth map before fusion, so the mirror world never enters G. The module
only loads, calls and saves; docs/GLOBAL_MESH.md explains the choices.
"""
from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import layout as L
from ..config import StageConfig, param
from ..errors import ConfigError, InputError
from ..geometry.fusion import FusionOptions
from ..runner import Stage, StageContext

log = logging.getLogger("ibr_pipeline.global_mesh")

OUTPUTS = L.SFM_FILES + (L.REGISTERED_CAMERAS, L.GLOBAL_MESH, L.GLOBAL_REPORT)


@dataclass(frozen=True)
class GlobalMeshConfig(StageConfig):
    force_sfm: bool = param(False, "run SfM even when the input gives camera poses")
    matching: str = param("auto", "SfM matching: sequential (video-like), exhaustive (small sets), "
                          "auto = exhaustive up to 40 images", choices=("auto", "sequential", "exhaustive"))
    sequential_overlap: int = param(10, "sequential matching: neighbours matched per image", min=1, max=100)
    close_loop: bool = param(True, "sequential matching: also match the last images with the first "
                             "(a capture that walks round the room)")
    min_registered: int = param(3, "fewer registered views than this is an error", min=2)
    scale: float = param(0.0, "metres per SfM unit when there is no depth (0 = keep SfM units)", min=0.0, max=1e6)
    dense: str = param("auto", "dense geometry: rgbd (TSDF of depth frames), mvs (plane sweep), "
                       "auto = rgbd when every view has depth", choices=("auto", "rgbd", "mvs"))
    fusion: FusionOptions = param(FusionOptions(), "TSDF fusion of the depth frames")
    reflector_fill: bool = param(True, "replace reflector pixels by the reflector plane (else drop them)")
    mvs_scale: float = param(0.5, "MVS working resolution relative to the images", min=0.05, max=1.0)
    mvs_sources: int = param(4, "MVS source views per reference view", min=1, max=16)
    mvs_depths: int = param(96, "MVS plane hypotheses (uniform in inverse depth) of the full sweep",
                            min=4, max=512)
    mvs_coarse_levels: int = param(1, "MVS pyramid: the full sweep runs this many octaves below the "
                                   "working size, finer levels search a band around it", min=0, max=4)
    mvs_refine_depths: int = param(16, "MVS hypotheses per pixel at each finer pyramid level", min=2, max=128)
    mvs_window: int = param(9, "MVS NCC window (odd)", min=3, max=21)
    mvs_max_cost: float = param(0.5, "MVS: reject pixels whose 1 - NCC exceeds this", min=0.0, max=2.0)
    mvs_min_consistent: int = param(1, "MVS: source depth maps that must agree (geometric filter)", min=0, max=16)
    mvs_consistency_tol: float = param(0.02, "MVS geometric filter: relative depth tolerance", min=1e-4, max=0.5)
    mvs_consistency_px: float = param(1.0, "MVS geometric filter: round-trip reprojection tolerance (px)",
                                      min=0.1, max=20.0)
    mvs_depth_min: float = param(0.3, "MVS depth range when there are no SfM points", min=1e-3, max=1e4)
    mvs_depth_max: float = param(8.0, "MVS depth range when there are no SfM points", min=1e-3, max=1e4)
    device: str = param("cpu", "torch device for MVS", choices=("cpu", "cuda"), affects_output=False)
    threads: int = param(1, "threads for pycolmap and for torch (MVS on CPU)", min=1, max=256,
                         affects_output=False)
    progress: bool = param(True, "show progress bars", affects_output=False)

    def check(self, prefix: str) -> None:
        if self.mvs_window % 2 == 0:
            raise ConfigError(prefix + "mvs_window", f"must be odd, got {self.mvs_window}")
        if self.mvs_depth_min >= self.mvs_depth_max:
            raise ConfigError(prefix + "mvs_depth_min", "must be below mvs_depth_max")


def inputs(ctx: StageContext) -> list[str]:
    keys = [L.SCENE]
    for v in ctx.scene.views:
        keys.append(v.image)
        if v.depth:
            keys.append(v.depth)
    if ctx.ws.path(L.USER_REFLECTORS).is_file():
        keys.append(L.USER_REFLECTORS)
    for r in ctx.scene.reflectors:
        keys += list(r.masks.values())
    return keys


# --- steps ----------------------------------------------------------------------------------------
def _image_dir(ws, scene) -> Path:
    v = scene.views[0]
    p = ws.path(v.image)
    return Path(str(p)[: -len(v.name)]) if str(p).endswith(v.name) else p.parent


def _poses(ctx, depth_views: dict) -> tuple[dict, dict, object]:
    """{name: Camera} in the output frame, report fields, pycolmap reconstruction (or None)."""
    from ..geometry import align, sfm
    from ..io.images import image_size, read_depth_png

    ws, cfg, scene = ctx.ws, ctx.config, ctx.scene
    given = {v.name: v.camera for v in scene.views if v.camera is not None}
    if given and not cfg.force_sfm:
        log.info("global_mesh: using the %d camera poses given by the input (%s); SfM skipped",
                 len(given), scene.source)
        return given, {"pose_source": scene.source, "units": "metres", "reprojection_error_px": None}, None
    sizes = {}
    for v in scene.views:
        sizes.setdefault(image_size(ws.path(v.image)), v.image)
    if len(sizes) > 1:
        (s1, k1), (s2, k2) = list(sizes.items())[:2]
        raise InputError(f"{ws.path(k2)}: image is {s2[0]}x{s2[1]} but {ws.path(k1)} is "
                         f"{s1[0]}x{s1[1]}; SfM needs one camera (all images the same size)")
    matching = cfg.matching if cfg.matching != "auto" else (
        "exhaustive" if len(scene.views) <= 40 else "sequential")
    intr = next(iter(given.values())) if given else None
    import tempfile
    ws.path(".ibr").mkdir(exist_ok=True)
    with tempfile.TemporaryDirectory(dir=ws.path(".ibr"), prefix="sfm-") as tmp:
        res = sfm.run_sfm(_image_dir(ws, scene), scene.names, Path(tmp), matching, intr,
                          cfg.sequential_overlap, cfg.threads, close_loop=cfg.close_loop)
    cams, rec = res.cameras, res.reconstruction
    if len(cams) < cfg.min_registered:
        raise InputError(f"{ws.input_root}: SfM registered only {len(cams)} of {len(scene.views)} "
                         f"images (global_mesh.min_registered is {cfg.min_registered})")
    info = {"pose_source": "sfm", "sfm": res.stats, "reprojection_error_px": res.stats["reprojection_error_px"]}
    s, R, t = 1.0, np.eye(3), np.zeros(3)
    if all(n in depth_views for n in cams):
        # metric scale from the depth frames at the SfM keypoints (Sim(3) with identity rotation)
        zs, zd = [], []
        for n, cam in cams.items():
            d = read_depth_png(ws.path(depth_views[n]))
            uv, z = sfm.keypoint_depths(rec, n)
            sx, sy = d.shape[1] / cam.width, d.shape[0] / cam.height
            iu = np.clip(np.round((uv[:, 0] + 0.5) * sx - 0.5).astype(int), 0, d.shape[1] - 1)
            iv = np.clip(np.round((uv[:, 1] + 0.5) * sy - 0.5).astype(int), 0, d.shape[0] - 1)
            zs.append(z)
            zd.append(d[iv, iu])
        s = align.depth_scale(np.concatenate(zs), np.concatenate(zd))
        # ICP refinement (Xu §4.1): scaled sparse points onto back-projected depth points
        pts = sfm.sparse_points(rec) * s
        scaled = {n: align.transform_camera(c, s, np.eye(3), np.zeros(3)) for n, c in cams.items()}
        dense = []
        for n, cam in list(scaled.items())[:: max(1, len(scaled) // 20)]:
            d = read_depth_png(ws.path(depth_views[n]))
            c = cam.resized(d.shape[1], d.shape[0])
            uv = c.pixel_grid()[::4, ::4].reshape(-1, 2)
            z = d[::4, ::4].reshape(-1)
            dense.append(c.unproject(uv[z > 0], z[z > 0]))
        T, fit, rmse = align.icp_refine(pts, np.concatenate(dense), max_distance=0.05)
        s2 = float(np.cbrt(np.linalg.det(T[:3, :3])))
        R, t, s = T[:3, :3] / s2, T[:3, 3], s * s2
        info.update(units="metres", alignment={"method": "keypoint depth scale + ICP", "scale": s,
                                                 "icp_fitness": fit, "icp_rmse_m": rmse})
    elif cfg.scale > 0:
        s = cfg.scale
        info.update(units="metres", alignment={"method": "user scale", "scale": s})
    else:
        info.update(units="sfm")
        log.warning("global_mesh: no depth frames and no global_mesh.scale: the mesh is in SfM units")
    if s != 1.0 or not np.allclose(R, np.eye(3)):
        import pycolmap
        rec.transform(pycolmap.Sim3d(s, pycolmap.Rotation3d(R), t))
        cams = {n: align.transform_camera(c, s, R, t) for n, c in cams.items()}
    return cams, info, rec


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
        yield d, c, read_image(ws.path(ctx.scene.view(name).image))


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
             v, "m" if metric else "SfM units")
    return v


def _mvs_depths(ctx, cams, rec, report) -> dict:
    """{name: (depth at working size, camera at working size)} filtered by geometric consistency."""
    import cv2
    from tqdm import tqdm

    from ..geometry import mvs
    from ..geometry.sfm import keypoint_depths
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

    import torch
    prev_threads = torch.get_num_threads()
    torch.set_num_threads(cfg.threads)  # threads beyond the free cores only spin-wait
    raw, t0, c0 = {}, time.perf_counter(), time.process_time()
    try:
        for n in tqdm(cams, desc="global_mesh: MVS", unit="view",
                      disable=not (cfg.progress and ctx.progress), leave=False):
            lo, hi = cfg.mvs_depth_min, cfg.mvs_depth_max
            if rec is not None:
                _, z = keypoint_depths(rec, n)
                if len(z) >= 10:  # search between the keypoints' depth percentiles, widened
                    lo, hi = float(np.percentile(z, 2)) * 0.7, float(np.percentile(z, 98)) * 1.4
            src = mvs.select_sources(wcams[n], wcams, k=cfg.mvs_sources, scene_depth=float(np.sqrt(lo * hi)))
            if not src:
                log.warning("global_mesh: view %s has no MVS source view; skipped", n)
                continue
            r = mvs.plane_sweep(imgs[n], wcams[n], [imgs[s] for s in src], [wcams[s] for s in src], lo, hi,
                                num_depths=cfg.mvs_depths, window=cfg.mvs_window, device=cfg.device,
                                max_cost=cfg.mvs_max_cost, coarse_levels=cfg.mvs_coarse_levels,
                                refine_depths=cfg.mvs_refine_depths,
                                refine_levels=0 if cfg.mvs_coarse_levels > 0 else 1)
            raw[n] = (r.depth, src)
        report["timings"]["mvs_s_per_view"] = (time.perf_counter() - t0) / max(len(raw), 1)
        report["timings"]["mvs_cpu_s_per_view"] = (time.process_time() - c0) / max(len(raw), 1)
        t0, c0 = time.perf_counter(), time.process_time()
        out = filtered(raw)
        report["timings"]["mvs_filter_s_per_view"] = (time.perf_counter() - t0) / max(len(raw), 1)
        report["timings"]["mvs_filter_cpu_s_per_view"] = (time.process_time() - c0) / max(len(raw), 1)
    finally:
        torch.set_num_threads(prev_threads)
    report["mvs_valid_fraction"] = float(np.mean([np.mean(d > 0) for d, _ in out.values()])) if out else 0.0
    return out



def run(ctx: StageContext) -> None:
    from ..geometry.fusion import apply_reflectors, tsdf_fuse
    from ..io.colmap import write_colmap_model
    from ..io.images import read_image
    from ..io.mesh import write_ply
    from ..scene import cameras_to_json
    from ..workspace import atomic_path

    t_start = time.perf_counter()
    ws, cfg, scene = ctx.ws, ctx.config, ctx.scene
    depth_views = {v.name: v.depth for v in scene.views if v.depth}
    dense = cfg.dense
    if dense == "auto":
        dense = "rgbd" if len(depth_views) == len(scene.views) else "mvs"
    if dense == "rgbd" and len(depth_views) != len(scene.views):
        missing = next(v for v in scene.views if not v.depth)
        raise InputError(f"{ws.path(missing.image)}: no depth frame for this image ({len(depth_views)} "
                         f"depth frames for {len(scene.views)} images; global_mesh.dense is rgbd)")
    report: dict = {"dense": dense, "timings": {}}
    t0 = time.perf_counter()
    cams, info, rec = _poses(ctx, depth_views)
    report["timings"]["poses_s"] = time.perf_counter() - t0
    report.update(info)
    registered = [n for n in scene.names if n in cams]
    unregistered = [n for n in scene.names if n not in cams]
    cams = {n: cams[n] for n in registered}
    if unregistered:
        log.warning("global_mesh: %d view(s) not registered, excluded from later stages: %s",
                    len(unregistered), ", ".join(unregistered[:10]))
    reflectors = scene.reflectors
    view_masks: dict = {}
    for r in reflectors:
        for vn, key in r.masks.items():
            view_masks.setdefault(vn, {})[r.name] = read_image(ws.path(key))[..., 0] > 0.5
    if not reflectors:
        log.warning("global_mesh: no reflectors.json: what depth/MVS sees in mirrors (the mirror "
                    "world) is fused into the global mesh as if it were real geometry")
    stats = {"reflector_pixels": 0}
    depths = _mvs_depths(ctx, cams, rec, report) if dense == "mvs" else None
    voxel = cfg.fusion.voxel_size or _auto_voxel(ctx, cams, depth_views, depths,
                                                 report.get("units") == "metres")
    report["voxel_size"] = {"value": voxel, "auto": not cfg.fusion.voxel_size}
    fopts = dataclasses.replace(cfg.fusion, voxel_size=voxel)
    if dense == "rgbd":
        frames = _depth_frames(ctx, cams, depth_views, reflectors, view_masks, stats)
    else:
        def _mvs_frames():
            for n, (d, c) in depths.items():
                if reflectors:
                    # masks are image-sized: resize to the working size
                    vm = {k: _resize_mask(m, c.size) for k, m in view_masks.get(n, {}).items()}
                    d, k = apply_reflectors(c, d, reflectors, cfg.reflector_fill, vm)
                    stats["reflector_pixels"] += k
                yield d, c, read_image(ws.path(scene.view(n).image))
        frames = _mvs_frames()
    mesh, fstats = tsdf_fuse(frames, fopts, progress=cfg.progress and ctx.progress, total=len(cams))
    if len(mesh.faces) == 0:
        raise InputError(f"{ws.input_root}: fusion produced an empty mesh (no usable depth)")
    report["timings"]["fusion_ms_per_frame"] = fstats["ms_per_frame"]
    report["fusion"] = fstats
    report.update(registered=registered, unregistered=unregistered,
                  counts={"views": len(scene.views), "registered": len(registered),
                          "unregistered": len(unregistered), "depth_frames": len(depth_views),
                          "reflectors": len(reflectors), "reflector_pixels": stats["reflector_pixels"],
                          "mesh_vertices": len(mesh.vertices), "mesh_faces": len(mesh.faces)},
                  mirror_world="masked by reflectors.json" if reflectors else
                  "NOT masked: no reflectors.json, mirror-world geometry may be in the mesh")
    # --- write (everything above can fail without leaving a file behind) ---
    import os
    import tempfile
    ws.path("sfm").mkdir(exist_ok=True)
    with tempfile.TemporaryDirectory(dir=ws.path("sfm"), prefix=".ibrtmp-") as tmp:
        if rec is not None:
            rec.write_text(tmp)
        else:
            write_colmap_model(cams, Path(tmp), text=True)
        for f in sorted(Path(tmp).iterdir()):
            with atomic_path(ws.path(f"sfm/{f.name}")) as dst:
                os.replace(f, dst)
    ws.write_text(L.REGISTERED_CAMERAS, cameras_to_json(cams))
    write_ply(ws.path(L.GLOBAL_MESH), mesh, comment="ibr_pipeline global_mesh")
    report["timings"]["total_s"] = time.perf_counter() - t_start
    ws.write_json(L.GLOBAL_REPORT, report)
    log.info("global_mesh: %d/%d views registered, %s mesh %d faces, %.1f s", len(registered),
             len(scene.views), dense, len(mesh.faces), report["timings"]["total_s"])


def _resize_mask(mask: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    import cv2
    return cv2.resize(mask.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0


STAGE = Stage(name="global_mesh", help="camera poses (given or COLMAP SfM) and a global mesh "
              "(RGB-D TSDF fusion or plane-sweep MVS), reflectors masked (Xu §4.1)",
              config=GlobalMeshConfig, version="3", run=run, inputs=inputs, outputs=OUTPUTS)
