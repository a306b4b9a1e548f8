"""Scene types and the conventions every module follows. Written once, here; never deviate.

Conventions
-----------
* Cameras use OpenCV axes: x right, y down, z forward. Extrinsics are `cam_from_world` (4x4,
  x_cam = R x_world + t); intrinsics `K` (3x3) in pixels; image size `(width, height)`.
* Pixel centres: the centre of the top-left pixel is (0, 0) (OpenCV). COLMAP puts it at
  (0.5, 0.5); `io.colmap` converts (cx, cy) -= 0.5 on read and += 0.5 on write.
* Units are metres. `depth` is z-depth along the optical axis; a distance along a ray is `range`.
* Colour images are 8-bit files in the **scene's encoding** (`Scene.image_encoding`, chosen by
  `ingest`): "srgb" for photographs (the default), "linear" for our synthetic scenes, which say so
  in gt/scene.json. Arrays in memory are always linear [0, 1]: `io.images.read_image(path, enc)`
  decodes and `write_image(path, img, enc)` encodes, so the layer composition I = I0 + beta * I1
  (Xu et al. Eq. 3), fusion and blending hold in linear radiance. Layer files (I0, I1) and renders
  are stored in the scene's encoding, like the photographs they are compared with. Matching
  (SfM, MVS, edges) works on the stored values, as COLMAP does.
* Float rasters (depth, layers, flows) are .npy/.npz. RGB-D sensor depth is a 16-bit PNG in
  millimetres (TUM/Open3D convention, `DEPTH_PNG_SCALE`), 0 = no measurement. A depth frame may be
  smaller than its colour image (sensors are lower resolution) but must cover the same field of
  view: same aspect ratio, intrinsics = K scaled by the size ratio (`Camera.resized`).
* Reflector planes are `n . x + d = 0` in world coordinates with unit `n`.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .errors import InputError, input_text

IMAGE_ENCODING = "linear"  # what a scene.json without the field means (written before it existed)
IMAGE_ENCODINGS = ("srgb", "linear")
DEPTH_PNG_SCALE = 1000.0  # 16-bit depth PNG units per metre (mm)
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg")


def _numbers(value: Any, what: str) -> np.ndarray:
    """`value` as a float64 array, or InputError naming `what` (strings, nulls, ragged lists)."""
    try:
        return np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{what}: must be numbers, got {str(value)[:80]}") from None


def _as_matrix(value: Any, shape: tuple[int, int], what: str) -> np.ndarray:
    arr = _numbers(value, what)
    if arr.shape != shape:
        raise InputError(f"{what}: expected a {shape[0]}x{shape[1]} matrix, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{what}: contains NaN or infinite values")
    return arr


@dataclass(frozen=True, eq=False)
class Camera:
    """A pinhole camera: intrinsics `K`, extrinsics `cam_from_world`, image `width` x `height`."""

    K: np.ndarray
    cam_from_world: np.ndarray
    width: int
    height: int

    def __post_init__(self) -> None:
        K = _as_matrix(self.K, (3, 3), "camera K")
        T = _as_matrix(self.cam_from_world, (4, 4), "camera cam_from_world")
        if not (K[0, 0] > 0 and K[1, 1] > 0) or K[2, 2] != 1 or np.any(K[2, :2] != 0):
            raise InputError(f"camera K: not a valid intrinsic matrix: {K.tolist()}")
        R = T[:3, :3]
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-5) or np.linalg.det(R) < 0:
            raise InputError("camera cam_from_world: rotation part is not a proper rotation")
        if not np.allclose(T[3], [0, 0, 0, 1]):
            raise InputError("camera cam_from_world: last row must be [0, 0, 0, 1]")
        size = _numbers([self.width, self.height], "camera width/height")
        if size.shape != (2,) or not np.all(np.isfinite(size)) or np.any(size != np.round(size)):
            raise InputError(f"camera width/height must be whole numbers, got {self.width}x{self.height}")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise InputError(f"camera size must be positive, got {self.width}x{self.height}")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "cam_from_world", T)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    # --- derived quantities -------------------------------------------------------------------
    @property
    def size(self) -> tuple[int, int]:
        return (self.width, self.height)

    @property
    def R(self) -> np.ndarray:
        return self.cam_from_world[:3, :3]

    @property
    def t(self) -> np.ndarray:
        return self.cam_from_world[:3, 3]

    @property
    def world_from_cam(self) -> np.ndarray:
        out = np.eye(4)
        out[:3, :3] = self.R.T
        out[:3, 3] = -self.R.T @ self.t
        return out

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates."""
        return -self.R.T @ self.t

    @property
    def viewing_direction(self) -> np.ndarray:
        """World-space direction of the optical axis (+z of the camera)."""
        return self.R[2].copy()

    # --- projection -----------------------------------------------------------------------------
    def project(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project (N, 3) world points: returns pixel coordinates (N, 2) and z-depth (N,)."""
        pts = np.asarray(points_world, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"points_world must be (N, 3), got {pts.shape}")
        cam = pts @ self.R.T + self.t
        z = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = (cam @ self.K.T)[:, :2] / z[:, None]
        return uv, z

    def unproject(self, uv: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Lift pixels (N, 2) with z-depth (N,) to world points (N, 3)."""
        uv = np.asarray(uv, dtype=np.float64)
        depth = np.asarray(depth, dtype=np.float64)
        if uv.ndim != 2 or uv.shape[1] != 2 or depth.shape != uv.shape[:1]:
            raise ValueError(f"uv must be (N, 2) and depth (N,), got {uv.shape} and {depth.shape}")
        rays = np.linalg.solve(self.K, np.c_[uv, np.ones(len(uv))].T).T  # z = 1
        cam = rays * depth[:, None]
        return (cam - self.t) @ self.R

    def pixel_grid(self) -> np.ndarray:
        """(H, W, 2) pixel-centre coordinates (u, v) of every pixel."""
        u, v = np.meshgrid(np.arange(self.width), np.arange(self.height))
        return np.stack([u, v], axis=-1).astype(np.float64)

    def resized(self, width: int, height: int) -> "Camera":
        """The same camera at another resolution (pixel-centre convention kept exact)."""
        sx, sy = width / self.width, height / self.height
        S = np.diag([sx, sy, 1.0])
        K = S @ self.K
        # centre of pixel 0 stays at the centre of the first pixel: c' = (c + 0.5) * s - 0.5
        K[0, 2] = (self.K[0, 2] + 0.5) * sx - 0.5
        K[1, 2] = (self.K[1, 2] + 0.5) * sy - 0.5
        return Camera(K, self.cam_from_world, width, height)

    # --- construction / serialisation -----------------------------------------------------------
    @staticmethod
    def look_at(eye, target, up, K: np.ndarray, width: int, height: int) -> "Camera":
        """Camera at `eye` looking at `target`; `up` is the world up direction (image y is down)."""
        eye, target, up = (np.asarray(a, dtype=np.float64) for a in (eye, target, up))
        z = target - eye
        z /= np.linalg.norm(z)
        x = np.cross(z, up)  # image right; then y = z × x points down the image (OpenCV)
        if np.linalg.norm(x) < 1e-9:
            raise ValueError("look_at: viewing direction is parallel to up")
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        R = np.stack([x, y, z])
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = -R @ eye
        return Camera(K, T, width, height)

    @staticmethod
    def intrinsics_from_fov(width: int, height: int, hfov_deg: float) -> np.ndarray:
        f = 0.5 * width / math.tan(math.radians(hfov_deg) / 2)
        return np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])

    def to_dict(self) -> dict:
        return {"K": self.K.tolist(), "cam_from_world": self.cam_from_world.tolist(),
                "width": self.width, "height": self.height}

    @staticmethod
    def from_dict(d: dict, where: str = "camera") -> "Camera":
        if not isinstance(d, dict):
            raise InputError(f"{where}: expected an object with K, cam_from_world, width, height")
        try:
            return Camera(d["K"], d["cam_from_world"], d["width"], d["height"])
        except KeyError as e:
            raise InputError(f"{where}: missing field {e.args[0]!r}") from None
        except InputError as e:
            raise InputError(f"{where}: {e}") from None


@dataclass(frozen=True)
class View:
    """One captured image. Paths are workspace keys (see `workspace.Workspace.path`)."""

    name: str
    image: str
    camera: Camera | None = None
    depth: str | None = None

    def to_dict(self) -> dict:
        return {"name": self.name, "image": self.image, "depth": self.depth,
                "camera": None if self.camera is None else self.camera.to_dict()}

    @staticmethod
    def from_dict(d: dict) -> "View":
        cam = d.get("camera")
        return View(d["name"], d["image"],
                    None if cam is None else Camera.from_dict(cam, f"view {d['name']}"),
                    d.get("depth"))


MATERIALS = ("mirror", "glass", "glossy")  # what a reflector is made of (docs/REFLECTION.md)


@dataclass(frozen=True)
class Reflector:
    """A user-given or detected planar reflector (`reflectors.json`, Xu et al. §4.3.1 "UI").

    plane: (a, b, c, d) with n . x + d = 0, n normalised on load. beta: reflectance in (0, 1] if
    known. polygon: optional (N, 3) world-space outline of the reflector's extent. masks: optional
    per-view mask images (view name -> workspace key), white = reflector. material: optional
    "mirror" (beta 1 when no beta is given), "glass" or "glossy"; detection sets it for the planes
    it finds, a user-given one overrides it (user planes win). outline: (view name, ((u, v), ...))
    instead of a plane: the reflector's corners in pixels of one photograph, for captures whose
    frame a user cannot give coordinates in (SfM units); plane is None until `global_mesh` fits it
    to the surface around the outline (`planes.plane_from_outline`).
    """

    name: str
    plane: tuple[float, float, float, float] | None
    beta: float | None = None
    polygon: tuple[tuple[float, float, float], ...] | None = None
    masks: dict[str, str] = field(default_factory=dict)
    material: str | None = None
    outline: tuple | None = None

    @property
    def normal(self) -> np.ndarray:
        return np.asarray(self.plane[:3])

    def to_dict(self) -> dict:
        d = {"name": self.name, "plane": None if self.plane is None else list(self.plane),
             "beta": self.beta,
             "polygon": None if self.polygon is None else [list(p) for p in self.polygon],
             "masks": dict(self.masks), "material": self.material}
        if self.outline is not None:
            d["outline"] = {"view": self.outline[0], "points": [list(p) for p in self.outline[1]]}
        return d

    @staticmethod
    def from_dict(d: dict, where: str) -> "Reflector":
        if not isinstance(d, dict) or (d.get("plane") is None and d.get("outline") is None):
            raise InputError(f"{where}: each reflector needs a 'plane' [a, b, c, d] or an "
                             "'outline' {\"view\": image name, \"points\": [[u, v], ...]}")
        name = str(d.get("name", where))
        outline = None if d.get("outline") is None else _outline(d["outline"], where)
        plane = None
        if d.get("plane") is not None:
            plane = _numbers(d["plane"], f"{where}: 'plane'")
            if plane.shape != (4,) or not np.all(np.isfinite(plane)):
                raise InputError(f"{where}: 'plane' must be 4 finite numbers, got {d['plane']!r}")
            n = np.linalg.norm(plane[:3])
            if n < 1e-9:
                raise InputError(f"{where}: 'plane' normal is zero")
            plane = tuple(float(c) for c in plane / n)
        beta = d.get("beta")
        if beta is not None and not (isinstance(beta, (int, float)) and 0 < beta <= 1):
            raise InputError(f"{where}: 'beta' must be a number in (0, 1], got {beta!r}")
        poly = d.get("polygon")
        if poly is not None:
            arr = _numbers(poly, f"{where}: 'polygon'")
            if arr.ndim != 2 or arr.shape[1] != 3 or len(arr) < 3 or not np.all(np.isfinite(arr)):
                raise InputError(f"{where}: 'polygon' must be >= 3 finite [x, y, z] points")
            poly = tuple(tuple(float(c) for c in p) for p in arr)
        masks = d.get("masks") or {}
        if not isinstance(masks, dict):
            raise InputError(f"{where}: 'masks' must map view names to mask image paths")
        material = d.get("material")
        if material is not None and material not in MATERIALS:
            raise InputError(f"{where}: 'material' must be one of {', '.join(MATERIALS)}, got "
                             f"{material!r}")
        if material == "mirror" and beta is None:
            beta = 1.0
        return Reflector(name, plane, None if beta is None else float(beta),
                         poly, {str(k): str(v) for k, v in masks.items()}, material, outline)


def _outline(o, where: str) -> tuple:
    """(view name, ((u, v), ...)) of a reflectors.json 'outline': >= 3 finite pixel positions."""
    if not isinstance(o, dict) or not isinstance(o.get("view"), str):
        raise InputError(f"{where}: 'outline' must be {{\"view\": image name, \"points\": "
                         "[[u, v], ...]}")
    pts = _numbers(o.get("points"), f"{where}: 'outline' points")
    if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) < 3 or not np.all(np.isfinite(pts)):
        raise InputError(f"{where}: 'outline' points must be >= 3 finite [u, v] pixel positions")
    return o["view"], tuple((float(u), float(v)) for u, v in pts)


@dataclass(frozen=True)
class Scene:
    """The scene manifest: every view, its camera (if known) and the user-given reflectors."""

    views: tuple[View, ...]
    reflectors: tuple[Reflector, ...] = ()
    source: str = ""  # the input layout it was read from (io/inputs.py): "colmap", "nerfstudio", ...
    image_encoding: str = IMAGE_ENCODING
    sparse: str | None = None  # key of a COLMAP model whose 3D points belong to the given poses

    def __post_init__(self) -> None:
        names = [v.name for v in self.views]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise InputError(f"duplicate view names: {sorted(dup)}")
        if self.image_encoding not in IMAGE_ENCODINGS:
            raise InputError(f"scene image_encoding must be one of {IMAGE_ENCODINGS}, "
                             f"got {self.image_encoding!r}")

    @property
    def names(self) -> list[str]:
        return [v.name for v in self.views]

    def view(self, name: str) -> View:
        for v in self.views:
            if v.name == name:
                return v
        raise KeyError(name)

    @property
    def posed_views(self) -> list[View]:
        return [v for v in self.views if v.camera is not None]

    def to_dict(self) -> dict:
        return {"format": "ibr_pipeline.scene/1", "source": self.source,
                "image_encoding": self.image_encoding, "sparse": self.sparse,
                "views": [v.to_dict() for v in self.views],
                "reflectors": [r.to_dict() for r in self.reflectors]}

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=1)

    @staticmethod
    def from_dict(d: dict) -> "Scene":
        return Scene(tuple(View.from_dict(v) for v in d["views"]),
                     tuple(Reflector.from_dict(r, f"reflector {i}")
                           for i, r in enumerate(d.get("reflectors", []))),
                     d.get("source", ""), d.get("image_encoding", IMAGE_ENCODING), d.get("sparse"))

    @staticmethod
    def from_json(text: str) -> "Scene":
        return Scene.from_dict(json.loads(text))


# --- cameras.json: our plain JSON camera format (also written by `ibr synth`) -------------------
def moved_camera(old: Camera, move_cm: float = 5.0, yaw_deg: float = 3.0, up_cm: float = 0.0) -> Camera:
    """`old` translated move_cm along its x axis (right), up_cm up, and yawed yaw_deg."""
    a = np.radians(yaw_deg)
    Ry = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    T = old.cam_from_world.copy()
    T[:3, :3] = Ry @ old.R
    c = old.center + 0.01 * move_cm * old.R[0] - 0.01 * up_cm * old.R[1]
    T[:3, 3] = -T[:3, :3] @ c
    return Camera(old.K, T, old.width, old.height)


def cameras_to_json(cameras: dict[str, Camera]) -> str:
    """Serialise {image name: Camera} in the `cameras.json` format."""
    return json.dumps({"format": "ibr_pipeline.cameras/1", "convention": "opencv",
                       "cameras": {name: cam.to_dict() for name, cam in cameras.items()}},
                      indent=1)


def cameras_from_json(path: Path) -> dict[str, Camera]:
    try:
        d = json.loads(input_text(path))
    except json.JSONDecodeError as e:
        raise InputError(f"{path}: cannot read camera JSON ({e})") from None
    if not isinstance(d, dict) or not isinstance(d.get("cameras"), dict):
        raise InputError(f"{path}: expected an object with a 'cameras' mapping")
    return {name: Camera.from_dict(c, f"{path}: camera {name!r}") for name, c in d["cameras"].items()}


def read_reflectors(path: Path) -> tuple[Reflector, ...]:
    try:
        d = json.loads(input_text(path))
    except json.JSONDecodeError as e:
        raise InputError(f"{path}: cannot read reflectors ({e})") from None
    items = d.get("reflectors") if isinstance(d, dict) else d
    if not isinstance(items, list):
        raise InputError(f"{path}: expected a list of reflectors (or {{'reflectors': [...]}})")
    return tuple(Reflector.from_dict(r, f"{path}: reflector {i}") for i, r in enumerate(items))
