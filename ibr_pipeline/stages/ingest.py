"""Stage `ingest`: read the input folder, check every file a later stage will read, write scene.json.

Bad input is caught here, before any expensive stage: an image that does not decode, a camera with
NaNs, a depth frame whose aspect ratio differs from its image, a missing reflector mask. Each raises
InputError naming the file, and scene.json is not written.
"""
from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

from .. import layout as L
from ..config import StageConfig, param
from ..errors import InputError, confined
from ..runner import Stage, StageContext
from ..io.inputs import input_files, read_input
from ..scene import Scene

log = logging.getLogger("ibr_pipeline.ingest")


@dataclass(frozen=True)
class IngestConfig(StageConfig):
    min_views: int = param(2, "fewer images than this is an error", min=1)
    check_pixels: bool = param(True, "decode every image fully (catches truncated files early)")


def inputs(ctx: StageContext) -> list[str]:
    return [ctx.ws.key(p) for p in input_files(ctx.ws.input_root)]


def run(ctx: StageContext) -> None:
    from tqdm import tqdm

    from ..io.images import image_size, read_depth_png, read_image

    ws, cfg = ctx.ws, ctx.config
    scene = read_input(ws.input_root)
    if len(scene.views) < cfg.min_views:
        raise InputError(f"{ws.input_root}: {len(scene.views)} image(s) found, "
                         f"ingest.min_views is {cfg.min_views}")
    for view in tqdm(scene.views, desc="ingest: checking images", unit="img", leave=False,
                     disable=not ctx.progress):
        path = ws.path(view.image)
        if cfg.check_pixels:
            h, w = read_image(path).shape[:2]
        else:
            w, h = image_size(path)
        if view.camera is not None and (view.camera.width, view.camera.height) != (w, h):
            raise InputError(f"{path}: image is {w}x{h} but its camera says "
                             f"{view.camera.width}x{view.camera.height}")
        if view.depth is not None:
            dpath = ws.path(view.depth)
            dh, dw = read_depth_png(dpath).shape
            if abs(dw / dh - w / h) > 0.01 * (w / h):
                raise InputError(f"{dpath}: depth is {dw}x{dh}, which does not have the aspect "
                                 f"ratio of its {w}x{h} image (depth must cover the same view)")
    reflectors = []
    for r in scene.reflectors:
        masks = {}
        for view_name, rel in r.masks.items():
            if view_name not in scene.names:
                raise InputError(f"{ws.input_root / 'reflectors.json'}: reflector {r.name!r} has a "
                                 f"mask for unknown view {view_name!r}")
            where = f"{ws.input_root / 'reflectors.json'}: reflector {r.name!r} mask of {view_name!r}"
            confined(ws.input_root, rel, where)  # a shared reflectors.json must not read outside
            key = f"input/{rel}"
            mw, mh = image_size(ws.path(key))
            cam = scene.view(view_name)
            iw, ih = image_size(ws.path(cam.image))
            if (mw, mh) != (iw, ih):
                raise InputError(f"{ws.path(key)}: mask is {mw}x{mh}, its image is {iw}x{ih}")
            masks[view_name] = key
        reflectors.append(dataclasses.replace(r, masks=masks))
    scene = Scene(scene.views, tuple(reflectors), scene.source)
    ws.write_text(ws.SCENE, scene.to_json())
    posed = len(scene.posed_views)
    log.info("ingest: %d images (%d with cameras, from %s), %d with depth, %d reflector(s)",
             len(scene.views), posed, scene.source, sum(v.depth is not None for v in scene.views),
             len(scene.reflectors))
    if posed == 0:
        log.info("ingest: no camera poses given: the poses stage will run SfM")


STAGE = Stage(name="ingest", help="read the input folder, check every file, write scene.json",
              config=IngestConfig, version="1", run=run, needs_scene=False,
              inputs=inputs, outputs=(L.SCENE,))
