"""The user's reflectors (input/reflectors.json in the scene frame, `layout.scene_reflectors`)
with every one given by its outline in a photograph placed on the surface around that outline.

`global_mesh` (to mask the mirror world out of G) and the `reflectors` stage (planes.json) both
call `user_reflectors` on the same saved depth map, so both see the same plane.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from .. import layout as L
from ..errors import InputError


def user_reflectors(ws, scene, dense: str | None = None) -> tuple:
    """layout.scene_reflectors with every outline-given one placed: its plane fitted to the
    surface around the outline (planes.plane_from_outline) in layout.outline_depth_key's map
    (dense: how G is made; None = as global/report.json says)."""
    from ..io.images import read_depth_png  # PIL: not at `ibr --help`'s import of the stages
    from .planes import plane_from_outline
    out, cams = [], None
    for r in L.scene_reflectors(ws):
        if r.plane is None:
            cams = L.registered_cameras(ws) if cams is None else cams
            view, pts = r.outline
            where = f"{ws.input_root / 'reflectors.json'}: reflector {r.name!r} outline"
            if view not in cams:
                raise InputError(f"{where}: view {view!r} is not a registered training view "
                                 f"(held out or not registered); outline it in one of "
                                 f"{', '.join(sorted(cams)[:4])}, ...")
            dense = L.global_dense(ws) if dense is None else dense
            key = L.outline_depth_key(scene, view, dense)
            if key is None or not ws.exists(key):
                raise InputError(f"{where}: view {view!r} has no depth to fit the plane to")
            depth = np.load(ws.path(key)) if key.endswith(".npy") else read_depth_png(ws.path(key))
            try:
                plane, poly = plane_from_outline(cams[view], depth, np.asarray(pts))
            except ValueError as e:
                raise InputError(f"{where}: {e}; outline it in a view where the surface around "
                                 "it has depth") from None
            r = dataclasses.replace(r, plane=tuple(map(float, plane)),
                                    polygon=tuple(tuple(map(float, p)) for p in poly))
        out.append(r)
    return tuple(out)
