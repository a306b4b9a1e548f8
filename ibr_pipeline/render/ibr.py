"""The IBR renderer (Xu et al. 2021, §5.1): view selection, fuzzy depth test, two-layer blending.

    model = IBRModel.load(ws, layers=True)          # per-view two-layer meshes of a workspace
    frame = model.render(camera, exclude=(), previous=None)
    frame.color (H, W, 3) float32 linear, frame.depth (H, W) float32 z-depth (0 = hole),
    frame.selected [view names], frame.ms (wall time of this frame, selection to read-back)

Per frame and per layer (surface layer M0/I0/beta, reflection layer M1/I1) the GL passes of
`render/shaders` run over the selected views: smallest IBR cost, front-most depth among the
points within 0.17 of it, then the fuzzy-depth-tested weighted blend (Eq. 15 weights × the
texture alpha = feathering × edge decay). The two blended layers are composed with the blended
beta (Eq. 3) after small holes are filled (`blend.fill_holes`). `layers=False` is the
single-layer baseline (every view's `mesh.ply` textured with its photograph: InsideOut-like).
A view without a reflector (`layers.json` reflector null, or no reflection outputs at all) is a
single-layer view with beta = 0 inside a two-layer model.
"""
from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field, replace

import numpy as np

from .. import layout as L
from ..config import Options, param
from ..errors import InputError
from ..scene import IMAGE_ENCODINGS, Camera
from . import blend, selection

log = logging.getLogger("ibr_pipeline.render")


@dataclass(frozen=True)
class RenderSettings(Options):
    """Every constant of §5.1; the `render_views` stage embeds these as [render_views.renderer]
    (`ibr render` and `evaluate` read them from there)."""

    lam: float = param(selection.LAMBDA, "Eq. 14 λ: weight of the camera-distance term, the "
                       "baseline's parallax angle at the scene depth (ours; the paper's 0.1 "
                       "divides by the distance from the world origin)", min=0.0, max=100.0)
    scene_depth: float = param(0.0, "Eq. 14's D: the scene's median depth that the camera "
                               "distance is divided by; 0 = the workspace's (global/poses.json "
                               "median_scene_depth)", min=0.0, max=1e6)
    delta: float = param(blend.DELTA, "Eq. 15 δ: blending weight w_k = exp(-d_k/δ)",
                         min=1e-4, max=10.0)
    max_angle: float = param(selection.MAX_ANGLE_DEG, "§5.1.2 view selection: largest angle "
                             "between optical axes (degrees)", min=1.0, max=180.0)
    max_dist: float = param(selection.MAX_DIST_M, "§5.1.2 view selection: largest distance "
                            "between optical centres (m)", min=0.01, max=1000.0)
    angle_bins: int = param(selection.ANGLE_BINS, "§5.1.2: angle intervals per quadrant",
                            min=1, max=18)
    dist_bins: int = param(selection.DIST_BINS, "§5.1.2: distance intervals per quadrant",
                           min=1, max=18)
    cost_margin: float = param(blend.COST_MARGIN, "§5.1.3 fuzzy depth test: IBR-cost margin",
                               min=0.0, max=10.0)
    depth_tol: float = param(blend.DEPTH_TOL_M, "§5.1.3 fuzzy depth test: depth tolerance (m)",
                             min=1e-4, max=10.0)
    feather_px: float = param(blend.FEATHER_PX, "§5.1.4 feathering width at image borders (px)",
                              min=0.0, max=500.0)
    edge_decay_px: float = param(blend.EDGE_DECAY_PX, "§5.1.4 weight decay around depth edges "
                                 "(px)", min=0.0, max=100.0)
    fill_holes: bool = param(True, "fill holes by push-pull (§5.1.4)")
    hole_decay_px: float = param(blend.HOLE_DECAY_PX, "warped pixels within this distance of a "
                                 "hole are blended with the fill (ours; px)", min=0.0, max=100.0)
    hysteresis: bool = param(True, "§5.1.2: keep the previous frame's views along a camera path")
    max_views: int = param(0, "blend at most this many of the selected views, smallest d_k first "
                           "(ours, a speed knob); 0 = every view §5.1.2 selects", min=0, max=72)
    visibility: str = param("auto", "fuzzy = §5.1.3's fuzzy depth test across the views' meshes; "
                            "per_view = each view's mesh z-buffered on its own, then blended by "
                            "Eq. 15 (ours: robust to meshes that disagree, as multi-view stereo of "
                            "photographs does; without §5.1.4's edge decay, whose edges are the "
                            "noise of such depth); auto = fuzzy when G was fused from depth "
                            "frames, else per_view (docs/RENDERING.md)",
                            choices=("auto", "fuzzy", "per_view"))
    per_view_max: int = param(4, "per_view: blend at most this many views, smallest d_k first",
                              min=1, max=72)
    blend_space: str = param("stored", "stored = blend the views' colours (and fill holes) in the "
                             "encoding their files hold, sRGB for photographs, and decode to "
                             "linear before Eq. 3 (ours: Xu et al. do not say; as 8-bit photo "
                             "textures are sampled by default on a GPU); linear = decode every "
                             "texture first "
                             "(docs/RENDERING.md \"Blending space\")",
                             choices=("stored", "linear"))


@dataclass
class LayerData:
    """One layer of one view: a world-space mesh, its texture (H, W, 3) and texture weight (H, W);
    beta (H, W) for the surface layer (None = 0); `encoding` is the one `rgb` holds its values in
    (io.images.decode gives linear)."""

    vertices: np.ndarray
    faces: np.ndarray
    rgb: np.ndarray
    alpha: np.ndarray
    beta: np.ndarray | None = None
    encoding: str = "linear"

    def __post_init__(self) -> None:
        self.vertices = np.ascontiguousarray(self.vertices, dtype=np.float32)
        self.faces = np.ascontiguousarray(self.faces, dtype=np.int32)
        if self.vertices.ndim != 2 or self.vertices.shape[1] != 3:
            raise ValueError(f"vertices must be (V, 3), got {self.vertices.shape}")
        if self.faces.ndim != 2 or self.faces.shape[1] != 3:
            raise ValueError(f"faces must be (F, 3), got {self.faces.shape}")
        h, w = np.shape(self.alpha)[:2]
        if np.shape(self.rgb) != (h, w, 3):
            raise ValueError(f"rgb must be (H, W, 3) = {(h, w, 3)}, got {np.shape(self.rgb)}")
        if self.beta is not None and np.shape(self.beta) != (h, w):
            raise ValueError(f"beta must be (H, W) = {(h, w)}, got {np.shape(self.beta)}")
        if self.encoding not in IMAGE_ENCODINGS:
            raise ValueError(f"encoding must be one of {IMAGE_ENCODINGS}, got {self.encoding!r}")


@dataclass
class ViewData:
    name: str
    camera: Camera
    layers: tuple  # (LayerData, LayerData | None)


@dataclass
class Frame:
    color: np.ndarray            # (H, W, 3) float32, linear
    depth: np.ndarray            # (H, W) float32 z-depth of the surface layer, 0 = hole
    selected: list               # names of the selected views
    ms: float                    # wall time of the frame
    camera: Camera | None = None
    covered: np.ndarray | None = None   # (H, W) bool: some selected view covered the pixel
    beta: np.ndarray | None = None      # (H, W) blended beta
    timings: dict = field(default_factory=dict)


def _pad_rgba(rgb: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    return np.concatenate([np.asarray(rgb, np.float32), np.asarray(alpha, np.float32)[..., None]], 2)


class IBRModel:
    """Per-view layered meshes + the GL renderer. GL objects are created lazily per view."""

    def __init__(self, views: list[ViewData], settings: RenderSettings | None = None):
        if not views:
            raise ValueError("IBR model: no views to render from")
        self.views = list(views)
        self.settings = settings or RenderSettings()
        self.names = [v.name for v in self.views]
        self._index = {n: i for i, n in enumerate(self.names)}
        self.centers = np.array([v.camera.center for v in self.views])
        self.axes = np.array([v.camera.viewing_direction for v in self.views])
        self.has_layer1 = any(v.layers[1] is not None for v in self.views)
        # Eq. 14's D: the workspace's (resolve_settings), else the median depth of the views' own
        # surface meshes (a model built from views, not loaded from a workspace)
        self.scene_depth = self.settings.scene_depth or median_depth(
            (v.camera, v.layers[0].vertices) for v in self.views)
        encodings = {lay.encoding for v in self.views for lay in v.layers if lay is not None}
        if len(encodings) != 1:
            raise ValueError(f"IBR model: the layers' textures mix encodings {sorted(encodings)}")
        # blended (and hole-filled) in this encoding, decoded to linear before Eq. 3
        self.texture_encoding = encodings.pop()
        self._gpu: dict = {}
        self._targets: dict = {}
        self._progs = None

    # --- loading ------------------------------------------------------------------------------
    @classmethod
    def load(cls, ws, layers: bool = True, settings: RenderSettings | None = None,
             progress: bool = False) -> "IBRModel":
        """The per-view meshes of workspace `ws` (after view_mesh; two layers after reflection)."""
        from tqdm import tqdm

        cams = L.registered_cameras(ws)
        scene = L.posed_scene(ws)
        s = settings or RenderSettings()
        views = []
        names = [n for n in scene.names if n in cams]
        if not names:
            raise InputError(f"{ws.path(L.REGISTERED_CAMERAS)}: no registered view to render from")
        s = resolve_settings(ws, s)
        for name in tqdm(names, desc="loading views", unit="view", disable=not progress, leave=False):
            views.append(load_view(ws, name, cams[name], scene.view(name).image, layers, s,
                                   scene.image_encoding))
        return cls(views, s)

    # --- view selection (§5.1.1–5.1.2) -----------------------------------------------------------
    def select(self, camera: Camera, exclude=(), previous: "Frame | None" = None):
        prev = None
        if self.settings.hysteresis and previous is not None and previous.camera is not None:
            prev = (previous.camera.R, previous.camera.center,
                    [self._index[n] for n in previous.selected if n in self._index])
        return select(self.axes, self.centers, self.names, self.settings, self.scene_depth,
                      camera, exclude, prev)

    # --- GL resources -------------------------------------------------------------------------
    def _programs(self):
        if self._progs is None:
            from . import gl, shaders
            ctx = gl.get_context()
            self._progs = {k: ctx.program(vertex_shader=shaders.VERTEX, fragment_shader=src)
                           for k, src in (("cost", shaders.COST), ("front", shaders.FRONT),
                                          ("blend", shaders.BLEND), ("single", shaders.SINGLE))}
        return self._progs

    def _view_gpu(self, k: int, layer: int):
        key = (k, layer)
        if key not in self._gpu:
            from . import gl
            ctx = gl.get_context()
            L = self.views[k].layers[layer]
            vbo = ctx.buffer(L.vertices.tobytes())
            ibo = ctx.buffer(L.faces.tobytes())
            vaos = {name: ctx.vertex_array(p, [(vbo, "3f", "in_pos")], ibo, index_element_size=4)
                    for name, p in self._programs().items()}
            beta = L.beta if L.beta is not None else np.zeros(L.alpha.shape, np.float32)
            self._gpu[key] = {"vaos": vaos, "rgba": gl.upload_texture(_pad_rgba(L.rgb, L.alpha)),
                              "beta": gl.upload_texture(beta), "objs": (vbo, ibo),
                              "has_beta": bool(layer == 0 and np.any(beta > 0))}
        return self._gpu[key]

    def _target(self, size):
        if size not in self._targets:
            from . import gl
            ctx = gl.get_context()
            t = {"cost": gl.float_target(size, 1), "front": gl.float_target(size, 1),
                 "acc": gl.float_target(size, 4), "beta": gl.float_target(size, 1)}
            t["fbo_cost"] = ctx.framebuffer([t["cost"]])
            t["fbo_front"] = ctx.framebuffer([t["front"]])
            t["fbo_blend"] = ctx.framebuffer([t["acc"], t["beta"]])
            self._targets[size] = t
        return self._targets[size]

    @staticmethod
    def _set(prog, **values):
        for k, v in values.items():
            if k in prog:
                if isinstance(v, bytes):
                    prog[k].write(v)
                else:
                    prog[k].value = v

    def _common_uniforms(self, camera: Camera):
        from . import gl
        return {"P_n": gl.mat_bytes(gl.projection(camera)),
                "V_n": gl.mat_bytes(camera.cam_from_world),
                "t_n": tuple(float(c) for c in camera.center)}

    def _view_uniforms(self, k: int):
        from . import gl
        cam = self.views[k].camera
        return {"S_k": gl.mat_bytes(gl.source_matrix(cam)),
                "t_k": tuple(float(c) for c in cam.center),
                "src_size": (float(cam.width), float(cam.height))}

    def _render_layer(self, camera: Camera, layer: int, items: list[tuple[int, float]],
                      box: tuple[int, int, int, int] | None = None):
        """The three GL passes for one layer, inside `box` (x, y, w, h; default: everything).
        Returns acc (h,w,4) = Σ w·(rgb, 1), beta_acc (h,w) = Σ w·beta, front (h,w) depth."""
        import moderngl

        from . import gl
        ctx = gl.get_context()
        s = self.settings
        size = camera.size
        t = self._target(size)
        progs = self._programs()
        common = self._common_uniforms(camera)
        box = box or (0, 0, size[0], size[1])
        for name in ("fbo_cost", "fbo_front", "fbo_blend"):
            t[name].scissor = box
        ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE)
        ctx.enable(moderngl.BLEND)
        ctx.blend_func = moderngl.ONE, moderngl.ONE
        # pass 1: smallest IBR cost per pixel (§5.1.3)
        ctx.blend_equation = moderngl.MIN
        t["fbo_cost"].use()
        t["fbo_cost"].clear(1e30, 1e30, 1e30, 1e30, viewport=box)
        for k, _ in items:
            g = self._view_gpu(k, layer)
            self._set(progs["cost"], **common, **self._view_uniforms(k))
            g["vaos"]["cost"].render(moderngl.TRIANGLES)
        # pass 2: front-most depth among points within cost_margin of the smallest cost
        t["fbo_front"].use()
        t["fbo_front"].clear(1e30, 1e30, 1e30, 1e30, viewport=box)
        t["cost"].use(location=0)
        for k, _ in items:
            g = self._view_gpu(k, layer)
            self._set(progs["front"], **common, **self._view_uniforms(k), cost_min=0,
                      cost_margin=float(s.cost_margin))
            g["vaos"]["front"].render(moderngl.TRIANGLES)
        # pass 3: fuzzy depth test + weighted blend (Eq. 15 × texture alpha)
        ctx.blend_equation = moderngl.FUNC_ADD
        t["fbo_blend"].use()
        t["fbo_blend"].clear(0.0, 0.0, 0.0, 0.0, viewport=box)
        t["front"].use(location=0)
        for k, w in items:
            g = self._view_gpu(k, layer)
            g["rgba"].use(location=1)
            g["beta"].use(location=2)
            self._set(progs["blend"], **common, **self._view_uniforms(k), front=0, tex_rgba=1,
                      tex_beta=2, depth_tol=float(s.depth_tol), w_k=float(w),
                      has_beta=g["has_beta"])
            g["vaos"]["blend"].render(moderngl.TRIANGLES)
        ctx.disable(moderngl.BLEND)
        acc = gl.read_float(t["fbo_blend"], 0, box, 4)
        bacc = gl.read_float(t["fbo_blend"], 1, box, 1)[..., 0] if layer == 0 else None
        front = gl.read_float(t["fbo_front"], 0, box, 1)[..., 0]
        return acc, bacc, front

    def _render_layer_per_view(self, camera: Camera, layer: int, items: list[tuple[int, float]],
                               box: tuple[int, int, int, int] | None = None):
        """`_render_layer` with each view's mesh z-buffered alone (render_single_view) and the
        views blended by w_k x texture alpha: no view's surface hides another's. Same returns."""
        x, y, bw, bh = box or (0, 0, *camera.size)
        acc = np.zeros((bh, bw, 4), np.float32)
        bacc = np.zeros((bh, bw), np.float32)
        front = np.full((bh, bw), 1e30, np.float32)
        for k, wk in items:
            r = self.render_single_view(camera, k, layer)
            cov = r["covered"][y:y + bh, x:x + bw]
            wgt = np.where(cov, wk * r["alpha"][y:y + bh, x:x + bw], 0.0).astype(np.float32)
            acc[..., :3] += wgt[..., None] * r["rgb"][y:y + bh, x:x + bw]
            acc[..., 3] += wgt
            bacc += wgt * r["beta"][y:y + bh, x:x + bw]
            front = np.where(cov, np.minimum(front, r["z"][y:y + bh, x:x + bw]), front)
        return acc, (bacc if layer == 0 else None), front

    # --- rendering ------------------------------------------------------------------------------
    def render(self, camera: Camera, exclude=(), previous: "Frame | None" = None,
               layers: bool = True) -> Frame:
        """Render `camera`: select views, blend both layers, fill holes, compose (Eq. 3)."""
        from . import post_nb  # numba pulls in scipy; `ibr --help` must stay light
        t0 = time.perf_counter()
        s = self.settings
        sel, d = self.select(camera, exclude, previous)
        if s.visibility == "per_view":
            sel = sel[:s.per_view_max]
        w = blend.view_weights(d[sel], s.delta)
        t1 = time.perf_counter()
        items0 = [(k, float(wk)) for k, wk in zip(sel, w)]
        layer_fn = self._render_layer_per_view if s.visibility == "per_view" else self._render_layer
        acc, bacc, front = layer_fn(camera, 0, items0)
        # normalised blend of (I0 rgb, beta), 0 where uncovered; box of the blended beta > 0
        color4, covered, depth, box = post_nb.normalise(acc, bacc, front)
        items1 = [(k, wk) for k, wk in items0 if layers and self.views[k].layers[1] is not None]
        box = box if items1 else None
        if box is not None:  # reflection layer only where the blended beta is > 0
            acc1, _, _ = layer_fn(camera, 1, items1, box)
            cov1 = acc1[..., 3] > 0
            i1 = acc1[..., :3] / np.where(cov1, acc1[..., 3], 1.0)[..., None]
        t2 = time.perf_counter()
        if s.fill_holes:
            color4 = post_nb.fill_holes(color4, covered, s.hole_decay_px)
        i1_box = None
        if box is not None:  # Eq. 3 inside the box (the frame when I1 is filled); I1 is 0 outside
            x, y, bw, bh = box
            H, W = covered.shape
            refl = color4[..., 3] > 1e-4  # after the fill, beta reaches into holes beyond the box
            inside = refl[y:y + bh, x:x + bw]
            if s.fill_holes and ((inside & ~cov1).any() or refl.sum() > inside.sum()):
                # I1 push-pull filled over the whole frame (uncovered outside the box) and
                # composed wherever the filled beta is, so that holes next to a reflector keep
                # its reflection: the box alone leaves them dark (docs/BENCHMARKS.md, session 28)
                full, cov_full = np.zeros((H, W, 3), np.float32), np.zeros((H, W), bool)
                full[y:y + bh, x:x + bw], cov_full[y:y + bh, x:x + bw] = i1, cov1
                i1, box = post_nb.fill_holes(full, cov_full, s.hole_decay_px), (0, 0, W, H)
            i1_box = i1
        color, beta = post_nb.finish(color4, i1_box, box, srgb=self.texture_encoding == "srgb")
        t3 = time.perf_counter()
        return Frame(color, depth,
                     [self.names[k] for k in sel], (t3 - t0) * 1e3, camera, covered, beta,
                     {"select_ms": (t1 - t0) * 1e3, "gl_ms": (t2 - t1) * 1e3,
                      "post_ms": (t3 - t2) * 1e3})

    def render_single_view(self, camera: Camera, k: int, layer: int = 0) -> dict:
        """Reference pass: view k alone with an ordinary depth test. Returns rgb (in the textures'
        encoding), alpha, z, cost, beta (H, W[, 3]) and covered (H, W) — the inputs of the numpy
        blend in `blend.py`."""
        import moderngl

        from . import gl
        ctx = gl.get_context()
        size = camera.size
        a, b = gl.float_target(size, 4), gl.float_target(size, 4)
        depth = ctx.depth_renderbuffer(size)
        fbo = ctx.framebuffer([a, b], depth)
        try:
            fbo.use()
            fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
            ctx.disable(moderngl.BLEND | moderngl.CULL_FACE)
            ctx.enable(moderngl.DEPTH_TEST)
            g = self._view_gpu(k, layer)
            g["rgba"].use(location=1)
            g["beta"].use(location=2)
            self._set(self._programs()["single"], **self._common_uniforms(camera),
                      **self._view_uniforms(k), tex_rgba=1, tex_beta=2)
            g["vaos"]["single"].render(moderngl.TRIANGLES)
            ctx.disable(moderngl.DEPTH_TEST)
            rgba = gl.read_float(fbo, 0, size, 4)
            geo = gl.read_float(fbo, 1, size, 4)
        finally:
            for o in (fbo, depth, a, b):
                o.release()
        cov = geo[..., 3] > 0
        return {"rgb": rgba[..., :3], "alpha": rgba[..., 3], "z": np.where(cov, geo[..., 0], 0),
                "cost": geo[..., 1], "beta": geo[..., 2], "covered": cov}

    def release(self) -> None:
        """Free the GL objects of this model (the context itself stays for the process)."""
        for g in self._gpu.values():
            for v in g["vaos"].values():
                v.release()
            for o in (*g["objs"], g["rgba"], g["beta"]):
                o.release()
        for t in self._targets.values():
            for o in t.values():
                o.release()
        if self._progs:
            for p in self._progs.values():
                p.release()
        self._gpu, self._targets, self._progs = {}, {}, None

    def with_settings(self, **changes) -> "IBRModel":
        return IBRModel(self.views, replace(self.settings, **changes))


def stored_settings(ws) -> RenderSettings:
    """The RenderSettings `render_views` rendered with (renders/settings.json), or the defaults
    before it ran; a malformed file, an unknown field or a value out of range names the file."""
    from ..errors import ConfigError
    p = ws.path(L.RENDER_SETTINGS)
    if not p.is_file():
        return RenderSettings()
    try:
        s = replace(RenderSettings(), **json.loads(p.read_text()))
        s.validate("render_views.renderer")
    except (json.JSONDecodeError, TypeError, ConfigError) as e:
        raise InputError(f"{p}: not render settings ({e}); rerun `ibr render_views`") from None
    return s


def median_depth(seen) -> float:
    """Eq. 14's D from (camera, world points) pairs: the median over the cameras of the median
    z-depth of the points inside each one's frame; 1 when there are none."""
    z = []
    for camera, pts in seen:
        if not len(pts):
            continue
        uv, d = camera.project(np.asarray(pts, np.float64))
        inside = (d > 0) & np.all((uv >= -0.5) & (uv <= [camera.width - 0.5,
                                                          camera.height - 0.5]), axis=1)
        if inside.any():
            z.append(float(np.median(d[inside])))
    return float(np.median(z)) if z else 1.0


def resolve_settings(ws, s: RenderSettings) -> RenderSettings:
    """`s` with what "auto" and 0 leave to the workspace filled in: visibility, scene_depth."""
    if s.visibility == "auto":
        s = replace(s, visibility=auto_visibility(ws))
    if not s.scene_depth:
        s = replace(s, scene_depth=workspace_scene_depth(ws))
    return s


def workspace_scene_depth(ws) -> float:
    """The median scene depth the poses stage measured (global/poses.json); where it measured
    none (no scene points), that of the global mesh's vertices in the registered cameras."""
    d = L.poses_report(ws).get("median_scene_depth")
    if d is not None and not (isinstance(d, (int, float)) and d > 0):
        raise InputError(f"{ws.path(L.POSES_REPORT)}: median_scene_depth {d!r} is not a positive "
                         "length (rerun `ibr poses`)")
    if d:
        return float(d)
    from ..io.mesh import read_ply
    mesh = ws.path(L.GLOBAL_MESH)
    pts = read_ply(mesh).vertices if mesh.is_file() else np.zeros((0, 3))
    return median_depth((c, pts) for c in L.registered_cameras(ws).values())


def auto_visibility(ws) -> str:
    """`visibility = auto`: the fuzzy depth test where G was fused from depth frames (geometry
    accurate to its tolerance), per-view z-buffering where it came from multi-view stereo."""
    import json
    p = ws.path(L.GLOBAL_REPORT)
    try:
        dense = json.loads(p.read_text()).get("dense") if p.is_file() else None
    except (OSError, json.JSONDecodeError):
        raise InputError(f"{p}: malformed JSON") from None
    return "fuzzy" if dense in (None, "rgbd") else "per_view"


def select(axes: np.ndarray, centers: np.ndarray, names: list[str], s: RenderSettings,
           scene_depth: float, camera: Camera, exclude=(), previous=None):
    """§5.1.1-5.1.2 over views with optical axes `axes` and centres `centers` (K, 3): the
    selected indices (sorted by d_k) and every view's d_k (Eq. 14); `previous` is
    select_views'."""
    d = selection.view_distance(axes, centers, camera.viewing_direction, camera.center, s.lam,
                                scene_depth)
    skip = set(exclude)
    avail = np.array([n not in skip for n in names])
    if not avail.any():
        raise ValueError("IBR model: every view is excluded")
    sel = selection.select_views(camera.R, camera.center, axes, centers, d, avail, previous,
                                 s.max_angle, s.max_dist, s.angle_bins, s.dist_bins)
    if s.max_views > 0:
        sel = sel[:s.max_views]  # select_views sorts by d_k: keep the closest
    return sel, d


def views_needed(cameras: dict[str, Camera], s: RenderSettings, frames) -> list[str]:
    """The views (of `cameras`, in their order) that a model of all of them selects for
    `frames`, [(camera, exclude)] rendered without a previous frame. A model of only these views
    selects the same ones: each sub-region's smallest d_k is among them, and the fallback's
    nearest views too (selection.select_views); `s.scene_depth` must be resolved."""
    if not s.scene_depth:
        raise ValueError("views_needed: settings.scene_depth must be resolved (Eq. 14's D)")
    names = list(cameras)
    axes = np.array([cameras[n].viewing_direction for n in names])
    centers = np.array([cameras[n].center for n in names])
    used: set[int] = set()
    for cam, exclude in frames:
        used.update(select(axes, centers, names, s, s.scene_depth, cam, exclude)[0])
    return [names[k] for k in sorted(used)]


# --- loading one view from a workspace -----------------------------------------------------------
def _edges(path) -> np.ndarray:
    from ..io.images import read_image
    return read_image(path)[..., 0] > 0.5


def mask_boundary(mask: np.ndarray) -> np.ndarray:
    """Pixels of `mask` next to a pixel outside it (4-neighbourhood) and image-border pixels."""
    m = np.asarray(mask, bool)
    p = np.pad(m, 1, constant_values=False)
    inner = p[:-2, 1:-1] & p[2:, 1:-1] & p[1:-1, :-2] & p[1:-1, 2:]
    return m & ~inner


def has_reflection_layer(ws, name: str) -> bool:
    """Whether view `name`'s `layers.json` (written by `reflection`) names a reflector: then a
    two-layer model renders it with a reflection layer (M1/I1); absent file: no."""
    lj = ws.path(f"{ws.view_dir(name)}/{L.LAYERS}")
    if not lj.is_file():
        return False
    try:
        info = json.loads(lj.read_text())
    except json.JSONDecodeError as e:
        raise InputError(f"{lj}: malformed JSON ({e})") from None
    if not isinstance(info, dict):
        raise InputError(f"{lj}: expected a JSON object (rerun `ibr reflection --force`)")
    return info.get("reflector") is not None


def load_view(ws, name: str, camera: Camera, image_key: str, layers: bool,
              s: RenderSettings, encoding: str = "linear") -> ViewData:
    """One view's LayerData from the files of docs/PIPELINE.md (view_mesh + reflection); colour
    files stored in `encoding` (the scene's) keep it with `s.blend_space` stored and are decoded
    to linear with `linear`."""
    from ..io.images import read_image
    from ..io.mesh import read_ply

    vdir = ws.view_dir(name)
    H, W = camera.height, camera.width

    stored = s.blend_space == "stored"
    tex_encoding = encoding if stored else "linear"

    def img(key):
        a = read_image(ws.path(key), "linear" if stored else encoding)  # "linear": as stored
        if a.shape[:2] != (H, W):
            raise InputError(f"{ws.path(key)}: image is {a.shape[1]}x{a.shape[0]}, camera says {W}x{H}")
        return a

    edges = _edges(ws.path(f"{vdir}/{L.EDGES}"))
    if edges.shape != (H, W):
        raise InputError(f"{ws.path(f'{vdir}/{L.EDGES}')}: size {edges.shape[::-1]} is not {W}x{H}")
    decay = 0.0 if s.visibility == "per_view" else s.edge_decay_px  # see RenderSettings.visibility
    alpha0 = blend.texture_alpha(edges, s.feather_px, decay)
    if layers and has_reflection_layer(ws, name):
        m0, m1 = read_ply(ws.path(f"{vdir}/{L.M0}")), read_ply(ws.path(f"{vdir}/{L.M1}"))
        bpath = ws.path(f"{vdir}/{L.BETA}")
        try:
            beta = np.load(bpath).astype(np.float32)
        except (OSError, ValueError) as e:
            raise InputError(f"{bpath}: cannot read ({e})") from None
        if beta.shape != (H, W) or not np.all(np.isfinite(beta)):
            raise InputError(f"{bpath}: beta must be finite with shape {(H, W)}, got {beta.shape}")
        beta = np.clip(beta, 0.0, 1.0)
        l0 = LayerData(m0.vertices, m0.faces, img(f"{vdir}/{L.I0}"), alpha0, beta, tex_encoding)
        # the reflection layer always decays at the border of its beta > 0 region
        e1 = mask_boundary(beta > 0) | (edges if decay else np.zeros_like(edges))
        alpha1 = blend.texture_alpha(e1, s.feather_px, s.edge_decay_px)
        l1 = LayerData(m1.vertices, m1.faces, img(f"{vdir}/{L.I1}"), alpha1, encoding=tex_encoding)
        return ViewData(name, camera, (l0, l1))
    m = read_ply(ws.path(f"{vdir}/{L.MESH}"))
    return ViewData(name, camera, (LayerData(m.vertices, m.faces, img(image_key), alpha0,
                                             encoding=tex_encoding), None))
