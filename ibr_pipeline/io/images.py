"""Image and RGB-D depth files. Values follow scene.py: 8-bit images in the scene's encoding
(sRGB for photographs, linear for our synthetic scenes), read as linear [0, 1] floats; depth PNG
16-bit in millimetres (0 = no measurement, returned as 0.0 m).

`encoding` is the transfer function of the file: "srgb" files are decoded to linear on read and
linear arrays encoded on write (IEC 61966-2-1), so that everything computed in between (the layer
model I = I0 + beta I1 of Xu Eq. 3, fusion, blending) holds in linear radiance; "linear" files are
taken as they are. Masks, edge maps and other non-colour images are always "linear".

Every reader raises InputError naming the file for anything it cannot decode (truncated files,
wrong bit depth, wrong channel count), because that is what a user must fix.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from ..errors import InputError
from ..scene import DEPTH_PNG_SCALE
from ..workspace import atomic_path


def _too_large(path: Path, e: Exception) -> InputError:
    return InputError(f"{path}: image too large to decode ({e}); a corrupt header or a "
                      "decompression bomb: replace or downscale the file")


def _open(path: Path) -> Image.Image:
    try:
        im = Image.open(path)
        im.load()  # decode fully: truncated/corrupt files fail here, not later
        return im
    except FileNotFoundError:
        raise InputError(f"{path}: file not found") from None
    except Image.DecompressionBombError as e:  # not an OSError: PIL's guard against huge headers
        raise _too_large(path, e) from None
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as e:
        raise InputError(f"{path}: cannot decode image ({e})") from None


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) from the header, without decoding pixels."""
    try:
        with Image.open(path) as im:
            return im.size
    except FileNotFoundError:
        raise InputError(f"{path}: file not found") from None
    except Image.DecompressionBombError as e:
        raise _too_large(path, e) from None
    except (UnidentifiedImageError, OSError) as e:
        raise InputError(f"{path}: cannot read image header ({e})") from None


ENCODINGS = ("srgb", "linear")
# zlib level of every PNG written: lossless at any level; level 1 encodes several times faster
# than PIL's default 6 for somewhat larger files, and the pipeline writes thousands of renders,
# layers and depth maps (docs/BENCHMARKS.md, `make demo-full`, session 36)
PNG_COMPRESS_LEVEL = 1


def _check_encoding(encoding: str) -> None:
    if encoding not in ENCODINGS:
        raise ValueError(f"encoding must be one of {ENCODINGS}, got {encoding!r}")


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """sRGB-encoded [0, 1] -> linear [0, 1] (IEC 61966-2-1)."""
    x = np.clip(np.asarray(x, dtype=np.float32), 0.0, 1.0)
    return np.where(x <= 0.04045, x / 12.92, np.power((x + 0.055) / 1.055, 2.4)).astype(np.float32)


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """Linear [0, 1] -> sRGB-encoded [0, 1] (IEC 61966-2-1)."""
    x = np.clip(np.asarray(x, dtype=np.float32), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055).astype(np.float32)


def decode(image: np.ndarray, encoding: str) -> np.ndarray:
    """Stored values in `encoding` -> linear floats."""
    _check_encoding(encoding)
    return srgb_to_linear(image) if encoding == "srgb" else np.asarray(image, dtype=np.float32)


def encode(image: np.ndarray, encoding: str) -> np.ndarray:
    """Linear floats -> values to store in `encoding`."""
    _check_encoding(encoding)
    return linear_to_srgb(image) if encoding == "srgb" else np.asarray(image, dtype=np.float32)


def read_image(path: Path, encoding: str = "linear") -> np.ndarray:
    """(H, W, 3) float32 RGB in [0, 1], linear (decoded from `encoding`). Grey images are
    expanded; alpha is dropped."""
    _check_encoding(encoding)
    im = _open(Path(path))
    if im.mode not in ("RGB", "RGBA", "L", "P", "LA"):
        raise InputError(f"{path}: unsupported image mode {im.mode} (need 8-bit RGB or grey)")
    return decode(np.asarray(im.convert("RGB"), dtype=np.float32) / 255.0, encoding)


def to_uint8(image: np.ndarray) -> np.ndarray:
    arr = np.asarray(image)
    if arr.dtype == np.uint8:
        return arr
    return np.clip(np.rint(np.nan_to_num(arr) * 255.0), 0, 255).astype(np.uint8)


def write_image(path: Path, image: np.ndarray, encoding: str = "linear") -> None:
    """Write (H, W, 3) or (H, W) linear floats in [0, 1] (or uint8, written as given) as 8-bit PNG
    in `encoding`, atomically."""
    _check_encoding(encoding)
    if encoding == "srgb" and np.asarray(image).dtype != np.uint8:
        image = linear_to_srgb(image)
    arr = to_uint8(image)
    if arr.ndim not in (2, 3) or (arr.ndim == 3 and arr.shape[2] not in (3, 4)):
        raise ValueError(f"image must be (H, W), (H, W, 3) or (H, W, 4), got {arr.shape}")
    with atomic_path(Path(path)) as tmp:
        Image.fromarray(arr).save(tmp, format="PNG", compress_level=PNG_COMPRESS_LEVEL)


def read_depth_png(path: Path) -> np.ndarray:
    """(H, W) float32 depth in metres from a 16-bit mm PNG; 0 where there is no measurement."""
    im = _open(Path(path))
    arr = np.asarray(im)
    if arr.ndim != 2 or arr.dtype not in (np.uint16, np.int32, np.uint8) or im.mode not in (
            "I;16", "I;16B", "I;16L", "I"):
        raise InputError(f"{path}: depth must be a single-channel 16-bit PNG in mm, got mode {im.mode}")
    if arr.dtype == np.int32 and (arr.min() < 0 or arr.max() > 65535):
        raise InputError(f"{path}: depth values outside the 16-bit range")
    return arr.astype(np.float32) / DEPTH_PNG_SCALE


def write_depth_png(path: Path, depth_m: np.ndarray) -> None:
    """Write metres as 16-bit mm PNG; NaN, inf, <= 0 and > 65.535 m become 0 (no measurement)."""
    d = np.asarray(depth_m, dtype=np.float64)
    if d.ndim != 2:
        raise ValueError(f"depth must be (H, W), got {d.shape}")
    mm = np.where(np.isfinite(d) & (d > 0), np.rint(d * DEPTH_PNG_SCALE), 0)
    mm = np.where(mm > 65535, 0, mm).astype(np.uint16)
    with atomic_path(Path(path)) as tmp:
        Image.fromarray(mm).save(tmp, format="PNG", compress_level=PNG_COMPRESS_LEVEL)
