"""COLMAP models via pycolmap: read registered cameras, write a model (text or binary).

COLMAP puts the centre of the top-left pixel at (0.5, 0.5); our convention (scene.py) puts it at
(0, 0), so the principal point moves by 0.5 px on the way in and out. Only undistorted pinhole
models are accepted (SIMPLE_PINHOLE, PINHOLE); distorted models must be undistorted first (COLMAP's
`image_undistorter`), because every later stage assumes straight projection.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError, input_text
from ..scene import Camera

_PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")


def _camera_K(cam) -> np.ndarray:
    K = np.array(cam.calibration_matrix(), dtype=np.float64)
    K[0, 2] -= 0.5
    K[1, 2] -= 0.5
    return K


def check_text_model(path: Path) -> None:
    """Name the file and line of a non-numeric or non-finite value in a text model.

    pycolmap reports these as a failed C++ stream check without saying where; a user needs the line.
    """
    import math

    def check(file: Path, lines_of_interest, skip_tokens: set[int]):
        for lineno, line in lines_of_interest:
            for i, tok in enumerate(line.split()):
                if i in skip_tokens:
                    continue
                try:
                    ok = math.isfinite(float(tok))
                except ValueError:
                    ok = False
                if not ok:
                    raise InputError(f"{file}: line {lineno}: value {tok!r} is not a finite number")

    def data_lines(file: Path):
        return [(n, l) for n, l in enumerate(input_text(file).splitlines(), 1)
                if l.strip() and not l.startswith("#")]

    if (path / "cameras.txt").is_file():
        check(path / "cameras.txt", data_lines(path / "cameras.txt"), {1})  # token 1: model name
    if (path / "images.txt").is_file():
        # pose lines alternate with 2D-point lines; a pose line: ID QW QX QY QZ TX TY TZ CAMERA_ID NAME
        lines = data_lines(path / "images.txt")
        poses = [(n, " ".join(l.split()[:9])) for n, l in lines if len(l.split()) >= 10]
        check(path / "images.txt", poses, set())


def read_colmap_model(path: Path) -> dict[str, Camera]:
    """Read a COLMAP model folder (binary or text) into {image name: Camera}, registered images only."""
    import pycolmap

    path = Path(path)
    if not any((path / f"cameras.{ext}").is_file() for ext in ("bin", "txt")):
        raise InputError(f"{path}: not a COLMAP model (no cameras.bin / cameras.txt)")
    if not (path / "cameras.bin").is_file():
        check_text_model(path)
    try:
        rec = pycolmap.Reconstruction(str(path))
    except Exception as e:  # pycolmap raises plain RuntimeError/ValueError for broken files
        raise InputError(f"{path}: cannot read COLMAP model ({str(e).splitlines()[0]})") from None
    out: dict[str, Camera] = {}
    for image in rec.images.values():
        if not image.has_pose:
            continue
        cam = image.camera
        if cam.model_name not in _PINHOLE_MODELS:
            raise InputError(f"{path}: camera {cam.camera_id} has model {cam.model_name}; "
                             f"undistort the images first (only {', '.join(_PINHOLE_MODELS)})")
        T = np.eye(4)
        T[:3, :] = image.cam_from_world().matrix()
        try:
            out[image.name] = Camera(_camera_K(cam), T, cam.width, cam.height)
        except InputError as e:
            raise InputError(f"{path}: image {image.name}: {e}") from None
    return out


def build_reconstruction(cameras: dict[str, Camera]):
    """A pycolmap.Reconstruction with one PINHOLE camera per distinct intrinsics and posed images."""
    import pycolmap

    rec = pycolmap.Reconstruction()
    cam_ids: dict[tuple, int] = {}
    for image_id, (name, cam) in enumerate(sorted(cameras.items()), start=1):
        key = (cam.width, cam.height, *np.round(cam.K.ravel(), 9))
        if key not in cam_ids:
            cam_ids[key] = len(cam_ids) + 1
            fx, fy, cx, cy = cam.K[0, 0], cam.K[1, 1], cam.K[0, 2] + 0.5, cam.K[1, 2] + 0.5
            pc = pycolmap.Camera(model="PINHOLE", width=cam.width, height=cam.height,
                                 params=[fx, fy, cx, cy], camera_id=cam_ids[key])
            rec.add_camera_with_trivial_rig(pc)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(cam.R), cam.t)
        image = pycolmap.Image(name=name, camera_id=cam_ids[key], image_id=image_id)
        rec.add_image_with_trivial_frame(image, pose)
    return rec


def write_colmap_model(cameras: dict[str, Camera], path: Path, text: bool = True) -> None:
    """Write {image name: Camera} as a COLMAP model (no 3D points) into folder `path`."""
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    rec = build_reconstruction(cameras)
    (rec.write_text if text else rec.write_binary)(str(path))
