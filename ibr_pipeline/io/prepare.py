"""What the `ingest` stage does to one frame so that every later stage reads a pinhole, upright,
8-bit image and a 16-bit millimetre depth frame (scene.py), whatever the capture's format.

`plan` decides from headers alone; `prepare` converts. A frame that needs nothing is read in place
from the input folder. Conversions, each for a reason the later stages cannot absorb:
- a distorted lens -> undistorted onto COLMAP's pinhole choice (io/undistort.py), with its depth;
- an EXIF orientation other than 1 -> turned upright (PIL's `exif_transpose`), unless the frame's
  camera was made for the stored pixels (COLMAP reads pixels as stored, so a model computed from
  the same files says which);
- depth in another unit (TUM: 5000 per metre) or from a sensor with its own intrinsics (ScanNet)
  -> resampled onto the colour camera scaled to the depth frame's size, in millimetres.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..scene import DEPTH_PNG_SCALE, Camera
from .capture import Frame, Lens

EXIF_ORIENTATION = 0x0112


@dataclass(frozen=True)
class Plan:
    """What a frame needs: `rotate` (EXIF), `undistort`, `depth` (rewrite the depth frame)."""

    rotate: bool
    undistort: bool
    depth: bool

    @property
    def image(self) -> bool:
        return self.rotate or self.undistort


def exif_orientation(path: Path) -> int:
    from PIL import Image
    try:
        with Image.open(path) as im:
            return int(im.getexif().get(EXIF_ORIENTATION, 1) or 1)
    except (OSError, ValueError, TypeError):
        return 1  # unreadable headers are reported by the pixel check, with the file's name


def plan(frame: Frame, size: tuple[int, int], orientation: int) -> Plan:
    """`size` = the stored pixels' (width, height); `orientation` its EXIF tag (1 = upright)."""
    turned = orientation in (5, 6, 7, 8)  # these swap width and height
    upright = (size[1], size[0]) if turned else size
    if frame.lens is None:
        rotate = orientation != 1
    elif (frame.lens.width, frame.lens.height) == size:
        rotate = False  # the camera describes the stored pixels
    else:
        rotate = orientation != 1 and (frame.lens.width, frame.lens.height) == upright
    undistort = frame.lens is not None and frame.lens.distorted
    depth = frame.depth is not None and (undistort or frame.depth_lens is not None
                                         or frame.depth_units_per_m != DEPTH_PNG_SCALE)
    return Plan(rotate, undistort, depth)


def _read_rgb8(path: Path, rotate: bool) -> np.ndarray:
    from PIL import ImageOps
    from .images import _open
    im = _open(Path(path))
    if rotate:
        im = ImageOps.exif_transpose(im)
    if im.mode not in ("RGB", "RGBA", "L", "P", "LA"):
        raise InputError(f"{path}: unsupported image mode {im.mode} (need 8-bit RGB or grey)")
    return np.asarray(im.convert("RGB"))


def prepare(frame: Frame, p: Plan, out_image: Path | None, out_depth: Path | None) -> Camera | None:
    """Write what `p` says into `out_image` / `out_depth`; return the frame's pinhole camera
    (None without a pose)."""
    from .images import read_depth_png, write_depth_png, write_image
    from .undistort import resample, scaled_lens, undistorted_lens

    lens = frame.lens
    out_lens = None if lens is None else (undistorted_lens(lens) if p.undistort else lens)
    if p.image:
        img = _read_rgb8(frame.image, p.rotate)
        if p.undistort:
            if img.shape[:2] != (lens.height, lens.width):
                raise InputError(f"{frame.image}: image is {img.shape[1]}x{img.shape[0]} but its "
                                 f"camera says {lens.width}x{lens.height}")
            img = resample(img, lens, out_lens)
        write_image(out_image, img)
    if p.depth:
        d = read_depth_png(frame.depth) * (DEPTH_PNG_SCALE / frame.depth_units_per_m)
        dh, dw = d.shape
        if lens is None:
            raise InputError(f"{frame.depth}: a depth frame to convert needs its colour camera's "
                             "intrinsics")
        src = frame.depth_lens or scaled_lens(lens, dw, dh)
        if (src.width, src.height) != (dw, dh):
            raise InputError(f"{frame.depth}: depth is {dw}x{dh} but its intrinsics say "
                             f"{src.width}x{src.height}")
        # the depth frame keeps its own resolution, on the colour camera's field of view
        scale = dw / lens.width
        tw, th = max(1, round(out_lens.width * scale)), max(1, round(out_lens.height * scale))
        dst = scaled_lens(Lens.from_K(out_lens.pinhole_K(), out_lens.width, out_lens.height), tw, th)
        d = resample(d.astype(np.float32), src, dst, nearest=True)
        write_depth_png(out_depth, d)
    if frame.cam_from_world is None or out_lens is None:
        return None
    return Camera(out_lens.pinhole_K(), frame.cam_from_world, out_lens.width, out_lens.height)
