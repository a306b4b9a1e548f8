"""The naïve diffuse-warp baseline: captured images warped with the surface depth only.

For a new camera, every pixel's surface point comes from ray casting the global mesh G
(`global/mesh.ply`); it takes the colour of the captured view nearest to the new camera by Xu et al.
Eq. 14 that sees that point (depth test against that view's own ray-cast depth of G), falling back
to the next-nearest views in Eq. 14 order; pixels no view sees are filled by the renderer's hole
filling (`blend.fill_holes`). No per-view meshes, no depth-edge refinement, no view blending, no
reflection layer: a reflection is pasted onto the reflector as if it were texture, and at the new
viewpoint it sits where the old view saw it (what Lochmann et al. 2014 and Xu et al. §1 call a
diffuse warp). It is the floor every refinement of the pipeline should lift.
"""
from __future__ import annotations

import time

import numpy as np

from .. import layout as L
from ..geometry.decompose_terms import sample_bilinear
from ..scene import Camera
from ..geometry import raycast
from .blend import fill_holes
from .selection import LAMBDA, view_distance

DEPTH_TOL_REL = 0.02   # visibility: |z_k(x) - depth_k| within 2 % of depth, plus 1 cm
DEPTH_TOL_ABS = 0.01
MAX_VIEWS = 4          # nearest views tried per frame, in Eq. 14 order


def visible_sample(camera: Camera, depth: np.ndarray, image: np.ndarray,
                   points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Colours (N, 3) of world `points` (N, 3) seen by `camera` (bilinear), and (N,) bool: in front
    of it, inside the image and not occluded (its ray-cast depth agrees with the point's depth)."""
    if depth.shape != (camera.height, camera.width) or image.shape[:2] != depth.shape:
        raise ValueError(f"depth {depth.shape} / image {image.shape} do not match camera "
                         f"{camera.width}x{camera.height}")
    uv, z = camera.project(points)
    H, W = depth.shape
    u, v = uv[:, 0], uv[:, 1]
    ok = (z > 1e-3) & (u >= -0.5) & (u <= W - 0.5) & (v >= -0.5) & (v <= H - 0.5)
    ui = np.clip(np.round(np.nan_to_num(u)), 0, W - 1).astype(np.int64)
    vi = np.clip(np.round(np.nan_to_num(v)), 0, H - 1).astype(np.int64)
    dk = depth[vi, ui]
    ok &= (dk > 0) & (np.abs(dk - z) <= DEPTH_TOL_REL * z + DEPTH_TOL_ABS)
    col = sample_bilinear(np.asarray(image, np.float32), np.nan_to_num(uv)).astype(np.float32)
    return col, ok


class NaiveWarp:
    """Renders new views by the naïve diffuse warp of `views` {name: (Camera, image)} over the
    mesh (vertices (V, 3), faces (F, 3)); an image is an (H, W, 3) array or a path, read on first
    use (only the views nearest to the rendered cameras are ever read).

    depths: {name: path of a .npy} of the mesh's z-depth already ray cast into that view (the
    workspace's `depth_init.npy`, view_depth's cast of the same G), read instead of casting again;
    a view without one, or whose file has another size, is cast."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, views: dict,
                 lam: float = LAMBDA, max_views: int = MAX_VIEWS, encoding: str = "linear",
                 scene_depth: float = 1.0, depths: dict | None = None):
        if not views:
            raise ValueError("NaiveWarp needs at least one captured view")
        self.encoding = encoding  # of the image files given by path: decoded to linear on read
        self.scene = raycast.build_scene(vertices, faces)
        self.views = dict(views)
        self.lam, self.scene_depth = lam, scene_depth  # Eq. 14's λ and D (selection.py)
        self.max_views = max_views
        self._depth: dict[str, np.ndarray] = {}
        self._depth_files = dict(depths or {})
        self._image: dict[str, np.ndarray] = {}
        names = list(self.views)
        self._names = names
        self._axes = np.stack([self.views[n][0].viewing_direction for n in names])
        self._centers = np.stack([self.views[n][0].center for n in names])

    def _view_depth(self, name: str) -> np.ndarray:
        if name not in self._depth:  # read or ray-cast once per view, on first use
            cam = self.views[name][0]
            path = self._depth_files.get(name)
            d = np.load(path).astype(np.float64) if path is not None else None
            if d is None or d.shape != (cam.height, cam.width):
                d = raycast.render_depth(self.scene, cam)
            self._depth[name] = d
        return self._depth[name]

    def _view_image(self, name: str) -> np.ndarray:
        if name not in self._image:
            img = self.views[name][1]
            if not isinstance(img, np.ndarray):
                from ..io.images import read_image
                img = read_image(img, self.encoding)
            self._image[name] = np.asarray(img[..., :3], np.float32)
        return self._image[name]

    def nearest(self, camera: Camera, exclude=()) -> tuple[str, np.ndarray]:
        """The captured image nearest to `camera` by Eq. 14, unwarped (the floor every IBR paper
        compares with), resized to the camera's size when it differs."""
        dist = view_distance(self._axes, self._centers, camera.viewing_direction, camera.center,
                             self.lam, self.scene_depth)
        skip = set(exclude)
        name = next(self._names[i] for i in np.argsort(dist) if self._names[i] not in skip)
        img = self._view_image(name)
        if img.shape[:2] != (camera.height, camera.width):
            import cv2
            img = cv2.resize(img, camera.size, interpolation=cv2.INTER_AREA)
        return name, img

    def render(self, camera: Camera, exclude=()) -> tuple[np.ndarray, np.ndarray, float]:
        """(H, W, 3) colour, (H, W) bool covered-by-a-view, and the frame's milliseconds (the
        captured views' depth maps are preprocessing: ray-cast once, outside the timing)."""
        dist = view_distance(self._axes, self._centers, camera.viewing_direction, camera.center,
                             self.lam, self.scene_depth)  # Eq. 14
        skip = set(exclude)
        order = [self._names[i] for i in np.argsort(dist) if self._names[i] not in skip]
        for name in order[:self.max_views]:  # preprocessing, outside the frame time
            self._view_depth(name)
            self._view_image(name)
        t0 = time.perf_counter()
        o, d = raycast.camera_rays(camera)
        t = raycast.cast(self.scene, o, d)["t_hit"]
        hit = np.isfinite(t)
        pts = o[hit] + d[hit] * t[hit, None]
        n = camera.height * camera.width
        color = np.zeros((n, 3), np.float32)
        covered = np.zeros(n, bool)
        idx_hit = np.flatnonzero(hit)
        todo = np.ones(len(idx_hit), bool)
        for name in order[:self.max_views]:
            if not todo.any():
                break
            col, ok = visible_sample(self.views[name][0], self._view_depth(name),
                                     self._view_image(name), pts[todo])
            sel = np.flatnonzero(todo)[ok]
            color[idx_hit[sel]] = col[ok]
            covered[idx_hit[sel]] = True
            todo[sel] = False
        img = color.reshape(camera.height, camera.width, 3)
        cov = covered.reshape(camera.height, camera.width)
        img = fill_holes(img, cov)
        return np.clip(img, 0, 1), cov, (time.perf_counter() - t0) * 1e3


def from_workspace(ws, lam: float = LAMBDA, scene_depth: float = 0.0) -> NaiveWarp | None:
    """The baseline over a workspace's global mesh and registered captured views (None when the
    global mesh or the cameras are missing)."""
    from ..io.mesh import read_ply

    mesh_path = ws.path(L.GLOBAL_MESH)
    if not mesh_path.is_file():
        return None
    cams = L.registered_cameras(ws)
    if not cams:
        return None
    scene = L.posed_scene(ws)
    views = {name: (cam, ws.path(scene.view(name).image)) for name, cam in cams.items()}
    mesh = read_ply(mesh_path)
    if not scene_depth:  # the workspace's, as the renderer resolves it
        from .ibr import workspace_scene_depth
        scene_depth = workspace_scene_depth(ws)
    return NaiveWarp(mesh.vertices, mesh.faces, views, lam=lam, encoding=scene.image_encoding,
                     scene_depth=scene_depth, depths=cast_depth_files(ws, cams))


def cast_depth_files(ws, cams) -> dict:
    """{view: path} of the views whose `depth_init.npy` (G ray cast by view_depth) exists."""
    out = {}
    for name in cams:
        p = ws.path(L.view_file(name, L.DEPTH_INIT))
        if p.is_file():
            out[name] = p
    return out
