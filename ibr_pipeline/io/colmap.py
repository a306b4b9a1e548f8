"""COLMAP models via pycolmap: read registered cameras, write a model (text or binary).

COLMAP puts the centre of the top-left pixel at (0.5, 0.5); our convention (scene.py) puts it at
(0, 0), so the principal point moves by 0.5 px on the way in and out. `read_colmap_capture` takes
every camera model COLMAP has: a distorted one (SIMPLE_RADIAL, OPENCV, OPENCV_FISHEYE, ...) is kept
as a `Lens` and undistorted by the `ingest` stage (io/undistort.py). `read_colmap_model` is the
pinhole-only reading for models we wrote ourselves.
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


MODEL_FILES = ("cameras", "images", "points3D")


def is_model(path: Path) -> bool:
    """True when `path` holds a COLMAP model (cameras.bin or cameras.txt)."""
    return any((Path(path) / f"cameras.{ext}").is_file() for ext in ("bin", "txt"))


def model_files(path: Path) -> list[Path]:
    """The files of a COLMAP model folder that a reader reads (binary preferred, as pycolmap)."""
    path = Path(path)
    ext = "bin" if (path / "cameras.bin").is_file() else "txt"
    return [path / f"{f}.{ext}" for f in MODEL_FILES if (path / f"{f}.{ext}").is_file()]


def load_reconstruction(path: Path):
    """pycolmap.Reconstruction of a model folder, or InputError naming what is wrong."""
    import pycolmap

    path = Path(path)
    if not is_model(path):
        raise InputError(f"{path}: not a COLMAP model (no cameras.bin / cameras.txt)")
    if not (path / "cameras.bin").is_file():
        check_text_model(path)
    try:
        return pycolmap.Reconstruction(str(path))
    except Exception as e:  # pycolmap raises plain RuntimeError/ValueError for broken files
        raise InputError(f"{path}: cannot read COLMAP model ({str(e).splitlines()[0]})") from None


def read_colmap_capture(path: Path, image_dir: Path, fmt: str = "colmap"):
    """A COLMAP model folder as a `Capture`: registered images with their `Lens` (any model).

    `image_dir` is the folder the model's image names are relative to. An image of the model that
    is not there is an error (a model of another folder); images there that the model does not
    register are views without a pose (ingest says so; the poses stage drops them).
    """
    from ..errors import confined
    from .capture import Capture, Frame, lens_from_colmap_camera

    path, image_dir = Path(path), Path(image_dir)
    rec = load_reconstruction(path)
    frames = []
    for image in sorted(rec.images.values(), key=lambda im: im.name):
        if not image.has_pose:
            continue
        confined(image_dir, image.name, f"{path}: image {image.name!r}")
        T = np.eye(4)
        T[:3, :] = image.cam_from_world().matrix()
        try:
            lens = lens_from_colmap_camera(image.camera)
            Camera(np.eye(3), T, lens.width, lens.height)  # rotation / size checks, named below
        except (InputError, ValueError) as e:
            raise InputError(f"{path}: image {image.name}: {e}") from None
        frames.append(Frame(name=image.name, image=image_dir / image.name, cam_from_world=T,
                            lens=lens))
    if not frames:
        raise InputError(f"{path}: the COLMAP model registers no image (an empty or failed "
                         "reconstruction: rerun the mapper, or remove it to let SfM run)")
    missing = [f.name for f in frames if not f.image.is_file()]
    if missing:
        raise InputError(f"{path}: model refers to images not in {image_dir}: {missing[:5]}"
                         + (f" (+{len(missing) - 5} more)" if len(missing) > 5 else ""))
    return Capture(fmt, tuple(frames), sparse=path, files=tuple(model_files(path)))


def read_colmap_model(path: Path) -> dict[str, Camera]:
    """Read a pinhole COLMAP model folder into {image name: Camera}, registered images only."""
    path = Path(path)
    rec = load_reconstruction(path)
    out: dict[str, Camera] = {}
    for image in rec.images.values():
        if not image.has_pose:
            continue
        cam = image.camera
        if cam.model_name not in _PINHOLE_MODELS:
            raise InputError(f"{path}: camera {cam.camera_id} has model {cam.model_name}, "
                             f"expected {' or '.join(_PINHOLE_MODELS)}")
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


def undistort_reconstruction(rec) -> None:
    """Every camera of pycolmap reconstruction `rec` replaced, in place, by its undistorted pinhole
    (io/undistort.py) and every keypoint moved with it: what COLMAP's image_undistorter does to a
    model. 3D points do not move; the poses stage measures the scene scale from them."""
    from .capture import colmap_camera, lens_from_colmap_camera
    from .undistort import undistort_points, undistorted_lens

    lenses = {cid: lens_from_colmap_camera(c) for cid, c in rec.cameras.items()}
    new = {cid: undistorted_lens(lens) for cid, lens in lenses.items()}
    for image in rec.images.values():
        pts = image.points2D
        if len(pts) and lenses[image.camera_id].distorted:
            uv = np.array([p.xy for p in pts]) - 0.5
            moved = undistort_points(uv, lenses[image.camera_id], new[image.camera_id]) + 0.5
            for p, xy in zip(pts, moved):
                p.xy = xy
    for cid, lens in new.items():
        rec.cameras[cid] = colmap_camera(lens, camera_id=cid)


def write_undistorted_model(path: Path, out: Path) -> None:
    """The model at `path` undistorted (`undistort_reconstruction`), as a text model in `out`:
    what COLMAP's image_undistorter writes as sparse/."""
    rec = load_reconstruction(path)
    undistort_reconstruction(rec)
    Path(out).mkdir(parents=True, exist_ok=True)
    rec.write_text(str(out))
