"""Stage `reflectors`: which planes of the scene are reflectors (Xu et al. §4.3: user-marked
planes, "we detect reflective planes ... using a multi-view consistency cue"), once for the scene.

Reads global/cameras.json, global/mesh.ply (G), global/reflectors.json (the user's planes in the
scene frame, when input/reflectors.json exists), global/found_reflectors.json (what global_mesh
found behind planes of the depth: taken as given) and, when detection runs, every registered
view's image and views/<v>/depth.npy. Writes reflection/planes.json: the reflectors (user-given,
then found by global_mesh, then detected) and every candidate with its evidence and the reason
it was kept or dropped (docs/REFLECTION.md, "Detection"). Candidates are scored in parallel
(`--jobs`); the per-view `reflection` stage reads the file as an ordinary input. The work is
geometry/reflection_views.py's.
"""
from __future__ import annotations

import logging

from .. import layout as L
from ..cache import ProcessCache
from ..executors import LocalExecutor
from ..geometry.reflection_views import (Loader, ReflectorsConfig, compute_planes, detect_enabled,
                                         score_plane, user_reflectors_key)
from ..runner import Stage, StageContext
from .common import registered_views

log = logging.getLogger("ibr_pipeline.reflectors")


def inputs(ctx: StageContext) -> list[str]:
    keys = [L.REGISTERED_CAMERAS, L.GLOBAL_MESH] + user_reflectors_key(ctx.ws, ctx.scene)
    if detect_enabled(ctx.ws, ctx.config):
        for v in registered_views(ctx):
            keys += [ctx.scene.view(v).image, ctx.ws.view_file(v, L.DEPTH)]
    return keys


_LOADERS = ProcessCache(1)


def _score_task(ws, scene, cfg, cand) -> dict:
    """score_plane in a worker process, with one Loader per (workspace, config) there."""
    loader = _LOADERS.get((str(ws.root), cfg.digest()), lambda: Loader(ws, scene, cfg))
    return score_plane(loader, cand)


def _score_all(ctx: StageContext):
    """score_plane over the candidates: ctx.jobs worker processes (each reads the views once),
    in this process when jobs = 1; results in candidate order."""
    def score_all(loader, cands):
        from tqdm import tqdm
        out = [None] * len(cands)
        with LocalExecutor(max(1, min(ctx.jobs, len(cands)))) as ex, \
                tqdm(total=len(cands), desc="reflectors: candidate planes", unit="plane",
                     disable=not ctx.progress, leave=False) as bar:
            if ex.jobs == 1:
                results = ((i, score_plane(loader, c)) for i, c in enumerate(cands))
            else:
                results = ex.results(_score_task, [(ctx.ws, ctx.scene, ctx.config, c) for c in cands])
            for i, res in results:
                out[i] = res
                bar.update(1)
        return out
    return score_all


def run(ctx: StageContext) -> None:
    planes = compute_planes(Loader(ctx.ws, ctx.scene, ctx.config), _score_all(ctx))
    cands = planes["candidates"]
    log.info("reflectors: %d user-given, %d found in the depth by global_mesh, %d detected of %d "
             "candidate plane(s)%s", sum(r.get("source") == "user" for r in planes["reflectors"]),
             sum(r.get("source") == "depth" for r in planes["reflectors"]),
             sum(r.get("source") == "detected" for r in planes["reflectors"]), len(cands),
             "" if detect_enabled(ctx.ws, ctx.config) else " (detection off)")
    for c in cands:
        if c["kept"]:
            log.info("reflectors: %s kept: %s", c["name"], c["reason"])
    ctx.ws.write_json(L.PLANES, planes)


STAGE = Stage(name="reflectors", help="reflector planes: user-given + detected (Xu et al. §4.3)",
              config=ReflectorsConfig, version="4", run=run, inputs=inputs, outputs=[L.PLANES])
