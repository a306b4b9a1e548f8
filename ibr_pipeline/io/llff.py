"""LLFF's `poses_bounds.npy` (Mildenhall et al. 2019; the NeRF "forward-facing" scenes).

`poses_bounds.npy` is an N x 17 float array, one row per image of `images/` in sorted file-name
order (LLFF's imgs2poses.py sorts COLMAP's images by name; NeRF's load_llff.py pairs rows with
`sorted(os.listdir(images))`). A row is a 3x5 matrix, row-major, then two depths:

    [ R | t | hwf ]  near far

R's columns are the camera's *down, right, backwards* axes in world coordinates (LLFF's
"[down, right, back]"; imgs2poses.py builds it from COLMAP's OpenCV camera-to-world as
[y, x, -z], and NeRF's loader turns it into OpenGL's [right, up, back] with
[:, 1], -[:, 0], [:, 2]). t is the camera centre, hwf = (H, W, focal) of the images the poses were
made for; the principal point is assumed to be the image centre, pixels square. near/far bound the
scene depth seen from each camera. Units are COLMAP's (arbitrary scale).

Ours (scene.py): OpenCV world-to-camera, so R_cv's columns are [right, down, forward] =
[R[:, 1], R[:, 0], -R[:, 2]], inverted.

NeX's variant (Wizadwongsa et al. 2021, its "shiny" and repackaged LLFF scenes): N x 14 rows (the
3x4 [R | t] alone, same axes) and the intrinsics in `hwf_cxcy.npy` = (H, W, fx, fy, cx, cy), the
principal point as COLMAP gives it (NeX's data come from COLMAP through imgs2poses.py).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from ..scene import IMAGE_EXTENSIONS, Camera
from .capture import Capture, Frame, Lens
from .nerfstudio import cam_from_c2w

FORMAT = "llff"
POSES_FILE = "poses_bounds.npy"
NEX_INTRINSICS = "hwf_cxcy.npy"
_ASPECT_TOL = 0.01  # relative aspect-ratio difference between hwf and images/ that is refused


def _llff_to_c2w_cv(P: np.ndarray) -> np.ndarray:
    """OpenCV camera-to-world 3x4 from a 3x5 LLFF pose: columns [down, right, back] -> [x, y, z]."""
    return np.stack([P[:, 1], P[:, 0], -P[:, 2], P[:, 3]], axis=1)


def image_files(folder: Path) -> list[Path]:
    """The images LLFF pairs with rows: files of `folder` (not sub-folders), sorted by name."""
    return sorted((p for p in folder.iterdir() if p.is_file() and not p.name.startswith(".")
                   and p.suffix.lower() in IMAGE_EXTENSIONS), key=lambda p: p.name)


def _load(path: Path) -> np.ndarray:
    if not path.is_file():
        raise InputError(f"{path}: file not found")
    try:
        arr = np.load(path, allow_pickle=False)  # never unpickle an input file
    except (ValueError, OSError, EOFError) as e:
        raise InputError(f"{path}: not a readable .npy array ({e})") from None
    if not isinstance(arr, np.ndarray) or arr.dtype.kind not in "fiu":
        raise InputError(f"{path}: expected an N x 17 float array, got "
                         f"{getattr(arr, 'dtype', type(arr).__name__)}")
    nex = arr.ndim == 2 and arr.shape[1] == 14 and (path.parent / NEX_INTRINSICS).is_file()
    if arr.ndim != 2 or arr.shape[1] != (14 if nex else 17) or arr.shape[0] == 0:
        raise InputError(f"{path}: expected an N x 17 array (3x5 pose + near, far per image), "
                         f"or N x 14 with {NEX_INTRINSICS} beside it (NeX), got shape {arr.shape}")
    arr = arr.astype(np.float64)
    bad = np.flatnonzero(~np.all(np.isfinite(arr), axis=1))
    if bad.size:
        raise InputError(f"{path}: row {bad[0]} contains NaN or infinite values")
    return arr


def _nex_rows(root: Path, arr: np.ndarray) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """NeX's N x 14 rows as LLFF's N x 17 (hwf from hwf_cxcy.npy), and its (fx, fy, cx, cy)."""
    path = root / NEX_INTRINSICS
    try:
        k = np.load(path, allow_pickle=False).astype(np.float64).ravel()
    except (ValueError, OSError, EOFError) as e:
        raise InputError(f"{path}: not a readable .npy array ({e})") from None
    if k.shape != (6,) or not np.all(np.isfinite(k)) or not np.all(k[:4] > 0):
        raise InputError(f"{path}: expected 6 finite numbers H, W, fx, fy, cx, cy (H, W, fx, fy "
                         f"> 0), got {k.tolist()[:8]}")
    H, W, fx, fy, cx, cy = k
    P = arr[:, :12].reshape(-1, 3, 4)
    hwf = np.tile(np.array([H, W, fx])[None, :, None], (len(arr), 1, 1))
    full = np.concatenate([np.concatenate([P, hwf], axis=2).reshape(len(arr), 15), arr[:, 12:]], 1)
    return full, (fx, fy, cx, cy)


def read_poses_bounds(root: Path) -> Capture:
    """Read an LLFF folder (`poses_bounds.npy` + `images/`, or NeX's N x 14 + hwf_cxcy.npy) into
    a Capture."""
    from .images import image_size

    root = Path(root)
    path = root / POSES_FILE
    arr = _load(path)
    nex = None
    if arr.shape[1] == 14:
        arr, nex = _nex_rows(root, arr)
    img_dir = root / "images"
    if not img_dir.is_dir():
        raise InputError(f"{root}: LLFF input needs an images/ folder beside {POSES_FILE}")
    images = image_files(img_dir)
    if len(images) != len(arr):
        raise InputError(f"{path}: {len(arr)} poses but {len(images)} images in {img_dir}; LLFF "
                         "pairs rows with the sorted image files, so the counts must match")

    frames = []
    rescaled: dict[tuple, float] = {}
    for i, (row, image) in enumerate(zip(arr, images)):
        where = f"{path}: row {i} ({image.name})"
        P = row[:15].reshape(3, 5)
        H, W, focal = P[:, 4]
        if not (H > 0 and W > 0 and focal > 0):
            raise InputError(f"{where}: H, W, focal must be > 0, got {H}, {W}, {focal}")
        w, h = image_size(image)
        if (w, h) != (W, H):
            # the poses were made for other-sized images (LLFF's images_4/ etc.): same field of
            # view if the aspect matches, so the focal scales with the width (as load_llff.py does)
            if abs((w / h) / (W / H) - 1) > _ASPECT_TOL:
                raise InputError(f"{where}: poses are for {W:g}x{H:g} images but {image} is {w}x{h}, "
                                 "another aspect ratio: not the images the poses were made for")
            s = w / W
            focal *= s
            rescaled[(W, H, w, h)] = s
        T = cam_from_c2w(_llff_to_c2w_cv(P), where)
        if nex is None:
            # LLFF assumes the principal point at the image centre: (W/2, H/2) in COLMAP's convention
            lens = Lens("PINHOLE", (focal, focal, w / 2, h / 2), w, h)
        else:  # NeX gives both focals and the principal point, for W x H: scale them alike
            s = w / W
            lens = Lens("PINHOLE", (nex[0] * s, nex[1] * s, nex[2] * s, nex[3] * s), w, h)
        frames.append(Frame(name=image.name, image=image, cam_from_world=T, lens=lens))

    near, far = arr[:, 15], arr[:, 16]
    notes = [f"{POSES_FILE}: {len(frames)} poses paired with sorted images/; "
             f"bounds near {near.min():.6g}, far {far.max():.6g}"]
    for (W, H, w, h), s in sorted(rescaled.items()):
        notes.append(f"{POSES_FILE}: poses are for {W:g}x{H:g} images, images/ holds {w}x{h}: "
                     f"focal scaled by {s:.6g}")
    if nex is not None:
        notes.append(f"{POSES_FILE}: NeX layout (N x 14 rows), intrinsics from {NEX_INTRINSICS}")
    files = (path, *images) + ((root / NEX_INTRINSICS,) if nex is not None else ())
    return Capture(format=FORMAT, frames=tuple(frames), files=files, notes=tuple(notes))


def write_poses_bounds(cameras: dict[str, Camera], path: Path,
                       near_far: tuple[float, float] = (0.5, 10.0)) -> None:
    """Write {image name: Camera} as poses_bounds.npy, rows in sorted-name order (for fixtures).

    LLFF stores one focal and no principal point: cameras need square pixels and a centred
    principal point ((W-1)/2, (H-1)/2 in our convention), else ValueError.
    """
    from ..workspace import atomic_path

    if not cameras:
        raise ValueError("write_poses_bounds: no cameras")
    near, far = (float(v) for v in near_far)
    if not (np.isfinite(near) and np.isfinite(far) and 0 < near < far):
        raise ValueError(f"near_far must be 0 < near < far, got {near_far}")
    rows = []
    for name in sorted(cameras):
        cam = cameras[name]
        K, w, h = cam.K, cam.width, cam.height
        if abs(K[0, 0] - K[1, 1]) > 1e-6 * K[0, 0] or K[0, 1] != 0:
            raise ValueError(f"camera {name!r}: fx {K[0, 0]} != fy {K[1, 1]} (or skew): "
                             "LLFF has square pixels")
        if abs(K[0, 2] - (w - 1) / 2) > 1e-6 or abs(K[1, 2] - (h - 1) / 2) > 1e-6:
            raise ValueError(f"camera {name!r}: principal point ({K[0, 2]}, {K[1, 2]}) is not the "
                             f"image centre ({(w - 1) / 2}, {(h - 1) / 2}): LLFF cannot store it")
        c2w = cam.world_from_cam
        x, y, z, t = c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3]
        P = np.stack([y, x, -z, t, [h, w, K[0, 0]]], axis=1)  # [down, right, back | t | hwf]
        rows.append(np.concatenate([P.ravel(), [near, far]]))
    with atomic_path(Path(path)) as tmp:
        np.save(tmp, np.asarray(rows, dtype=np.float64))
