"""nerfstudio's `transforms.json` (a capture) and `camera_path.json` (a render trajectory).

transforms.json (nerfstudio's dataparser, also instant-ngp's): global intrinsics `fl_x fl_y cx cy
w h camera_model k1 k2 k3 k4 p1 p2`, any of which a frame may override, and per frame `file_path`
(relative to the json's folder), `transform_matrix` (4x4 camera-to-world), optional
`depth_file_path` and `mask_path`.

Conventions, and how they map to ours (scene.py, capture.py):
* Poses are camera-to-world in OpenGL/Blender camera axes (x right, y up, z backwards). Ours are
  OpenCV (x right, y down, z forward) world-to-camera: c2w_cv = c2w_gl @ diag(1, -1, -1, 1), then
  inverted. The world frame is kept as the file gives it (no re-centring, no rescaling).
* cx, cy are in COLMAP's pixel convention (top-left pixel centre at (0.5, 0.5)): nerfstudio's
  COLMAP converter copies COLMAP's params unchanged, so a `Lens` takes them as they are.
* nerfstudio's perspective distortion is OpenCV's: radial 1 + k1 r^2 + k2 r^4 + k3 r^6 + k4 r^8
  (r^2 = x^2 + y^2) plus tangential p1, p2; OPENCV_FISHEYE's k1..k4 are the theta polynomial of
  OpenCV's (and COLMAP's) fisheye model.

camera_path.json (nerfstudio viewer / `ns-render camera-path`): `render_width`, `render_height`,
`camera_type`, and a `camera_path` list of {`camera_to_world`: 16 numbers row-major, `fov`:
vertical field of view in degrees, `aspect`}; `fps` and `seconds`. The same OpenGL axes; the
principal point is the image centre. A path saved by the nerfstudio viewer is in the *trained
model's* normalised world (dataparser_transforms.json), not in transforms.json's.
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError, confined, input_text
from ..scene import Camera
from .capture import Capture, Frame, Lens

FORMAT = "nerfstudio"
# OpenGL camera axes -> OpenCV camera axes (flip y and z); its own inverse.
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])
_INTRINSICS = ("fl_x", "fl_y", "cx", "cy", "w", "h")
_DISTORTION = ("k1", "k2", "k3", "k4", "p1", "p2")
# nerfstudio models whose projection is perspective + OpenCV radial-tangential distortion
_PERSPECTIVE = ("PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
_ROTATION_TOL = 1e-3  # |R R^T - I| accepted (files written with few decimals), then re-orthonormalised
_DEFAULT_DEPTH_SCALE = 1e-3  # nerfstudio's depth_unit_scale_factor default: depth PNGs in mm


# --- shared helpers (io/llff.py uses cam_from_c2w too) -------------------------------------------
def load_json(path: Path) -> Any:
    """The parsed JSON of an input file, or InputError naming it and where it is broken."""
    try:
        return json.loads(input_text(path))
    except json.JSONDecodeError as e:
        raise InputError(f"{path}: not valid JSON (line {e.lineno}, column {e.colno}: {e.msg})") from None
    except RecursionError:
        raise InputError(f"{path}: not valid JSON (nested too deeply)") from None


def number(value: Any, what: str) -> float:
    """`value` as a finite float; JSON strings, booleans and nulls are refused (InputError)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(f"{what}: must be a number, got {json.dumps(value)[:80]}")
    out = float(value)
    if not math.isfinite(out):
        raise InputError(f"{what}: must be finite, got {value}")
    return out


def _fields(obj: Any, keys: tuple[str, ...], where: str) -> None:
    """InputError unless `obj` is a JSON object holding every one of `keys`."""
    if not isinstance(obj, dict):
        raise InputError(f"{where}: expected an object with {' and '.join(keys)}")
    for key in keys:
        if key not in obj:
            raise InputError(f"{where}: missing field {key!r}")


def _size(value: Any, what: str) -> int:
    v = number(value, what)
    if v <= 0 or v != round(v):
        raise InputError(f"{what}: must be a positive whole number of pixels, got {value}")
    return int(v)


def _matrix4(value: Any, what: str) -> np.ndarray:
    """A 4x4 matrix from nested lists or 16 numbers (row-major), numbers only."""
    if isinstance(value, list) and len(value) == 16 and not any(isinstance(v, list) for v in value):
        value = [value[i:i + 4] for i in range(0, 16, 4)]
    if not (isinstance(value, list) and len(value) == 4
            and all(isinstance(r, list) and len(r) == 4 for r in value)):
        raise InputError(f"{what}: must be a 4x4 matrix (4 rows of 4 numbers)")
    return np.array([[number(v, what) for v in row] for row in value])


def cam_from_c2w(c2w: np.ndarray, what: str) -> np.ndarray:
    """cam_from_world from an OpenCV-axes camera-to-world 4x4 (or 3x4), checked to be rigid.

    Files written with float32 or a few decimals are a little off a rotation; within
    `_ROTATION_TOL` the nearest rotation is taken, so that `Camera` (stricter) accepts it.
    """
    c2w = np.asarray(c2w, dtype=np.float64)
    if c2w.shape not in ((4, 4), (3, 4)):
        raise ValueError(f"c2w must be 4x4 or 3x4, got {c2w.shape}")
    if c2w.shape == (4, 4) and np.max(np.abs(c2w[3] - [0, 0, 0, 1])) > 1e-6:
        raise InputError(f"{what}: last row must be [0, 0, 0, 1], got {c2w[3].tolist()}")
    R, t = c2w[:3, :3], c2w[:3, 3]
    err = np.max(np.abs(R @ R.T - np.eye(3)))
    if err > _ROTATION_TOL:
        raise InputError(f"{what}: rotation part is not a rotation (scaled or sheared; "
                         f"|R R^T - I| = {err:.2g})")
    if np.linalg.det(R) < 0:
        raise InputError(f"{what}: rotation part is a reflection (determinant < 0)")
    if err > 1e-9:
        u, _, vt = np.linalg.svd(R)
        R = u @ vt
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def _c2w_gl(cam: Camera) -> np.ndarray:
    return cam.world_from_cam @ GL_TO_CV


# --- transforms.json -------------------------------------------------------------------------------
def _lens(model: Any, intr: dict[str, float], dist: dict[str, float], what: str) -> Lens:
    """The COLMAP lens equal to a nerfstudio camera: same maths, COLMAP's names and order."""
    fx, fy, cx, cy = intr["fl_x"], intr["fl_y"], intr["cx"], intr["cy"]
    w, h = int(intr["w"]), int(intr["h"])
    k1, k2, k3, k4, p1, p2 = (dist[k] for k in _DISTORTION)
    if model is not None and not isinstance(model, str):
        raise InputError(f"{what}camera_model: must be a string, got {json.dumps(model)[:40]}")
    if model is None or model in _PERSPECTIVE:  # nerfstudio applies k1..k4, p1, p2 to all of them
        if k4 != 0:
            raise InputError(f"{what}k4 = {k4}: nerfstudio's k4 multiplies r^8, a radial term no "
                             "COLMAP model has, so these images cannot be undistorted exactly")
        if not any((k1, k2, k3, p1, p2)):
            return Lens("PINHOLE", (fx, fy, cx, cy), w, h)
        if k3 != 0:
            # FULL_OPENCV's radial factor is (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4
            # + k6 r^6): nerfstudio's k3 (r^6) is its numerator k3; the denominator stays 1.
            return Lens("FULL_OPENCV", (fx, fy, cx, cy, k1, k2, p1, p2, k3, 0.0, 0.0, 0.0), w, h)
        if model in ("SIMPLE_RADIAL", "RADIAL") and fx == fy and p1 == p2 == 0:
            if model == "SIMPLE_RADIAL" and k2 == 0:
                return Lens("SIMPLE_RADIAL", (fx, cx, cy, k1), w, h)
            return Lens("RADIAL", (fx, cx, cy, k1, k2), w, h)
        return Lens("OPENCV", (fx, fy, cx, cy, k1, k2, p1, p2), w, h)
    if model == "OPENCV_FISHEYE":
        if p1 or p2:
            raise InputError(f"{what}OPENCV_FISHEYE with p1/p2 = {p1}, {p2}: a fisheye model has no "
                             "tangential terms in COLMAP, so these images cannot be undistorted")
        return Lens("OPENCV_FISHEYE", (fx, fy, cx, cy, k1, k2, k3, k4), w, h)
    raise InputError(f"{what}camera_model {model!r} cannot be undistorted to a pinhole camera "
                     f"(readable: {', '.join(_PERSPECTIVE)}, OPENCV_FISHEYE)")


def _inside(root: Path, folder: Path, rel: Any, what: str) -> tuple[Path, str]:
    """(file, its path relative to `root`) for a path named relative to `folder`, which is inside
    `root`; InputError when it is not a string, leaves `root` or does not exist."""
    if not isinstance(rel, str) or not rel:
        raise InputError(f"{what}: must be a path string, got {json.dumps(rel)[:80]}")
    base = os.path.relpath(os.path.abspath(folder), os.path.abspath(root))
    joined = rel if os.path.isabs(rel) or base == "." else os.path.join(base, rel)
    file = confined(root, joined, f"{what} {rel!r}")
    if not file.is_file():
        raise InputError(f"{what}: {rel!r} not found ({file})")
    return file, os.path.normpath(joined).replace(os.sep, "/")


def _frame_name(folder_rel: str, root_rel: str) -> str:
    """The view name: the image path relative to the json's folder, without a leading "images/"
    (so that names match the COLMAP and cameras.json readers'); relative to the input folder for
    an image outside the json's folder."""
    name = folder_rel if not folder_rel.startswith("../") else root_rel
    return name[len("images/"):] if name.startswith("images/") else name


def read_transforms(path: Path, root: Path, images: bool = True) -> Capture:
    """Read a nerfstudio transforms.json inside input folder `root` into a Capture.

    images=False reads the cameras alone (a camera set to render): the files need not exist."""
    path, root = Path(path), Path(root)
    meta = load_json(path)
    if not isinstance(meta, dict):
        raise InputError(f"{path}: expected a JSON object with 'frames'")
    frames_in = meta.get("frames")
    if not isinstance(frames_in, list) or not frames_in:
        raise InputError(f"{path}: 'frames' must be a non-empty list of frames")

    def field(frame: dict, key: str) -> Any:  # a frame's own value overrides the global one
        return frame[key] if key in frame else meta.get(key)

    scale = meta.get("depth_unit_scale_factor", _DEFAULT_DEPTH_SCALE)  # metres per depth unit
    scale = number(scale, f"{path}: depth_unit_scale_factor")
    if scale <= 0:
        raise InputError(f"{path}: depth_unit_scale_factor must be > 0, got {scale}")

    frames: list[Frame] = []
    files: list[Path] = [path]
    masks = 0
    for i, fr in enumerate(frames_in):
        where = f"{path}: frame {i}"
        _fields(fr, ("file_path", "transform_matrix"), where)
        intr = {}
        for key in _INTRINSICS:
            v = field(fr, key)
            if v is None:
                raise InputError(f"{where}: missing field {key!r} (neither in the frame nor global)")
            intr[key] = (_size if key in ("w", "h") else number)(v, f"{where}: {key}")
        if not (intr["fl_x"] > 0 and intr["fl_y"] > 0):
            raise InputError(f"{where}: fl_x, fl_y must be > 0, got {intr['fl_x']}, {intr['fl_y']}")
        dist = {k: 0.0 if field(fr, k) is None else number(field(fr, k), f"{where}: {k}")
                for k in _DISTORTION}
        lens = _lens(field(fr, "camera_model"), intr, dist, f"{where}: ")

        c2w = _matrix4(fr["transform_matrix"], f"{where}: transform_matrix")
        T = cam_from_c2w(c2w @ GL_TO_CV, f"{where}: transform_matrix")

        if images:
            image, root_rel = _inside(root, path.parent, fr["file_path"], f"{where}: file_path")
        else:  # cameras only: the file path is a name, never opened, so it may lead anywhere
            if not isinstance(fr["file_path"], str) or not fr["file_path"]:
                raise InputError(f"{where}: file_path must be a path string")
            image, root_rel = path.parent / fr["file_path"], os.path.basename(fr["file_path"])
        folder_rel = os.path.normpath(fr["file_path"]).replace(os.sep, "/")
        depth = None
        if images and fr.get("depth_file_path") is not None:
            depth, _ = _inside(root, path.parent, fr["depth_file_path"], f"{where}: depth_file_path")
            if depth.suffix.lower() != ".png":
                raise InputError(f"{where}: depth_file_path {fr['depth_file_path']!r}: only 16-bit "
                                 "PNG depth frames are read; convert it, or remove the field")
            files.append(depth)
        masks += "mask_path" in fr
        files.append(image)
        frames.append(Frame(name=_frame_name(folder_rel, root_rel), image=image, cam_from_world=T,
                            lens=lens, depth=depth, depth_units_per_m=1.0 / scale))

    with_depth = sum(f.depth is not None for f in frames)
    if 0 < with_depth < len(frames):  # nerfstudio refuses this too; a partial set would mix geometry
        missing = [i for i, f in enumerate(frames) if f.depth is None]
        raise InputError(f"{path}: {with_depth} of {len(frames)} frames have a depth_file_path; "
                         f"missing in frames {missing[:5]}")
    names = [f.name for f in frames]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise InputError(f"{path}: several frames name the same image: {dup[:5]}")
    models = sorted({f.lens.model for f in frames})
    notes = [f"{path.name}: {len(frames)} frames, lens {', '.join(models)}"
             + (", with depth" if with_depth else "")]
    if masks:
        notes.append(f"{path.name}: mask_path of {masks} frames ignored (masks are not used)")
    frames.sort(key=lambda f: f.name)  # nerfstudio sorts by file name too
    return Capture(format=FORMAT, frames=tuple(frames), files=tuple(files), image_encoding=None,
                   notes=tuple(notes))


def _pinhole(cam: Camera) -> dict[str, float | int]:
    K = cam.K
    if K[0, 1] != 0:
        raise ValueError(f"K has skew {K[0, 1]}: transforms.json cannot store it")
    return {"fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]), "cx": float(K[0, 2]) + 0.5,
            "cy": float(K[1, 2]) + 0.5, "w": cam.width, "h": cam.height}


def write_transforms(cameras: dict[str, Camera], path: Path, image_prefix: str = "images/") -> None:
    """Write {image name: Camera} as a PINHOLE transforms.json (frame file_path = prefix + name);
    intrinsics global when all cameras share them, else per frame."""
    from ..workspace import atomic_path

    if not cameras:
        raise ValueError("write_transforms: no cameras")
    intr = {name: _pinhole(cam) for name, cam in cameras.items()}
    shared = len({tuple(v.values()) for v in intr.values()}) == 1
    out: dict[str, Any] = {"camera_model": "PINHOLE"}
    if shared:
        out.update(next(iter(intr.values())))
    frames = []
    for name in sorted(cameras):
        fr: dict[str, Any] = {"file_path": f"{image_prefix}{name}",
                              "transform_matrix": _c2w_gl(cameras[name]).tolist()}
        if not shared:
            fr.update(intr[name])
        frames.append(fr)
    out["frames"] = frames
    with atomic_path(Path(path)) as tmp, open(tmp, "w", encoding="utf-8") as f:
        json.dump(out, f, indent=1)


# --- camera_path.json ------------------------------------------------------------------------------
def read_camera_path(path: Path) -> list[Camera]:
    """The cameras of a nerfstudio camera_path.json, in path order (perspective paths only)."""
    path = Path(path)
    d = load_json(path)
    if not isinstance(d, dict) or not isinstance(d.get("camera_path"), list) or not d["camera_path"]:
        raise InputError(f"{path}: expected an object with a non-empty 'camera_path' list")
    kind = d.get("camera_type", "perspective")  # nerfstudio's default when absent
    if kind != "perspective":
        raise InputError(f"{path}: camera_type {kind!r}: only 'perspective' paths can be rendered")
    for key in ("render_width", "render_height"):
        if key not in d:
            raise InputError(f"{path}: missing field {key!r}")
    w = _size(d["render_width"], f"{path}: render_width")
    h = _size(d["render_height"], f"{path}: render_height")
    out = []
    for i, kf in enumerate(d["camera_path"]):
        where = f"{path}: camera_path[{i}]"
        _fields(kf, ("camera_to_world", "fov"), where)
        fov = number(kf["fov"], f"{where}: fov")
        if not 0 < fov < 180:
            raise InputError(f"{where}: fov must be in (0, 180) degrees, got {fov}")
        # nerfstudio: f = (H / 2) / tan(fov / 2), fov vertical; it ignores `aspect` (the render
        # size decides), and so do we
        f = 0.5 * h / math.tan(math.radians(fov) / 2)
        K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
        c2w = _matrix4(kf["camera_to_world"], f"{where}: camera_to_world")
        T = cam_from_c2w(c2w @ GL_TO_CV, f"{where}: camera_to_world")
        try:
            out.append(Camera(K, T, w, h))
        except InputError as e:
            raise InputError(f"{where}: {e}") from None
    return out


def write_camera_path(cameras: list[Camera], path: Path, fps: float = 24.0) -> None:
    """Write cameras as a camera_path.json that `ns-render camera-path` and read_camera_path read.

    The format has one size, square pixels and a centred principal point: cameras that differ
    from that raise ValueError rather than being written as other cameras.
    """
    from ..workspace import atomic_path

    if not cameras:
        raise ValueError("write_camera_path: no cameras")
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be > 0, got {fps}")
    w, h = cameras[0].size
    path_out = []
    for i, cam in enumerate(cameras):
        K = cam.K
        if cam.size != (w, h):
            raise ValueError(f"camera {i} is {cam.width}x{cam.height}, camera 0 {w}x{h}: "
                             "a camera path has one render size")
        if abs(K[0, 0] - K[1, 1]) > 1e-6 * K[0, 0] or K[0, 1] != 0:
            raise ValueError(f"camera {i}: fx {K[0, 0]} != fy {K[1, 1]} (or skew): a camera path "
                             "has square pixels")
        if abs(K[0, 2] - (w - 1) / 2) > 1e-6 * w or abs(K[1, 2] - (h - 1) / 2) > 1e-6 * h:
            raise ValueError(f"camera {i}: principal point ({K[0, 2]}, {K[1, 2]}) is not the image "
                             f"centre ({(w - 1) / 2}, {(h - 1) / 2}): a camera path cannot store it")
        fov = math.degrees(2 * math.atan(0.5 * h / K[1, 1]))
        path_out.append({"camera_to_world": _c2w_gl(cam).ravel().tolist(), "fov": fov,
                         "aspect": w / h})
    out = {"camera_type": "perspective", "render_width": w, "render_height": h,
           "fps": float(fps), "seconds": len(cameras) / fps, "camera_path": path_out}
    with atomic_path(Path(path)) as tmp, open(tmp, "w", encoding="utf-8") as f:
        json.dump(out, f, indent=1)


# --- sniffing --------------------------------------------------------------------------------------
def _sniff(path: Path, key: str) -> bool:
    try:
        path = Path(path)
        if not path.is_file():
            return False
        with open(path, "rb") as f:
            if not f.read(64).lstrip().startswith(b"{"):  # not a JSON object: no need to read it all
                return False
        d = json.loads(path.read_bytes().decode("utf-8"))
        return isinstance(d, dict) and isinstance(d.get(key), list)
    except Exception:  # junk of any kind (unreadable, not UTF-8, not JSON, too deep) is "no"
        return False


def is_transforms(path: Path) -> bool:
    """True when `path` looks like a transforms.json (a JSON object with a 'frames' list)."""
    return _sniff(path, "frames")


def is_camera_path(path: Path) -> bool:
    """True when `path` looks like a camera_path.json (a JSON object with a 'camera_path' list)."""
    return _sniff(path, "camera_path")
