"""The web bundle of a workspace: what the browser viewer (`ibr view`, viewer/static) loads.

`write_bundle(ws, out)` writes into `out` (default WS/export/web):

* `manifest.json`: the renderer's settings (RenderSettings as `render_views` resolved them, with
  `visibility` auto already decided), the scene's colour encoding, the GLSL of `render/shaders`
  rewritten for WebGL2 (GLSL ES 3.00), every registered camera (K, cam_from_world, size), the
  held-out and fly-through cameras of `render_views`, and per view its layers;
* per view and layer, `<key>.<layer>.pos.bin` (float32 x, y, z per vertex, little-endian) and
  `.idx.bin` (uint32 triangle indices): the world-space meshes the offline renderer draws;
* per view and layer, `<key>.<layer>.rgb.png` (the layer image, 8-bit, in the scene's encoding;
  the page blends it as the offline renderer does, `RenderSettings.blend_space`: sRGB values
  as stored, decoded before Eq. 3, or uploaded as SRGB8_ALPHA8 so that the GPU decodes them
  first) and `<key>.<layer>.aux.png` (R = sqrt of the texture
  alpha = feathering x edge decay of §5.1.4, G = beta of Eq. 3, 8-bit each; the square root keeps
  the 1e-3 weight floor above zero at 8 bits).

The layers are the offline renderer's own (`render.ibr.load_view`): the viewer blends exactly the
meshes, textures and weights that `render_views` blends. Layer names: `single` (mesh.ply + photo,
the single-layer baseline), `surface` (M0 + I0 + beta) and `reflection` (M1 + I1); a view without
a reflector has `surface` = its `single` files and no `reflection`.

PNG rather than KTX2/Basis or lossy WebP: lossless (the browser-vs-offline check compares the same
texels), written by OpenCV in milliseconds, decoded natively by every browser with no transcoder.
Everything is staged in a sibling folder and moved into place when all of it was written, so a
failed export leaves the previous bundle as it was. `bundle_is_current` says whether the bundle is
newer than every file it was made from (`ibr view` rebuilds it otherwise).
"""
from __future__ import annotations

import json
import os
import re
import shutil
import tempfile
from dataclasses import asdict
from pathlib import Path

import numpy as np

from .. import layout as L
from ..errors import InputError

FORMAT = "ibr-web-bundle"
VERSION = 1
MANIFEST = "manifest.json"


def webgl_shader(src: str) -> str:
    """A GLSL 330 shader of render/shaders as GLSL ES 3.00 (WebGL2): the same code with an ES
    header (float samplers at highp, so that float render targets are read at full precision) and
    the bundle's two 8-bit textures per layer in place of the offline float16 RGBA + beta pair:
    `texture(tex_rgba, uv)` becomes ibr_rgba(uv) = (rgb, aux.r^2), `texture(tex_beta, uv).r`
    becomes aux.g."""
    if not src.lstrip().startswith("#version 330"):
        raise ValueError("expected a '#version 330' shader")
    header = ("#version 300 es\nprecision highp float;\nprecision highp int;\n"
              "precision highp sampler2D;")
    out = re.sub(r"#version 330[^\n]*", header, src.lstrip(), count=1)
    if "tex_rgba" in out:
        if "texture(tex_rgba, uv)" not in out:
            raise ValueError("shader samples tex_rgba in a way webgl_shader does not rewrite")
        out = (out.replace("texture(tex_rgba, uv)", "ibr_rgba(uv)")
                  .replace("texture(tex_beta, uv).r", "texture(tex_aux, uv).g"))
        helper = ("uniform sampler2D tex_aux;  // R = sqrt(texture alpha), G = beta\n"
                  "vec4 ibr_rgba(vec2 uv) {\n"
                  "    float s = texture(tex_aux, uv).r;\n"
                  "    return vec4(texture(tex_rgba, uv).rgb, s * s);\n}\n")
        i = out.rindex("void main()")
        out = out[:i] + helper + out[i:]
    return out


def webgl_shaders() -> dict[str, str]:
    from ..render import shaders
    names = ("VERTEX", "COST", "FRONT", "BLEND", "SINGLE")
    return {k: webgl_shader(getattr(shaders, k)) for k in names}


def _camera_json(name: str, cam) -> dict:
    return {"name": name, "K": np.asarray(cam.K).tolist(),
            "cam_from_world": np.asarray(cam.cam_from_world)[:3].tolist(),
            "width": int(cam.width), "height": int(cam.height),
            "center": np.asarray(cam.center).tolist(),
            "axis": np.asarray(cam.viewing_direction).tolist()}


def _png(path: Path, img: np.ndarray) -> None:
    import cv2
    a = np.clip(np.rint(np.asarray(img, np.float32) * 255.0), 0, 255).astype(np.uint8)
    if not cv2.imwrite(str(path), a[..., ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 1]):
        raise OSError(f"{path}: cannot write PNG")


def _encode(data, encoding: str) -> np.ndarray:
    """The layer's texture in `encoding` (LayerData.rgb holds it in data.encoding)."""
    from ..io.images import linear_to_srgb
    if data.encoding == encoding:
        return data.rgb
    return linear_to_srgb(data.rgb) if encoding == "srgb" else data.rgb


def _write_layer(stage: Path, key: str, layer_name: str, data) -> dict:
    base = f"{key}.{layer_name}"
    (stage / f"{base}.pos.bin").write_bytes(np.ascontiguousarray(data.vertices, "<f4").tobytes())
    (stage / f"{base}.idx.bin").write_bytes(np.ascontiguousarray(data.faces, "<u4").tobytes())
    return {"pos": f"{base}.pos.bin", "idx": f"{base}.idx.bin",
            "vertices": int(len(data.vertices)), "triangles": int(len(data.faces)),
            "has_beta": bool(data.beta is not None and np.any(data.beta > 0))}


def _write_textures(stage: Path, key: str, layer_name: str, data, encoding: str) -> dict:
    base = f"{key}.{layer_name}"
    _png(stage / f"{base}.rgb.png", _encode(data, encoding))
    beta = data.beta if data.beta is not None else np.zeros(data.alpha.shape, np.float32)
    aux = np.stack([np.sqrt(np.clip(data.alpha, 0, 1)), beta, np.zeros_like(beta)], -1)
    _png(stage / f"{base}.aux.png", aux)
    return {"rgb": f"{base}.rgb.png", "aux": f"{base}.aux.png"}


def _sources(ws) -> list[Path]:
    """Every file the bundle is made from (for `bundle_is_current`)."""
    files = [ws.path(L.REGISTERED_CAMERAS), ws.path(ws.SCENE), ws.root / "ibr.toml",
             ws.path(L.RENDER_SETTINGS)]
    scene = L.posed_scene(ws)
    for name in L.registered_cameras(ws):
        files.append(ws.path(scene.view(name).image))
        files += [ws.path(k) for k in L.renderer_files(ws, name)]
    return [f for f in files if f.is_file()]


def bundle_is_current(ws, out: Path) -> bool:
    m = Path(out) / MANIFEST
    if not m.is_file():
        return False
    try:
        if json.loads(m.read_text()).get("version") != VERSION:
            return False
    except (OSError, json.JSONDecodeError):
        return False
    t = m.stat().st_mtime
    return all(f.stat().st_mtime <= t for f in _sources(ws))


def _render_views_config(ws):
    from ..config import build_config
    from ..stages import render_views as rv
    return build_config(rv.RenderViewsConfig, "render_views", ws.config().get("render_views", {}))


def render_settings(ws):
    """The RenderSettings `render_views` rendered with (renders/settings.json: `ibr run --set`
    overrides included), else the ones it would use from ibr.toml; visibility resolved."""
    from ..render.ibr import resolve_settings, stored_settings
    if ws.path(L.RENDER_SETTINGS).is_file():
        return resolve_settings(ws, stored_settings(ws))
    return resolve_settings(ws, _render_views_config(ws).renderer)


def _extra_cameras(ws) -> dict[str, list]:
    """The held-out and fly-through cameras of `render_views` (as `ibr render` renders them)."""
    from ..runner import StageContext
    from ..stages import render_views as rv
    sets = rv.render_sets(StageContext(ws, "render_views", _render_views_config(ws),
                                       L.posed_scene(ws)))
    out = {}
    if "test" in sets and sets["test"]["source"] != "leave_one_out":
        out["heldout"] = [_camera_json(n, c) for n, c in sets["test"]["cameras"]]
    if "fly" in sets:
        out["fly"] = [_camera_json(n, c) for n, c in sets["fly"]["cameras"]]
    return out


def write_bundle(ws, out: Path | None = None, progress: bool = True) -> Path:
    """Write the web bundle of workspace `ws` into `out` (module docstring); returns `out`."""
    from tqdm import tqdm

    from ..render import blend, gl, selection
    from ..render.ibr import load_view

    out = Path(out) if out is not None else ws.path("export/web")
    if not ws.path(L.REGISTERED_CAMERAS).is_file():
        raise InputError(f"{ws.path(L.REGISTERED_CAMERAS)}: missing: no registered cameras yet "
                         f"(run `ibr run {ws.root}`)")
    cams = L.registered_cameras(ws)
    scene = L.posed_scene(ws)
    names = [n for n in scene.names if n in cams]
    for n in names:
        mesh = ws.path(L.view_file(n, L.MESH))
        if not mesh.is_file():
            raise InputError(f"{mesh}: missing: the view has no mesh "
                             f"(run `ibr view_mesh {ws.root}`)")
    s = render_settings(ws)
    enc = scene.image_encoding
    out.parent.mkdir(parents=True, exist_ok=True)
    for left in out.parent.glob(f".{out.name}-*"):  # staging of a run that was killed
        shutil.rmtree(left, ignore_errors=True)
    stage = Path(tempfile.mkdtemp(prefix=f".{out.name}-", dir=out.parent))
    try:
        views = []
        for i, name in enumerate(tqdm(names, desc="web bundle", unit="view", disable=not progress,
                                      leave=False)):
            key = f"v{i:04d}"
            image = scene.view(name).image
            single = load_view(ws, name, cams[name], image, False, s, enc).layers[0]
            two = load_view(ws, name, cams[name], image, True, s, enc).layers
            layers = {"single": {**_write_layer(stage, key, "single", single),
                                 **_write_textures(stage, key, "single", single, enc)}}
            if two[1] is None:
                layers["surface"] = layers["single"]
            else:
                for lname, data in (("surface", two[0]), ("reflection", two[1])):
                    layers[lname] = {**_write_layer(stage, key, lname, data),
                                     **_write_textures(stage, key, lname, data, enc)}
            views.append({**_camera_json(name, cams[name]), "key": key, "layers": layers})
        manifest = {"format": FORMAT, "version": VERSION, "workspace": ws.root.name,
                    "encoding": enc, "settings": asdict(s), "shaders": webgl_shaders(),
                    "near": gl.NEAR_M, "far": gl.FAR_M,
                    "selection": {"fallback": selection.FALLBACK_VIEWS,
                                  "view_weight_floor": blend.VIEW_WEIGHT_FLOOR},
                    "views": views, **_extra_cameras(ws)}
        (stage / MANIFEST).write_text(json.dumps(manifest))
        old = None
        if out.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{out.name}-old-", dir=out.parent))
            os.replace(out, old / out.name)
        os.replace(stage, out)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    finally:
        if stage.exists():
            shutil.rmtree(stage, ignore_errors=True)
    return out
