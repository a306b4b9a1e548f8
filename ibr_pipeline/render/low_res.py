"""Low-resolution renderers of capture views for DSRNet's training data (nn/data.py: any callable
`renderer(name, camera_lr) -> (color, depth)` that renders view `name` without using that view).

* `IBRRenderer(ws)`: the real one, the render_views renderer (render/ibr.py) with
  `exclude=(name,)`.
* `StandInRenderer(folder)`: a STAND-IN for tests and benchmarks of a synthetic scene: the
  ground-truth image with IBR-like artefacts (sub-pixel misalignment as a smooth random
  displacement, blending blur, holes at depth discontinuities), area-downsampled to the camera
  size, and the ground-truth depth. It is not an IBR render: it has no ghosting in reflections and
  no seams between source views.
"""
from __future__ import annotations

import copy
import hashlib
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..scene import Camera, cameras_from_json


def _seed_of(*parts) -> int:
    return int.from_bytes(hashlib.sha256("/".join(map(str, parts)).encode()).digest()[:8], "little")


class StandInRenderer:
    """STAND-IN low-resolution IBR render of a synthetic scene (see the module docstring).

    folder: a synthetic scene folder (`ibr synth` output, with gt/). Knows capture views
    (images/NAME + gt/geom), test views (gt/test/...) and fly-through frames (gt/flythrough/images;
    depth by ray casting gt/mesh.ply). Artefacts are seeded by (seed, view name): deterministic."""

    def __init__(self, folder: Path | str, seed: int = 0, shift_px: float = 0.3,
                 blur_sigma: float = 0.7, hole_prob: float = 0.25):
        self.folder = Path(folder)
        if not (self.folder / "gt").is_dir():
            raise InputError(f"{self.folder}: not a synthetic scene (no gt/ folder)")
        self.seed, self.shift_px, self.blur_sigma, self.hole_prob = seed, shift_px, blur_sigma, hole_prob
        self._mesh_scene = None
        self.extra: dict = {}  # name -> (image (H,W,3), depth (H,W)) of frames traced elsewhere

    def cameras(self, which: str = "capture") -> dict[str, Camera]:
        f = {"capture": "cameras.json", "test": "gt/test_cameras.json",
             "flythrough": "gt/flythrough_cameras.json"}[which]
        return cameras_from_json(self.folder / f)

    def gt_image(self, name: str) -> np.ndarray:
        from ..io.images import read_image
        if name in self.extra:
            return self.extra[name][0]
        return read_image(self._image_path(name))

    def _image_path(self, name: str) -> Path:
        if name.startswith("test_"):
            return self.folder / "gt/test/images" / name
        if name.startswith("fly_"):
            return self.folder / "gt/flythrough/images" / name
        return self.folder / "images" / name

    def gt_depth(self, name: str, camera: Camera) -> np.ndarray:
        """Full-resolution z-depth of a view (gt/geom npz, else ray cast of gt/mesh.ply)."""
        if name in self.extra:
            return self.extra[name][1]
        stem = Path(name).stem
        geom = (self.folder / "gt/test/geom" / f"{stem}.npz" if name.startswith("test_")
                else self.folder / "gt/geom" / f"{stem}.npz")
        if geom.is_file():
            with np.load(geom) as z:
                return z["depth"].astype(np.float32)
        from ..geometry.raycast import build_scene, render_depth
        from ..io.mesh import read_ply
        if self._mesh_scene is None:
            m = read_ply(self.folder / "gt/mesh.ply")
            self._mesh_scene = build_scene(m.vertices, m.faces)
        return render_depth(self._mesh_scene, camera).astype(np.float32)

    def __call__(self, name: str, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
        import cv2

        gt = self.gt_image(name)
        H, W = gt.shape[:2]
        full_cam = camera.resized(W, H)
        depth_full = self.gt_depth(name, full_cam)
        rng = np.random.default_rng(_seed_of(self.seed, name, camera.width))
        # misalignment: a smooth random displacement field (imprecise geometry / blending seams)
        coarse = rng.normal(0.0, self.shift_px, size=(3, 4, 2)).astype(np.float32)
        disp = cv2.resize(coarse, (W, H), interpolation=cv2.INTER_CUBIC)
        u, v = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
        img = cv2.remap(gt, u + disp[..., 0], v + disp[..., 1], cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_REFLECT)
        dep = cv2.remap(depth_full, u + disp[..., 0], v + disp[..., 1], cv2.INTER_NEAREST,
                        borderMode=cv2.BORDER_REFLECT)
        if self.blur_sigma > 0:  # blending of several source views blurs
            img = cv2.GaussianBlur(img, (0, 0), self.blur_sigma)
        w, h = camera.width, camera.height
        color = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
        fy, fx = H // h, W // w
        depth = dep[:h * fy, :w * fx].reshape(h, fy, w, fx).min(axis=(1, 3))  # nearest surface
        # holes: small blobs at depth discontinuities, colour and depth 0 (disocclusions)
        with np.errstate(divide="ignore", invalid="ignore"):
            jump = np.zeros((h, w), bool)
            jump[:, 1:] |= np.abs(np.diff(depth, axis=1)) > 0.05 * depth[:, 1:]
            jump[1:] |= np.abs(np.diff(depth, axis=0)) > 0.05 * depth[1:]
        seeds = jump & (rng.random((h, w)) < self.hole_prob * 0.1)
        holes = cv2.dilate(seeds.astype(np.uint8), np.ones((2, 2), np.uint8)) > 0
        color[holes] = 0.0
        depth = np.where(holes, 0.0, depth)
        return color.astype(np.float32), depth.astype(np.float32)


class IBRRenderer:
    """The real low-resolution renderer: leave-one-out renders with render/ibr.py's IBRModel.

    `excluding({name: more views})` (`nearest_views`): the same model, leaving those views out of
    that view's render as well: renders from farther sources, with the artefacts of a view off the
    capture path."""

    def __init__(self, ws, layers: bool = True):
        from .ibr import IBRModel, stored_settings
        # render_views' settings: DSRNet learns to upsample the renders `ibr render` makes
        self.model = IBRModel.load(ws, layers=layers, settings=stored_settings(ws))
        self.exclude: dict = {}

    def __call__(self, name: str, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
        frame = self.model.render(camera, exclude=(name, *self.exclude.get(name, ())))
        return np.asarray(frame.color, np.float32), np.asarray(frame.depth, np.float32)

    def excluding(self, exclude: dict) -> "IBRRenderer":
        """The same loaded model, leaving out `exclude[name]` as well (see the class doc)."""
        other = copy.copy(self)
        other.exclude = dict(exclude)
        return other
