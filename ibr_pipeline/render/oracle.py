"""The oracle representation: per-view two-layer meshes built from a synthetic scene's ground truth.

Used by `evaluate` as the ceiling our reconstruction stages chase (the same renderer on GT depth
and GT layers), and by gt_workspace.py, which writes those meshes as a workspace's files.

Per capture view (docs/SYNTHETIC.md): M0 = grid mesh of gt/geom depth cut at depth jumps; I0, I1,
beta = gt/I0, gt/I1, gt/beta; M1 = the reflection layer's mirror-world geometry: for every pixel
with beta > 0 the reflector whose plane passes through its GT point is found, and the camera ray is
cast against the GT mesh mirrored through that plane (only the part in front of the plane), which
gives the virtual point the reflection is seen at. Behind glass (a reflector of material "glass")
M0 takes the depth of what the pane transmits, the camera ray cast on through it into the GT
mesh, as the pipeline's glass model does (docs/REFLECTION.md "Glass"), so that the oracle stays
the ceiling of that model and not of a pane painted with the room behind it.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..cache import ProcessCache, file_key
from ..errors import InputError
from ..scene import Camera, cameras_from_json, read_reflectors
from . import blend
from .ibr import LayerData, RenderSettings, ViewData, mask_boundary

DEPTH_JUMP = 0.05  # relative depth jump that cuts the grid mesh and marks a depth edge
GRID_STEP = 2      # grid mesh: one vertex every 2 pixels
SIMPLIFY = 0.9     # then 90 % of the triangles removed by quadric decimation


def depth_edges(depth: np.ndarray, jump: float = DEPTH_JUMP) -> np.ndarray:
    """(H, W) bool: pixels with a 4-neighbour whose depth differs by more than `jump` (relative),
    or that border a pixel without depth."""
    d = np.asarray(depth, dtype=np.float64)
    if d.ndim != 2:
        raise ValueError(f"depth must be (H, W), got {d.shape}")
    e = np.zeros(d.shape, bool)
    for a, b in (((slice(None), slice(1, None)), (slice(None), slice(None, -1))),
                 ((slice(1, None), slice(None)), (slice(None, -1), slice(None)))):
        x, y = d[a], d[b]
        valid = (x > 0) & (y > 0)
        jumpy = ~valid & ((x > 0) | (y > 0)) | valid & (np.maximum(x, y) > (1 + jump) * np.minimum(x, y))
        e[a] |= jumpy
        e[b] |= jumpy
    return e & (d > 0)


def grid_mesh(camera: Camera, depth: np.ndarray, step: int = 1,
              jump: float = DEPTH_JUMP) -> tuple[np.ndarray, np.ndarray]:
    """World-space triangle mesh of a z-depth map (0 = no depth): one vertex per `step`-th pixel
    centre, two triangles per grid cell, a triangle dropped when its corners' depths differ by more
    than `jump` (relative): the mesh is cut at depth discontinuities."""
    d = np.asarray(depth, dtype=np.float64)
    if d.shape != (camera.height, camera.width):
        raise ValueError(f"depth {d.shape} does not match camera {camera.width}x{camera.height}")
    ys = np.unique(np.r_[np.arange(0, camera.height, step), camera.height - 1])
    xs = np.unique(np.r_[np.arange(0, camera.width, step), camera.width - 1])
    sub = d[np.ix_(ys, xs)]
    uu, vv = np.meshgrid(xs, ys)
    verts = camera.unproject(np.c_[uu.ravel(), vv.ravel()], sub.ravel())
    idx = np.arange(sub.size).reshape(sub.shape)
    a, b, c, e = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    tris = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, e], -1).reshape(-1, 3)])
    z = sub.ravel()[tris]
    ok = (z.min(1) > 0) & (z.max(1) <= (1 + jump) * z.min(1))
    return verts.astype(np.float32), tris[ok].astype(np.int32)


def simplified_grid_mesh(camera: Camera, depth: np.ndarray, step: int = 2,
                         reduction: float = SIMPLIFY) -> tuple[np.ndarray, np.ndarray]:
    """`grid_mesh` reduced by quadric decimation (fast-simplification, borders preserved, so the
    cuts at depth discontinuities stay where they are): planar rooms need few triangles, and the
    rasterizer's cost is per triangle (llvmpipe)."""
    v, f = grid_mesh(camera, depth, step)
    if reduction <= 0 or len(f) < 200:
        return v, f
    import fast_simplification
    v2, f2 = fast_simplification.simplify(v, f, target_reduction=reduction, agg=7,
                                          preserve_border=True)
    return np.asarray(v2, np.float32), np.asarray(f2, np.int32)


def _mirrored_mesh(vertices: np.ndarray, faces: np.ndarray, plane: np.ndarray, side: float):
    """The part of a mesh strictly in front of `plane` (on the cameras' side), mirrored through it."""
    n, d0 = np.asarray(plane[:3]), float(plane[3])
    s = side * (vertices @ n + d0)
    fs = s[faces]
    keep = (fs.min(1) > -1e-3) & (fs.max(1) > 1e-3)  # not behind, not lying in the plane itself
    v = vertices - 2.0 * (vertices @ n + d0)[:, None] * n[None]
    return v.astype(np.float32), faces[keep][:, ::-1].astype(np.uint32)


class GroundTruth:
    """Reads a synthetic input folder's gt/ once (mesh, reflectors, mirrored meshes)."""

    def __init__(self, root: Path):
        self.root = Path(root)
        for rel in ("cameras.json", "gt/mesh.ply", "gt/geom"):
            if not (self.root / rel).exists():
                raise InputError(f"{self.root / rel}: missing (not a synthetic scene with ground truth)")
        self.cameras = cameras_from_json(self.root / "cameras.json")
        rp = self.root / "reflectors.json"
        self.reflectors = read_reflectors(rp) if rp.is_file() else ()
        self._mesh = None
        self._scenes: dict[int, object] = {}
        self._direct = None  # the GT mesh itself, for rays through glass

    def _scene(self, i: int):
        if i not in self._scenes:
            from ..io.mesh import read_ply
            from ..geometry.raycast import build_scene
            if self._mesh is None:
                self._mesh = read_ply(self.root / "gt" / "mesh.ply")
            plane = np.asarray(self.reflectors[i].plane)
            centres = np.array([c.center for c in self.cameras.values()])
            side = float(np.sign(np.median(centres @ plane[:3] + plane[3])) or 1.0)
            v, f = _mirrored_mesh(self._mesh.vertices.astype(np.float64), self._mesh.faces, plane, side)
            self._scenes[i] = build_scene(v, f)
        return self._scenes[i]

    def geom(self, name: str) -> dict:
        p = self.root / "gt" / "geom" / f"{Path(name).stem}.npz"
        try:
            with np.load(p) as z:
                return {k: z[k] for k in z.files}
        except (OSError, ValueError) as e:
            raise InputError(f"{p}: cannot read ground-truth geometry ({e})") from None

    def layers(self, name: str):
        from ..io.images import read_image
        stem = Path(name).stem
        i0 = read_image(self.root / "gt" / "I0" / f"{stem}.png")
        i1 = read_image(self.root / "gt" / "I1" / f"{stem}.png")
        beta = read_image(self.root / "gt" / "beta" / f"{stem}.png")[..., 0]
        return i0, i1, beta

    def _mesh_scene(self):
        if self._direct is None:
            from ..geometry.raycast import build_scene
            from ..io.mesh import read_ply
            if self._mesh is None:
                self._mesh = read_ply(self.root / "gt" / "mesh.ply")
            self._direct = build_scene(self._mesh.vertices, self._mesh.faces)
        return self._direct

    def transmitted_depth(self, camera: Camera, depth: np.ndarray) -> np.ndarray:
        """`depth` with every pixel whose GT point lies on a glass reflector (inside its polygon)
        replaced by the z-depth of what the pane transmits: the camera ray cast on from just
        beyond the pane into the GT mesh (a thin pane, no ray offset, as the tracer models it)."""
        from ..geometry.fusion import polygon_mask
        from ..geometry.raycast import camera_rays, cast
        glass = [r for r in self.reflectors if r.material == "glass"]
        out = np.array(depth, dtype=np.float32, copy=True)
        if not glass or not (depth > 0).any():
            return out
        uv = camera.pixel_grid().reshape(-1, 2)
        pts = camera.unproject(uv, depth.reshape(-1).astype(np.float64))
        origins, dirs = camera_rays(camera)
        for r in glass:
            plane = np.asarray(r.plane, np.float64)
            on = (depth.reshape(-1) > 0) & (np.abs(pts @ plane[:3] + plane[3]) < 0.02)
            if r.polygon is not None:
                on &= polygon_mask(camera, np.asarray(r.polygon)).reshape(-1)
            if not on.any():
                continue
            start = pts[on] + 1e-3 * dirs[on]  # past the pane's own triangles
            t = cast(self._mesh_scene(), start, dirs[on])["t_hit"]
            z = ((start + dirs[on] * np.where(np.isfinite(t), t, 0.0)[:, None] - camera.center)
                 @ camera.viewing_direction)
            out.reshape(-1)[np.flatnonzero(on)] = np.where(np.isfinite(t) & (z > 0), z, 0.0)
        return out

    def virtual_depth(self, camera: Camera, depth: np.ndarray, beta: np.ndarray) -> np.ndarray:
        """(H, W) z-depth of the reflection layer's virtual points (0 outside reflectors)."""
        from ..geometry.raycast import camera_rays, cast, hit_depth
        out = np.zeros(depth.shape, np.float64)
        refl = (beta > 0) & (depth > 0)
        if not refl.any() or not self.reflectors:
            return out.astype(np.float32)
        uv = camera.pixel_grid().reshape(-1, 2)
        pts = camera.unproject(uv, depth.reshape(-1)).reshape(*depth.shape, 3)
        planes = np.array([r.plane for r in self.reflectors])
        dist = np.abs(pts @ planes[:, :3].T + planes[:, 3])  # (H, W, R)
        which = np.where(dist.min(-1) < 0.02, dist.argmin(-1), -1)
        origins, dirs = camera_rays(camera)
        for i in range(len(self.reflectors)):
            m = (refl & (which == i)).reshape(-1)
            if not m.any():
                continue
            hit = cast(self._scene(i), origins[m], dirs[m])["t_hit"]
            vals = hit_depth(hit, dirs[m], camera)
            flat = out.reshape(-1)
            flat[np.flatnonzero(m)] = vals
        return out.astype(np.float32)

    def view(self, name: str, layers: bool = True, step: int = GRID_STEP,
             settings: RenderSettings | None = None, image: np.ndarray | None = None) -> ViewData:
        """ViewData of capture view `name` built from ground truth (two layers when `layers`)."""
        from ..io.images import read_image
        s = settings or RenderSettings()
        cam = self.cameras[name]
        surface = self.geom(name)["depth"].astype(np.float32)  # the first surface: a pane itself
        depth = self.transmitted_depth(cam, surface)
        edges = depth_edges(depth)
        alpha0 = blend.texture_alpha(edges, s.feather_px, s.edge_decay_px)
        v0, f0 = simplified_grid_mesh(cam, depth, step)
        if not layers:
            img = image if image is not None else read_image(self.root / "images" / name)
            return ViewData(name, cam, (LayerData(v0, f0, img, alpha0), None))
        i0, i1, beta = self.layers(name)
        vdepth = self.virtual_depth(cam, surface, beta) if (beta > 0).any() else None
        v1, f1 = simplified_grid_mesh(cam, vdepth, step) if vdepth is not None else (None, np.zeros((0, 3)))
        if len(f1) == 0:
            return ViewData(name, cam, (LayerData(v0, f0, i0, alpha0, beta), None))
        alpha1 = blend.texture_alpha(depth_edges(vdepth) | edges | mask_boundary(beta > 0),
                                     s.feather_px, s.edge_decay_px)
        return ViewData(name, cam, (LayerData(v0, f0, i0, alpha0, beta), LayerData(v1, f1, i1, alpha1)))

    def model(self, layers: bool = True, step: int = GRID_STEP, settings: RenderSettings | None = None,
              names=None, progress: bool = False):
        """The IBRModel of the GT-built views, in view order, built here (`submit_model` builds
        them in worker processes)."""
        from tqdm import tqdm

        from .ibr import IBRModel
        names = list(self.cameras) if names is None else list(names)
        views = [self.view(n, layers, step, settings)
                 for n in tqdm(names, desc="oracle views", disable=not progress, leave=False)]
        return IBRModel(views, settings)

    def submit_model(self, submit, layers: bool = True, step: int = GRID_STEP,
                     settings: RenderSettings | None = None, names=None):
        """`model` with its views built by `submit(fn, *args)` -> Future (a worker pool's submit:
        each worker its own GroundTruth, the mirrored ray-casting scenes do not pickle), all
        started now; returns finish() -> the IBRModel, which waits for them, so that the caller
        does other work while the views are built. submit=None: built here, now."""
        from .ibr import IBRModel
        if submit is None:
            built = self.model(layers, step, settings, names)
            return lambda: built
        names = list(self.cameras) if names is None else list(names)
        futures = [submit(_view_task, self.root, n, layers, step, settings) for n in names]
        return lambda: IBRModel([f.result() for f in futures], settings)


_TRUTHS = ProcessCache(1)


def _view_task(root: Path, name: str, layers: bool, step: int, settings) -> ViewData:
    """GroundTruth(root).view in a worker process, one GroundTruth per scene there."""
    gt = _TRUTHS.get(file_key(Path(root) / "gt" / "mesh.ply"), lambda: GroundTruth(root))
    return gt.view(name, layers, step, settings)
