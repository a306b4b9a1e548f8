"""Stage `reflection`: two-layer reflection decomposition (Xu et al. §4.3, Eqs. 3-13), per view.

Reads reflection/planes.json (stage `reflectors`), global/cameras.json, global/mesh.ply (G) and
every registered view's image and views/<v>/depth.npy, mesh.ply. Writes per view layers.json;
views that see a reflector also get I0.png, I1.png, beta.npy, M0.ply, M1.ply (docs/PIPELINE.md).
The work is geometry/reflection_views.py's and reflection_layers.py's; docs/REFLECTION.md
explains the choices.
"""
from __future__ import annotations

import json
import logging

from .. import layout as L
from ..cache import ProcessCache, file_key
from ..errors import InputError
from ..geometry.reflection_views import Loader, ReflectionConfig
from ..runner import Stage, StageContext
from .common import registered_views

log = logging.getLogger("ibr_pipeline.reflection")


# --- declarations -------------------------------------------------------------------------------
def inputs(ctx: StageContext) -> list[str]:
    keys = [L.PLANES, L.REGISTERED_CAMERAS, L.GLOBAL_MESH]
    for v in registered_views(ctx):  # neighbours are chosen at run time: every view may be read
        keys += [ctx.scene.view(v).image, ctx.ws.view_file(v, L.DEPTH)]
    return keys


def view_inputs(ctx: StageContext, view: str) -> list[str]:
    return [ctx.ws.view_file(view, L.MESH)]


def view_outputs(ctx: StageContext, view: str) -> list[str]:
    keys = [ctx.ws.view_file(view, L.LAYERS)]
    if L.has_two_layers(ctx.ws, view):
        keys += [ctx.ws.view_file(view, f) for f in L.TWO_LAYER_FILES]
    return keys


def read_planes(ws) -> dict:
    path = ws.path(L.PLANES)
    try:
        d = json.loads(path.read_text())
        d["reflectors"]
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise InputError(f"{path}: cannot read the reflector planes ({e}); run `ibr run "
                         f"{ws.root} --from reflectors`") from None
    return d


_LOADERS = ProcessCache(1)


def _loader(ctx) -> Loader:
    """One Loader per worker process and (workspace, config, inputs): a worker that runs several
    views reuses the masks / mirror points / images of the others instead of recomputing them."""
    stamps = tuple(file_key(p) for p in
                   (ctx.ws.path(k) for k in [L.PLANES] + [ctx.ws.view_file(v, L.DEPTH)
                                                          for v in registered_views(ctx)])
                   if p.is_file())
    key = (str(ctx.ws.root), ctx.config.digest(), stamps)
    return _LOADERS.get(key, lambda: Loader(ctx.ws, ctx.scene, ctx.config))


def run(ctx: StageContext, view: str) -> None:
    import numpy as np

    from ..geometry.reflection_layers import compose_layers, decompose_view, layer_report
    from ..io.images import write_image
    from ..io.mesh import Mesh, read_ply, write_ply

    ws = ctx.ws
    loader = _loader(ctx)
    loader.reflectors = read_planes(ws)["reflectors"]
    results, report = decompose_view(loader, view, loader.reflectors, ctx.config)
    if not results:
        ws.write_json(ws.view_file(view, L.LAYERS), report)
        return
    img, _depth, wc, _wi, _wd = loader.raw(view)
    M0 = read_ply(ws.path(ws.view_file(view, L.MESH)))  # M0: the refined-depth surface mesh
    lay = compose_layers(results, img, wc, M0.vertices, ctx.config)
    enc = ctx.scene.image_encoding  # layer files are stored like the photographs
    write_image(ws.path(ws.view_file(view, L.I0)), lay.I0, enc)
    write_image(ws.path(ws.view_file(view, L.I1)), lay.I1, enc)
    with ws.atomic_write(ws.view_file(view, L.BETA)) as f:
        np.save(f, lay.beta)
    if lay.m0_vertices is not None:
        write_ply(ws.path(ws.view_file(view, L.M0)), Mesh(lay.m0_vertices, M0.faces),
                  comment="view mesh with optimised vertex offsets")
    else:
        write_ply(ws.path(ws.view_file(view, L.M0)),
                  Mesh(M0.vertices, M0.faces, normals=M0.normals))
    write_ply(ws.path(ws.view_file(view, L.M1)), Mesh(lay.m1_vertices, lay.m1_faces),
              comment="mirror-world geometry")
    ws.write_json(ws.view_file(view, L.LAYERS), layer_report(results, report))


STAGE = Stage(name="reflection", help="two-layer reflection decomposition (Xu et al. §4.3)",
              config=ReflectionConfig, version="9", run=run, per_view=True,
              inputs=inputs, view_inputs=view_inputs, view_outputs=view_outputs,
              views=registered_views)
