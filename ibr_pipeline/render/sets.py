"""Rendering named sets of cameras (the `render_views` stage's test / fly / tour / loo sets), one
set per task so that sets render side by side in worker processes, each with its own GL context.

    frames = render_set(ws, cameras, excludes, paths, layers=True, settings=s, sequential=False)

A set is the unit of work because fly-throughs and tours pass each frame to the next (view
selection hysteresis, §5.1.2): a set cut into pieces would render differently at the cuts. The
frames of a set are the same whichever process renders them (GL draws in primitive order per pixel,
whatever llvmpipe's thread count).
"""
from __future__ import annotations

import logging

from .. import layout as L
from ..scene import Camera
from .ibr import IBRModel, RenderSettings, has_reflection_layer

log = logging.getLogger("ibr_pipeline.render")

# the models this process loaded for the current run, keyed by (workspace, run key, layers):
# a worker renders several sets from one load; `release_models` empties it
_models: dict = {}


def reflective_views(ws, names: list[str]) -> list[str]:
    """The views of `names` that a two-layer model renders with a reflection layer."""
    return [n for n in names if has_reflection_layer(ws, n)]


def model(ws, layers: bool, settings: RenderSettings, key: str = "",
          progress: bool = False) -> IBRModel:
    """The workspace's IBR model, loaded once per (workspace, key, layers) in this process."""
    k = (str(ws.root), key, bool(layers), settings)
    if k not in _models:
        layered = _models.get((str(ws.root), key, True, settings))
        if not layers and layered is not None:
            _models[k] = single_layer_of(ws, layered)
        else:
            _models[k] = IBRModel.load(ws, layers=layers, settings=settings, progress=progress)
    return _models[k]


def single_layer_of(ws, layered: IBRModel) -> IBRModel:
    """The single-layer model of `layered`'s workspace: views without a reflection layer are the
    same in both (`ibr.load_view` reads them alike), so only the reflective ones are loaded
    again, as mesh.ply textured with the photograph."""
    from .ibr import load_view
    scene = L.posed_scene(ws)
    s = layered.settings
    views = [v if v.layers[1] is None else
             load_view(ws, v.name, v.camera, scene.view(v.name).image, False, s,
                       scene.image_encoding) for v in layered.views]
    return IBRModel(views, s)


def release_models() -> None:
    """Free the GL objects and the data of every model `model` loaded in this process."""
    for m in _models.values():
        m.release()
    _models.clear()


def render_set(ws, cameras: list[tuple[str, Camera]], excludes: list, paths: list[str],
               layers: bool, settings: RenderSettings, encoding: str, sequential: bool,
               key: str = "", progress: str | None = None) -> list[dict]:
    """Render `cameras` (name, Camera) in order, `excludes[i]` (a view name or None) left out of
    frame i, each written to the workspace key `paths[i]` (PNG in `encoding`); `sequential`: each
    frame is the next one's `previous` (a path). Returns one record per frame: index, name, ms,
    the renderer's phase timings, the selected views and the hole fraction. `progress`: the
    label of a per-frame bar (None: no bar, as in a worker beside others)."""
    from tqdm import tqdm

    from ..io.images import write_image
    if not (len(cameras) == len(excludes) == len(paths)):
        raise ValueError(f"render_set: {len(cameras)} cameras, {len(excludes)} excludes, "
                         f"{len(paths)} paths")
    m = model(ws, layers, settings, key, progress is not None)
    frames, prev = [], None
    for i, ((name, cam), excl) in enumerate(tqdm(list(zip(cameras, excludes)), desc=progress,
                                                 unit="frame", disable=progress is None,
                                                 leave=False)):
        f = m.render(cam, exclude=() if excl is None else (excl,),
                     previous=prev if sequential else None)
        prev = f
        write_image(ws.path(paths[i]), f.color, encoding)
        frames.append({"index": i, "name": name, "ms": round(f.ms, 3),
                       **{k: round(v, 3) for k, v in f.timings.items()},
                       "selected": f.selected, "holes": round(float(1 - f.covered.mean()), 5)})
    return frames
