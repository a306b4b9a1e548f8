"""Stage `render_views`: novel views by view selection, fuzzy depth test and two-layer blending
(Xu et al. 2021, §5.1; the renderer is `render/ibr.py`).

Render sets, each `renders/<set>/NNNN.png` + `timings.json` + `cameras.json` (the cameras, in the
cameras.json format, so `evaluate` and `ibr render` know what was rendered):
  test         the input's held-out cameras (gt/test_cameras.json, in the scene frame); else the
               images `poses` held out (poses.holdout_every); else a leave-one-out set: every
               registered capture view rendered from the others
  test_single  the same cameras with the single-layer baseline (decomposition off), if `baseline`
  fly          gt/flythrough_cameras.json, or a smooth path through the registered cameras
  fly_single   the fly-through with the single-layer baseline, if `baseline`
  tour         `tour_frames` frames on a smooth path through the fly-through (else the registered)
               cameras: the video of evaluate and the report, long enough to watch
  loo          leave-one-out renders of every capture view (`leave_one_out`; supersample trains on them)
Single-layer rendering is used throughout when `reflection` has not run; when no view has a
reflection layer the `<set>_single` renders are copies of `<set>` (the same model renders them).
"""
from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

from .. import layout as L
from ..config import StageConfig, param
from ..render.ibr import RenderSettings
from ..runner import Stage, StageContext
from .common import input_cameras, registered_views

log = logging.getLogger("ibr_pipeline.render_views")



@dataclass(frozen=True)
class RenderViewsConfig(StageConfig):
    baseline: bool = param(True, "also render the single-layer baseline (<set>_single)")
    leave_one_out: bool = param(True, "also render every capture view from the others (renders/loo)")
    fly_frames: int = param(0, "render at most this many fly-through frames (0 = all; a generated "
                            "path has 48)", min=0, max=100000)
    tour_frames: int = param(96, "frames of the tour video's smooth path (4 s at 24 fps; 0 = no "
                             "tour)", min=0, max=100000)
    renderer: RenderSettings = param(RenderSettings(), "view selection, depth test and blending "
                                     "(§5.1)")


def render_sets(ctx: StageContext) -> dict[str, dict]:
    """{set: {"cameras": [(name, Camera)], "exclude": [names or None], "source": str}} — a pure
    function of the workspace and config, shared by the inputs/outputs declarations and run()."""
    from ..render.video import interpolate_path
    cfg = ctx.config
    cams = L.registered_cameras(ctx.ws)
    names = [n for n in ctx.scene.names if n in cams]
    loo = {"cameras": [(n, cams[n]) for n in names], "exclude": names, "source": "leave_one_out"}
    test, src = input_cameras(ctx, L.TEST_CAMERAS), "heldout"
    if not test:
        test, src = L.heldout_cameras(ctx.ws), "heldout_captures"
    sets = {"test": {"cameras": list(test.items()), "exclude": [None] * len(test),
                     "source": src} if test else dict(loo)}
    fly = input_cameras(ctx, L.FLY_CAMERAS)
    if fly:
        fly_list, src = list(fly.items()), "flythrough"
    else:
        path = interpolate_path([cams[n] for n in names], 48) if len(names) >= 2 else []
        fly_list, src = [(f"path_{i:04d}", c) for i, c in enumerate(path)], "interpolated"
    if cfg.fly_frames:
        fly_list = fly_list[:cfg.fly_frames]
    if fly_list:
        sets["fly"] = {"cameras": fly_list, "exclude": [None] * len(fly_list), "source": src}
    if cfg.baseline:
        for s in list(sets):
            sets[f"{s}_single"] = dict(sets[s], layers=False)
    keys = [c for _, c in fly_list] if fly else [cams[n] for n in names]
    if cfg.tour_frames >= 2 and len(keys) >= 2:
        sets["tour"] = {"cameras": [(f"tour_{i:04d}", c) for i, c in
                                    enumerate(interpolate_path(keys, cfg.tour_frames))],
                        "exclude": [None] * cfg.tour_frames, "source": "interpolated"}
    if cfg.leave_one_out:
        sets["loo"] = loo
    return sets


def inputs(ctx: StageContext) -> list[str]:
    keys = [L.REGISTERED_CAMERAS, L.HELDOUT_CAMERAS, L.POSES_REPORT]
    if not ctx.ws.path(L.REGISTERED_CAMERAS).is_file():
        return keys
    for v in registered_views(ctx):
        keys += [ctx.scene.view(v).image] + L.renderer_files(ctx.ws, v)
    keys += [k for k in (L.TEST_CAMERAS, L.FLY_CAMERAS) if ctx.ws.path(k).is_file()]
    return keys


def outputs(ctx: StageContext) -> list[str]:
    if not ctx.ws.path(L.REGISTERED_CAMERAS).is_file():
        return []
    out = [L.RENDER_SETTINGS]
    for s, spec in render_sets(ctx).items():
        out += [L.render_file(s, f"{i:04d}.png") for i in range(len(spec["cameras"]))]
        out += [L.render_file(s, "timings.json"), L.render_file(s, "cameras.json")]
    return out


def run(ctx: StageContext) -> None:
    import numpy as np
    from tqdm import tqdm

    from ..io.images import write_image
    from ..render.gl import renderer_name
    from ..render.ibr import IBRModel
    from ..scene import cameras_to_json

    ws = ctx.ws
    progress = ctx.progress and log.isEnabledFor(logging.INFO)
    settings = ctx.config.renderer
    sets = render_sets(ctx)
    models = {True: IBRModel.load(ws, layers=True, settings=settings, progress=progress)}
    two = sum(v.layers[1] is not None for v in models[True].views)
    if two and any(not spec.get("layers", True) for spec in sets.values()):
        models[False] = IBRModel.load(ws, layers=False, settings=settings, progress=progress)
    # what `supersample` renders its training pairs with, so that DSRNet learns these renders
    ws.write_json(L.RENDER_SETTINGS, dataclasses.asdict(models[True].settings))
    log.info("render_views: %d views (%d with a reflection layer), GL: %s", len(models[True].views),
             two, renderer_name())
    for s, spec in sets.items():
        if not spec.get("layers", True) and not two:
            # no view has a second layer: the single-layer model is the same model, so its
            # renders are the layered set's (rendered first: `<set>` precedes `<set>_single`)
            _copy_set(ws, s.removesuffix("_single"), s, len(spec["cameras"]))
            continue
        model = models[spec.get("layers", True)]
        frames, prev = [], None
        sequential = s.startswith(("fly", "tour"))
        for i, ((name, cam), excl) in enumerate(tqdm(list(zip(spec["cameras"], spec["exclude"])),
                                                     desc=f"render {s}", unit="frame",
                                                     disable=not progress, leave=False)):
            f = model.render(cam, exclude=() if excl is None else (excl,),
                             previous=prev if sequential else None)
            prev = f
            write_image(ws.path(L.render_file(s, f"{i:04d}.png")), f.color, ctx.scene.image_encoding)
            frames.append({"index": i, "name": name, "ms": round(f.ms, 3),
                           **{k: round(v, 3) for k, v in f.timings.items()},
                           "selected": f.selected, "holes": round(float(1 - f.covered.mean()), 5)})
        ms = [f["ms"] for f in frames]
        ws.write_json(L.render_file(s, "timings.json"), {
            "set": s, "source": spec["source"], "layers": bool(spec.get("layers", True)) and two > 0,
            "size": list(spec["cameras"][0][1].size) if frames else None,
            "renderer": renderer_name(), "median_ms": float(np.median(ms)) if ms else None,
            "frames": frames})
        ws.write_text(L.render_file(s, "cameras.json"), cameras_to_json(dict(spec["cameras"])))
        log.info("render_views: %-12s %3d frames, median %.1f ms/frame", s, len(frames),
                 float(np.median(ms)) if ms else float("nan"))
    for m in models.values():
        m.release()


def _copy_set(ws, src: str, dst: str, n: int) -> None:
    import json
    for name in [f"{i:04d}.png" for i in range(n)] + ["cameras.json"]:
        with ws.atomic_write(L.render_file(dst, name)) as f:
            f.write(ws.path(L.render_file(src, name)).read_bytes())
    timings = json.loads(ws.path(L.render_file(src, "timings.json")).read_text())
    ws.write_json(L.render_file(dst, "timings.json"), {**timings, "set": dst, "copied_from": src})
    log.info("render_views: %-12s %3d frames, copied from %s (no view has a reflection layer)",
             dst, n, src)


STAGE = Stage(name="render_views", help="view selection and blending into novel views (Xu §5.1)",
              config=RenderViewsConfig, version="8", run=run, inputs=inputs, outputs=outputs)
