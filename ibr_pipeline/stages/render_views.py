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
  loo          leave-one-out renders of every capture view (`leave_one_out`, off by default;
               supersample renders its own at half resolution)
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
    leave_one_out: bool = param(False, "also render every capture view from the others "
                                "(renders/loo: how well each capture view is predicted; "
                                "nothing downstream reads them)")
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
    """Each set is one task: with `--jobs N` the sets render in N worker processes (each loads the
    models it needs once), largest first; the records are written here."""
    from tqdm import tqdm

    from ..executors import LocalExecutor
    from ..render.gl import renderer_name
    from ..render.ibr import resolve_settings
    from ..render.sets import reflective_views, release_models, render_set

    ws = ctx.ws
    progress = ctx.progress and log.isEnabledFor(logging.INFO)
    settings = resolve_settings(ws, ctx.config.renderer)
    sets = render_sets(ctx)
    names = registered_views(ctx)
    two = len(reflective_views(ws, names))
    # what `supersample` renders its training pairs with, so that DSRNet learns these renders
    ws.write_json(L.RENDER_SETTINGS, dataclasses.asdict(settings))
    log.info("render_views: %d views (%d with a reflection layer), GL: %s", len(names), two,
             renderer_name())
    # no view has a second layer: the single-layer model is the same model, so `<set>_single`
    # is a copy of `<set>`'s renders
    copies = [s for s, spec in sets.items() if not spec.get("layers", True) and not two]
    todo = [s for s in sets if s not in copies]
    jobs = min(max(1, ctx.jobs), len(todo)) if todo else 1
    if jobs > 1:  # the largest sets first, so that the workers finish together
        todo.sort(key=lambda s: -len(sets[s]["cameras"]))
    args = [(ws, sets[s]["cameras"], sets[s]["exclude"],
             [L.render_file(s, f"{i:04d}.png") for i in range(len(sets[s]["cameras"]))],
             bool(sets[s].get("layers", True)), settings, ctx.scene.image_encoding,
             s.startswith(("fly", "tour")), ctx.fingerprint,
             f"render {s}" if progress and jobs == 1 else None) for s in todo]
    bar = tqdm(total=sum(len(sets[s]["cameras"]) for s in todo), desc="render sets",
               unit="frame", disable=not progress or jobs == 1, leave=False)
    try:
        with LocalExecutor(jobs) as ex:
            # each set's records as soon as it is rendered: a killed run leaves whole sets
            for i, frames, exc in ex.map_unordered(render_set, args, in_order=True):
                if exc is not None:
                    raise exc
                _write_set(ws, todo[i], sets[todo[i]], frames, two, jobs)
                bar.update(len(frames))
    finally:
        bar.close()
        release_models()
    for s in copies:
        _copy_set(ws, s.removesuffix("_single"), s, len(sets[s]["cameras"]))


def _write_set(ws, s: str, spec: dict, frames: list, two: int, jobs: int) -> None:
    import numpy as np

    from ..render.gl import renderer_name
    from ..scene import cameras_to_json
    ms = [f["ms"] for f in frames]
    ws.write_json(L.render_file(s, "timings.json"), {
        "set": s, "source": spec["source"], "layers": bool(spec.get("layers", True)) and two > 0,
        "size": list(spec["cameras"][0][1].size) if frames else None,
        "renderer": renderer_name(), "median_ms": float(np.median(ms)) if ms else None,
        "frames": frames, "processes": jobs})
    ws.write_text(L.render_file(s, "cameras.json"), cameras_to_json(dict(spec["cameras"])))
    log.info("render_views: %-12s %3d frames, median %.1f ms/frame", s, len(frames),
             float(np.median(ms)) if ms else float("nan"))


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
