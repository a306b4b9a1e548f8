"""Stage `poses` (Xu et al. §4.1, first half): a camera for every image, in the scene frame.

Poses are taken from the input (any pose source ingest read: COLMAP, nerfstudio, LLFF, TUM,
ScanNet, cameras.json) unless `force_sfm`; otherwise pycolmap
SfM (geometry/sfm.py), whose model is written here so that a failure of the dense stage after it
never costs the SfM again. The scene frame (docs/DESIGN.md "Scene frame") is metric when the
capture says how: RGB-D depth frames (SfM scaled to the depth at its keypoints and refined by ICP)
or a user `scale`; otherwise it is *normalised*: scaled so that the median scene depth is
`normalised_depth`, the room-sized distance every length default of the pipeline is written for.
Held-out images (`holdout_every`, the LLFF/NeRF protocol) take part in SfM but not in anything
after it: their cameras go to global/heldout_cameras.json and they become the test set.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import layout as L
from ..config import StageConfig, param
from ..errors import InputError
from ..runner import Stage, StageContext

log = logging.getLogger("ibr_pipeline.poses")

OUTPUTS = L.SFM_FILES + (L.REGISTERED_CAMERAS, L.HELDOUT_CAMERAS, L.POSES_REPORT, L.SCENE_REFLECTORS)


@dataclass(frozen=True)
class PosesConfig(StageConfig):
    force_sfm: bool = param(False, "run SfM even when the input gives camera poses")
    matching: str = param("auto", "SfM matching: sequential (video-like), exhaustive (small sets); "
                          "auto = sequential when the names are numbered frames of one capture or "
                          "there are more than 40 images, else exhaustive",
                          choices=("auto", "sequential", "exhaustive"))
    sequential_overlap: int = param(10, "sequential matching: neighbours matched per image", min=1, max=100)
    close_loop: bool = param(True, "sequential matching: also match the last images with the first "
                             "(a capture that walks round the room)")
    camera_model: str = param("SIMPLE_PINHOLE", "SfM's camera when the input gives no intrinsics; "
                              "a distorted model (COLMAP's SIMPLE_RADIAL, RADIAL, OPENCV) is "
                              "estimated and every image undistorted into sfm/images/ for the "
                              "later stages", choices=("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL",
                                                       "OPENCV"))
    min_registered: int = param(3, "fewer registered training views than this is an error", min=2)
    scale: float = param(0.0, "metres per input unit (given poses or SfM): makes the scene metric "
                         "when there are no depth frames; 0 = metric from depth frames if every "
                         "view has one, else normalised", min=0.0, max=1e9)
    normalised_depth: float = param(2.5, "median scene depth of the normalised frame (a room seen "
                                    "from a few metres: the lengths of all defaults assume it)",
                                    min=0.01, max=1e4)
    holdout_every: int = param(0, "hold out images 0, N, 2N, ... (LLFF/NeRF protocol): posed by "
                               "SfM with the rest, then left out of the reconstruction and used as "
                               "the test set (0 = none)", min=0, max=1000)
    max_jump: float = param(4.0, "warn when a step of the ordered camera path is longer than this "
                            "many median steps", min=1.0, max=1e3)
    threads: int = param(1, "threads for pycolmap", min=1, max=256, affects_output=False)


def outputs(ctx: StageContext) -> list[str]:
    """The fixed outputs, and with a distorted SfM lens global/views.json and the undistorted
    images and depth frames it names."""
    import json
    keys = list(OUTPUTS)
    p = ctx.ws.path(L.POSED_VIEWS)
    if p.is_file():
        try:
            views = json.loads(p.read_text()).get("views", {})
            keys += [L.POSED_VIEWS] + sorted(k for d in views.values() for k in d.values() if k)
        except (json.JSONDecodeError, AttributeError, OSError):
            pass  # a broken file: the stage reruns on "output changed"
    return keys


def inputs(ctx: StageContext) -> list[str]:
    keys = [L.SCENE]
    for v in ctx.scene.views:
        keys.append(v.image)
        if v.depth:
            keys.append(v.depth)
    for k in (L.USER_REFLECTORS, L.INPUT_CAMERAS, L.GT_CAMERAS):
        if ctx.ws.path(k).is_file():
            keys.append(k)
    if ctx.scene.sparse:
        from ..io.colmap import model_files
        keys += [ctx.ws.key(p) for p in model_files(ctx.ws.path(ctx.scene.sparse))]
    return keys


def _link_images(ws, scene, folder: Path) -> None:
    """`folder/<view name>` -> each view's image: SfM reads one folder by view name, while the
    images may sit in the input folder and in ingest/ (prepared frames)."""
    for v in scene.views:
        link = folder / v.name
        link.parent.mkdir(parents=True, exist_ok=True)
        link.symlink_to(ws.path(v.image).resolve())


def _matching(cfg, names) -> str:
    from ..geometry.scale import numbered_sequence
    if cfg.matching != "auto":
        return cfg.matching
    return "sequential" if len(names) > 40 or numbered_sequence(names) else "exhaustive"


def _run_sfm(ctx, given):
    from ..geometry import sfm
    from ..io.images import image_size
    import tempfile

    ws, cfg, scene = ctx.ws, ctx.config, ctx.scene
    sizes = {image_size(ws.path(v.image)) for v in scene.views}
    matching = _matching(cfg, scene.names)
    # images of several sizes (phones, mixed cameras) get a camera each, as COLMAP's PER_IMAGE
    log.info("poses: SfM on %d images, %s matching, %s", len(scene.names), matching,
             "one shared camera" if len(sizes) == 1 else f"a camera per image ({len(sizes)} sizes)")
    intr = next(iter(given.values())) if given and len(sizes) == 1 else None
    ws.path(".ibr").mkdir(exist_ok=True)
    with tempfile.TemporaryDirectory(dir=ws.path(".ibr"), prefix="sfm-") as tmp:
        _link_images(ws, scene, Path(tmp) / "images")
        res = sfm.run_sfm(Path(tmp) / "images", scene.names, Path(tmp) / "work", matching, intr,
                          cfg.sequential_overlap, cfg.threads, close_loop=cfg.close_loop,
                          single_camera=len(sizes) == 1, camera_model=cfg.camera_model)
    return res


def _point_depths(ctx, cams, rec) -> dict:
    """{view: z-depths of the scene points it sees}, input frame: the SfM / COLMAP model's tracks,
    else SIFT matches triangulated with the given poses."""
    from ..geometry import scale, sfm
    from ..io.images import read_image
    if rec is not None:
        names = {img.name for img in rec.images.values() if img.has_pose}
        return {n: sfm.keypoint_depths(rec, n)[1] for n in cams if n in names}
    pairs = scale.neighbour_pairs(cams, k=2)
    need = {x for p in pairs for x in p}
    images = {n: read_image(ctx.ws.path(ctx.scene.view(n).image)) for n in need}
    return {n: z for n, (_, z) in scale.triangulate_given(images, cams, pairs).items()}


def _frame_depths(ctx, cams, depth_views) -> dict:
    """{view: a sample of its depth frame's valid depths} (metres), views with a depth frame."""
    from ..io.images import read_depth_png
    out = {}
    for n in (n for n in cams if n in depth_views):
        d = read_depth_png(depth_views[n])[::8, ::8]
        out[n] = d[d > 0].astype(np.float64)
    return out


def _depth_scale(ctx, cams, rec, depth_views, median_depth: float):
    """Metric Sim(3) of SfM poses from the depth frames (keypoint depth ratio + ICP, Xu §4.1)."""
    from ..geometry import align, sfm
    from ..io.images import read_depth_png
    zs, zd = [], []
    for n, cam in ((n, c) for n, c in cams.items() if n in depth_views):
        d = read_depth_png(depth_views[n])
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
    with_depth = [(n, c) for n, c in scaled.items() if n in depth_views]
    for n, cam in with_depth[:: max(1, len(with_depth) // 20)]:
        d = read_depth_png(depth_views[n])
        c = cam.resized(d.shape[1], d.shape[0])
        uv = c.pixel_grid()[::4, ::4].reshape(-1, 2)
        z = d[::4, ::4].reshape(-1)
        dense.append(c.unproject(uv[z > 0], z[z > 0]))
    # ICP's correspondence distance is a fraction of the scene depth, not a fixed length
    T, fit, rmse = align.icp_refine(pts, np.concatenate(dense), max_distance=0.02 * median_depth)
    s2 = float(np.cbrt(np.linalg.det(T[:3, :3])))
    R, t = T[:3, :3] / s2, T[:3, 3]
    return s * s2, R, t, {"method": "keypoint depth scale + ICP", "icp_fitness": fit,
                          "icp_rmse": rmse}


def _frame(ctx, cams, rec, depth_views, given_poses: bool):
    """(s, R, t, units, info, {view: depths of what it sees, scene frame}) of the map
    x_scene = s R x_input + t."""
    from ..geometry.scale import normalising_scale
    cfg = ctx.config
    eye, zero = np.eye(3), np.zeros(3)
    rgbd = any(n in depth_views for n in cams)  # depth frames are metres (scene.py)
    sensed = _frame_depths(ctx, cams, depth_views) if rgbd else None
    if cfg.scale > 0:
        depths = sensed or {n: z * cfg.scale for n, z in _point_depths(ctx, cams, rec).items()}
        return cfg.scale, eye, zero, "metres", {"method": "user scale (poses.scale)"}, depths
    if rgbd:
        if given_poses:
            return 1.0, eye, zero, "metres", {"method": "given poses with depth frames"}, sensed
        med = float(np.median(np.concatenate([z for z in sensed.values() if len(z)])))
        s, R, t, info = _depth_scale(ctx, cams, rec, depth_views, med)
        return s, R, t, "metres", info, sensed
    depths = _point_depths(ctx, cams, rec)
    flat = np.concatenate([z for z in depths.values() if len(z)] or [np.zeros(0)])
    try:
        s = normalising_scale(flat, cfg.normalised_depth)
    except ValueError as e:
        raise InputError(f"{ctx.ws.input_root}: cannot measure the scene scale ({e}); give "
                         "depth frames or poses.scale (metres per input unit)") from None
    return s, eye, zero, "normalised", {
        "method": f"median scene depth -> {cfg.normalised_depth:g}",
        "median_depth_input_units": float(np.median(flat[flat > 0]))}, {
        n: z * s for n, z in depths.items()}


def _path_check(cfg, names, cams, sfm: bool) -> list[dict]:
    from ..geometry.scale import path_jumps
    order = [n for n in names if n in cams]
    C = np.array([cams[n].center for n in order]).reshape(-1, 3)
    jumps = [{"from": order[i], "to": order[i + 1], "median_steps": round(r, 2)}
             for i, r in path_jumps(C, cfg.max_jump)]
    if jumps:
        shown = ", ".join(f"{j['from']} -> {j['to']} ({j['median_steps']:.1f}x)" for j in jumps[:6])
        hint = ("if it is a video or a walk, try --set poses.matching=sequential" if sfm else
                "check the input's poses of these frames")
        log.warning("poses: the camera path jumps %d time(s) by more than %g median steps: %s. "
                    "A capture taken in order should move smoothly; %s", len(jumps), cfg.max_jump,
                    shown, hint)
    return jumps


def _gt_alignment(ctx, cams) -> dict | None:
    """Sim(3) from a synthetic capture's true camera frame (input/gt/cameras.json) to the scene
    frame, from the camera centres (Umeyama): places gt/ test cameras when poses came from SfM."""
    from ..geometry.align import umeyama
    from ..scene import cameras_from_json
    p = ctx.ws.path(L.GT_CAMERAS)
    if not p.is_file():
        return None
    gt = cameras_from_json(p)
    common = [n for n in cams if n in gt]
    if len(common) < 3:
        return None
    src = np.array([gt[n].center for n in common])
    dst = np.array([cams[n].center for n in common])
    s, R, t = umeyama(src, dst)
    res = np.linalg.norm((s * src @ R.T + t) - dst, axis=1)
    return {"scale": s, "R": R.tolist(), "t": t.tolist(), "views": len(common),
            "rms_residual": float(np.sqrt(np.mean(res ** 2)))}


def _undistort(ctx, rec, cams, staging: Path):
    """SfM estimated a distorted lens (`camera_model`): every registered image (and its depth) is
    undistorted onto pycolmap's pinhole choice into `staging` (moved to sfm/images, sfm/depth
    with the other outputs), the model's cameras and keypoints with them; later stages read these
    images through global/views.json (layout.posed_scene)."""
    from ..io.capture import Frame, lens_from_colmap_camera
    from ..io.colmap import undistort_reconstruction
    from ..io.prepare import Plan, prepare
    lenses = {im.name: lens_from_colmap_camera(rec.cameras[im.camera_id])
              for im in rec.images.values() if im.has_pose}
    undistort_reconstruction(rec)
    out, views = {}, {}
    for n, cam in cams.items():
        v = ctx.scene.view(n)
        stem = Path(n).with_suffix("").as_posix()
        img_key = f"{L.SFM_IMAGES}/{stem}.png"
        depth_key = f"{L.SFM_DEPTH}/{stem}.png" if v.depth else None
        f = Frame(n, ctx.ws.path(v.image), cam.cam_from_world, lenses[n],
                  depth=ctx.ws.path(v.depth) if v.depth else None)
        paths = [staging / Path(k).relative_to("sfm") for k in (img_key, depth_key) if k]
        for q in paths:
            q.parent.mkdir(parents=True, exist_ok=True)
        out[n] = prepare(f, Plan(False, True, bool(v.depth)), paths[0],
                         paths[1] if depth_key else None)
        views[n] = {"image": img_key, "depth": depth_key}
    lens = next(iter(lenses.values()))
    log.info("poses: SfM's %s lens %s undistorted: %d images into %s", lens.model,
             [round(x, 4) for x in lens.params], len(out), ctx.ws.path(L.SFM_IMAGES))
    return out, views


def run(ctx: StageContext) -> None:
    import tempfile

    # undistorted images are staged and moved into sfm/ with the other outputs, at the end
    with tempfile.TemporaryDirectory(dir=ctx.ws.root, prefix=".ibrtmp-poses-") as tmp:
        _run(ctx, Path(tmp))


def _run(ctx: StageContext, staging: Path) -> None:
    import os
    import tempfile

    from ..geometry import align
    from ..io.capture import lens_from_colmap_camera
    from ..geometry.scale import depth_range, holdout_names
    from ..io.colmap import write_colmap_model
    from ..scene import cameras_to_json
    from ..workspace import atomic_path

    t_start = time.perf_counter()
    ws, cfg, scene = ctx.ws, ctx.config, ctx.scene
    depth_views = {v.name: ws.path(v.depth) for v in scene.views if v.depth}  # files
    given = {v.name: v.camera for v in scene.views if v.camera is not None}
    report: dict = {"timings": {}}
    rec = None
    if given and not cfg.force_sfm:
        log.info("poses: using the %d camera poses given by the input (%s); SfM skipped",
                 len(given), scene.source)
        cams = given
        report.update(pose_source=scene.source, reprojection_error_px=None)
        if scene.sparse:
            from ..io.colmap import load_reconstruction
            rec = load_reconstruction(ws.path(scene.sparse))
    else:
        res = _run_sfm(ctx, given)
        cams, rec = res.cameras, res.reconstruction
        report.update(pose_source="sfm", sfm=res.stats,
                      reprojection_error_px=res.stats["reprojection_error_px"])
        if res.stats["models"] > 1:
            lost = [n for n in scene.names if n not in cams]
            log.warning("poses: SfM split the capture into %d models (sizes %s); the largest is "
                        "kept and %d image(s) are dropped: %s. More overlap between neighbouring "
                        "photos joins them", res.stats["models"], res.stats["model_sizes"], len(lost),
                        ", ".join(lost[:8]))
    posed_views = None
    if report["pose_source"] == "sfm" and rec is not None and any(
            lens_from_colmap_camera(c).distorted for c in rec.cameras.values()):
        cams, posed_views = _undistort(ctx, rec, cams, staging)
        depth_views = {n: staging / Path(k).relative_to("sfm") for n, d in posed_views.items()
                       if (k := d["depth"])}
    report["timings"]["poses_s"] = time.perf_counter() - t_start
    s, R, t, units, how, depths = _frame(ctx, cams, rec, depth_views,
                                         given_poses=report["pose_source"] != "sfm")
    cams = {n: align.transform_camera(c, s, R, t) for n, c in cams.items()} if (
        s != 1.0 or not np.allclose(R, np.eye(3)) or np.any(t)) else dict(cams)
    if rec is not None and (s != 1.0 or not np.allclose(R, np.eye(3)) or np.any(t)):
        import pycolmap
        rec.transform(pycolmap.Sim3d(s, pycolmap.Rotation3d(R), t))
    registered = [n for n in scene.names if n in cams]
    unregistered = [n for n in scene.names if n not in cams]
    if unregistered:
        log.warning("poses: %d image(s) not registered, excluded from later stages: %s",
                    len(unregistered), ", ".join(unregistered[:10]))
    heldout = [n for n in holdout_names(scene.names, cfg.holdout_every) if n in cams]
    training = [n for n in registered if n not in heldout]
    if len(training) < cfg.min_registered:
        raise InputError(f"{ws.input_root}: only {len(training)} of {len(scene.views)} images registered "
                         f"for training (poses.min_registered is {cfg.min_registered}"
                         + (f", {len(heldout)} held out" if heldout else "") + ")")
    seen = [z for z in depths.values() if len(z)]
    # a view with too few points of its own searches the whole scene's range
    every = depth_range(np.concatenate(seen)) if seen else None
    ranges = {n: r for n in training if (r := depth_range(depths.get(n, np.zeros(0))) or every)}
    jumps = _path_check(cfg, scene.names, cams, sfm=report["pose_source"] == "sfm")
    scene_depth = float(np.median(np.concatenate(seen))) if seen else None
    report.update(
        units=units, scale=s, transform={"scale": s, "R": R.tolist(), "t": np.asarray(t).tolist()},
        alignment=how, median_scene_depth=scene_depth, depth_ranges=ranges, path_jumps=jumps,
        gt_to_scene=_gt_alignment(ctx, cams), registered=training, heldout=heldout,
        unregistered=unregistered, counts={"images": len(scene.views), "registered": len(registered),
                                           "training": len(training), "heldout": len(heldout)})
    log.info("poses: %d/%d registered (%d held out), scene frame %s (x%.4g), median depth %s",
             len(registered), len(scene.views), len(heldout), units, s,
             "?" if scene_depth is None else f"{scene_depth:.3g}")
    # --- write (everything above can fail without leaving a file behind) ---
    ws.path("sfm").mkdir(exist_ok=True)
    with tempfile.TemporaryDirectory(dir=ws.path("sfm"), prefix=".ibrtmp-") as tmp:
        if rec is not None:
            rec.write_text(tmp)
        else:
            write_colmap_model({n: cams[n] for n in registered}, Path(tmp), text=True)
        for f in sorted(Path(tmp).iterdir()):
            with atomic_path(ws.path(f"sfm/{f.name}")) as dst:
                os.replace(f, dst)
    for src in sorted(p for p in staging.rglob("*") if p.is_file()):
        dst = ws.path(f"sfm/{src.relative_to(staging).as_posix()}")
        dst.parent.mkdir(parents=True, exist_ok=True)
        os.replace(src, dst)
    if posed_views is not None:
        ws.write_json(L.POSED_VIEWS, {"format": "ibr_pipeline.views/1", "views": posed_views})
    elif ws.path(L.POSED_VIEWS).is_file():
        ws.path(L.POSED_VIEWS).unlink()  # a pinhole run after a distorted one: no stale overlay
    ws.write_text(L.REGISTERED_CAMERAS, cameras_to_json({n: cams[n] for n in training}))
    ws.write_text(L.HELDOUT_CAMERAS, cameras_to_json({n: cams[n] for n in heldout}))
    ws.write_json(L.SCENE_REFLECTORS, {"format": "ibr_pipeline.reflectors/1", "units": units,
                                       "reflectors": [align.transform_reflector(r, s, R, t).to_dict()
                                                      for r in scene.reflectors]})
    report["timings"]["total_s"] = time.perf_counter() - t_start
    ws.write_json(L.POSES_REPORT, report)


STAGE = Stage(name="poses", help="camera poses (given or COLMAP SfM) in a metric or normalised "
              "scene frame, held-out split, path check (Xu §4.1)",
              config=PosesConfig, version="3", run=run, inputs=inputs, outputs=outputs)
