"""Stage `reflection`: two-layer reflection decomposition (Xu et al. §4.3, Eqs. 3-13), per view.

Reads global/cameras.json, global/mesh.ply (G), input/reflectors.json (user planes, optional) and
every registered view's image and views/<v>/depth.npy, mesh.ply. Writes reflection/planes.json
(detected + user-given reflectors, written identically by every view task; computed once under a
file lock) and per view layers.json; views that see a reflector also get I0.png, I1.png, beta.npy,
M0.ply, M1.ply (docs/PIPELINE.md). The work is geometry/reflection_views.py's; docs/REFLECTION.md
explains the choices.
"""
from __future__ import annotations

import json
import logging

from .. import layout as L
from ..cache import ProcessCache, file_key
from ..geometry.reflection_views import (Loader, ReflectionConfig, compute_planes,
                                         decompose_reflector, planes_fingerprint, simplify_m1,
                                         user_reflectors_key)
from ..runner import Stage, StageContext
from .common import registered_views

log = logging.getLogger("ibr_pipeline.reflection")


# --- declarations -------------------------------------------------------------------------------
def inputs(ctx: StageContext) -> list[str]:
    keys = [L.REGISTERED_CAMERAS, L.GLOBAL_MESH] + user_reflectors_key(ctx.ws)
    for v in registered_views(ctx):  # neighbours are chosen at run time: every view may be read
        keys += [ctx.scene.view(v).image, ctx.ws.view_file(v, L.DEPTH)]
    return keys


def view_inputs(ctx: StageContext, view: str) -> list[str]:
    return [ctx.ws.view_file(view, L.MESH)]


def view_outputs(ctx: StageContext, view: str) -> list[str]:
    keys = [L.PLANES, ctx.ws.view_file(view, L.LAYERS)]
    if L.has_two_layers(ctx.ws, view):
        keys += [ctx.ws.view_file(view, f) for f in L.TWO_LAYER_FILES]
    return keys


def get_planes(ctx, loader: Loader) -> dict:
    import fcntl
    fp = planes_fingerprint(ctx.ws, ctx.scene, ctx.config)
    path = ctx.ws.path(L.PLANES)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path.parent / ".planes.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if path.is_file():
            try:
                d = json.loads(path.read_text())
                if d.get("fingerprint") == fp:
                    return d
            except json.JSONDecodeError:
                pass
        d = compute_planes(loader)
        ctx.ws.write_json(L.PLANES, d)
        return d


_LOADERS = ProcessCache(1)


def _loader(ctx) -> Loader:
    """One Loader per worker process and (workspace, config, inputs): a worker that runs several
    views reuses the masks / mirror points / images of the others instead of recomputing them."""
    stamps = tuple(file_key(p) for p in
                   (ctx.ws.path(ctx.ws.view_file(v, L.DEPTH)) for v in registered_views(ctx))
                   if p.is_file())
    key = (str(ctx.ws.root), ctx.config.digest(), planes_fingerprint(ctx.ws, ctx.scene, ctx.config),
           stamps)
    return _LOADERS.get(key, lambda: Loader(ctx.ws, ctx.scene, ctx.config))


def run(ctx: StageContext, view: str) -> None:
    import cv2
    import numpy as np

    from ..geometry.geometry_step import optimised_m0, optimised_m1
    from ..geometry.planes import grid_mesh
    from ..io.images import write_image
    from ..io.mesh import Mesh, read_ply, write_ply

    cfg = ctx.config
    ws = ctx.ws
    loader = _loader(ctx)
    planes = get_planes(ctx, loader)
    loader.reflectors = planes["reflectors"]
    opts = cfg.decompose
    img, _depth, wc, _wi, _wd = loader.raw(view)
    H, W = img.shape[:2]
    results, skipped = [], []
    for refl in planes["reflectors"]:
        n = int(loader.mask(view, refl).sum())
        if n < cfg.min_mask_pixels:
            continue
        r = decompose_reflector(loader, view, refl, opts)
        (skipped if "discarded" in r else results).append(r)
    report = {"reflector": None, "reflectors": [], "discarded": [
        {k: v for k, v in r.items() if k in ("name", "discarded", "neighbours", "mask_pixels")}
        for r in skipped], "work_size": [wc.width, wc.height]}
    if not results:
        ws.write_json(ws.view_file(view, L.LAYERS), report)
        return
    # combine the reflectors of this view: beta (reflectance), R = beta I1, M1 pieces
    beta_w = np.zeros((wc.height, wc.width))
    R_w = np.zeros((wc.height, wc.width, 3))
    verts, faces, off = [], [], 0
    for r in sorted(results, key=lambda r: r["mask_pixels"]):
        m = r["mask"]
        beta_w[m] = r["beta"]
        R_w[m] = r["R"][m]
        X1, D1 = optimised_m1(r["geom"], m, r.get("m1_offset"), r["pose"])  # Eq. 7
        v, f = grid_mesh(X1, np.where(m, D1, 0.0), step=cfg.mesh_step)
        if cfg.m1_simplify and len(f):
            v, f, m1_steps = simplify_m1(v, f, wc, cfg)
            r["m1_simplify"] = m1_steps
        verts.append(v)
        faces.append(f + off)
        off += len(v)
    if (wc.width, wc.height) != (W, H):
        beta = cv2.resize(beta_w, (W, H), interpolation=cv2.INTER_NEAREST)
        R = cv2.resize(R_w, (W, H), interpolation=cv2.INTER_LINEAR) * (beta > 0)[..., None]
    else:
        beta, R = beta_w, R_w
    if any(r["mirror"] for r in results):  # mirror special case at full resolution: I1 = I
        R = np.where((beta >= 1.0)[..., None], img, R)
    R = np.clip(np.minimum(R, img), 0, None)
    I0 = img - R  # Eq. 3: I = I0 + beta I1
    I1 = np.where(beta[..., None] > 0, R / np.maximum(beta, 1e-6)[..., None], 0.0)
    enc = ctx.scene.image_encoding  # layer files are stored like the photographs
    write_image(ws.path(ws.view_file(view, L.I0)), np.clip(I0, 0, 1), enc)
    write_image(ws.path(ws.view_file(view, L.I1)), np.clip(I1, 0, 1), enc)
    with ws.atomic_write(ws.view_file(view, L.BETA)) as f:
        np.save(f, beta.astype(np.float32))
    M0 = read_ply(ws.path(ws.view_file(view, L.MESH)))  # M0: the refined-depth surface mesh
    m0_off = [r["m0_offset"] for r in results if r.get("m0_offset") is not None]
    if m0_off:  # M0's optimised vertex offsets (Eq. 7); masks are disjoint, others are 0
        m0v = optimised_m0(M0.vertices, wc, np.sum(m0_off, axis=0))
        write_ply(ws.path(ws.view_file(view, L.M0)), Mesh(m0v, M0.faces),
                  comment="view mesh with optimised vertex offsets")
    else:
        write_ply(ws.path(ws.view_file(view, L.M0)),
                  Mesh(M0.vertices, M0.faces, normals=M0.normals))
    write_ply(ws.path(ws.view_file(view, L.M1)),
              Mesh(np.concatenate(verts), np.concatenate(faces)), comment="mirror-world geometry")
    main = max(results, key=lambda r: r["mask_pixels"])
    report["reflector"] = main["name"]
    report["reflectors"] = [{k: v for k, v in r.items() if k not in ("R", "mask", "geom",
                                                                      "m1_offset", "m0_offset")}
                            for r in results]
    ws.write_json(ws.view_file(view, L.LAYERS), report)


STAGE = Stage(name="reflection", help="two-layer reflection decomposition (Xu et al. §4.3)",
              config=ReflectionConfig, version="7", run=run, per_view=True,
              inputs=inputs, view_inputs=view_inputs, view_outputs=view_outputs,
              views=registered_views)
