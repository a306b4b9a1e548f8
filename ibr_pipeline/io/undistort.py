"""Undistortion of images, depth frames and keypoints to a pinhole camera, with pycolmap's models.

Every stage after `ingest` assumes straight projection (scene.py), so a distorted capture is
resampled once, at ingest, onto the pinhole camera COLMAP's `image_undistorter` would choose
(`pycolmap.undistort_camera`: the largest pinhole view without blank pixels). The maps are built
from pycolmap's own camera models (`cam_from_img` / `img_from_cam`, every COLMAP model) and
applied with OpenCV's `remap`: bilinear for colour, nearest for depth (interpolating across a depth
edge would invent surfaces). pycolmap's `undistort_image` does the colour part alone; we build the
map ourselves because depth frames and SfM keypoints need the same mapping.

Pixel conventions: `Lens` and pycolmap use COLMAP's (top-left pixel centre at (0.5, 0.5)); the
arrays here use ours (scene.py, (0, 0)).
"""
from __future__ import annotations

import numpy as np

from .capture import Lens, colmap_camera, lens_from_colmap_camera


def undistorted_lens(lens: Lens) -> Lens:
    """The pinhole lens COLMAP's image_undistorter gives `lens` (no blank pixels, same scale)."""
    import pycolmap
    if not lens.distorted:
        return Lens.from_K(lens.pinhole_K(), lens.width, lens.height)
    out = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(), colmap_camera(lens))
    return lens_from_colmap_camera(out)


def scaled_lens(lens: Lens, width: int, height: int) -> Lens:
    """`lens` at another resolution (a depth sensor's smaller frame of the same field of view)."""
    cam = colmap_camera(lens)
    cam.rescale(int(width), int(height))
    return lens_from_colmap_camera(cam)


def source_pixels(src: Lens, dst: Lens) -> np.ndarray:
    """(H_dst, W_dst, 2) float32: for every pixel of `dst`, where its ray meets `src`'s image
    (our pixel convention). Rays behind `src` get -1 (outside the image)."""
    u, v = np.meshgrid(np.arange(dst.width, dtype=np.float64), np.arange(dst.height, dtype=np.float64))
    uv = np.stack([u.ravel() + 0.5, v.ravel() + 0.5], axis=1)
    xy = colmap_camera(dst).cam_from_img(uv)
    rays = np.c_[xy, np.ones(len(xy))]
    out = colmap_camera(src).img_from_cam(rays, check_cheirality=False)
    out = np.asarray(out, dtype=np.float64) - 0.5
    out[~np.all(np.isfinite(out), axis=1)] = -1.0
    return out.reshape(dst.height, dst.width, 2).astype(np.float32)


def resample(image: np.ndarray, src: Lens, dst: Lens, nearest: bool = False) -> np.ndarray:
    """`image` (taken with `src`, H_src x W_src [x C]) as `dst` would have seen it."""
    import cv2
    img = np.asarray(image)
    if img.shape[:2] != (src.height, src.width):
        raise ValueError(f"image is {img.shape[1]}x{img.shape[0]}, its lens says {src.width}x{src.height}")
    m = source_pixels(src, dst)
    interp = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
    return cv2.remap(img, m[..., 0], m[..., 1], interp, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def undistort_points(uv: np.ndarray, src: Lens, dst: Lens) -> np.ndarray:
    """(N, 2) pixels of `src` (our convention) -> the same rays' pixels in `dst`."""
    uv = np.asarray(uv, dtype=np.float64)
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise ValueError(f"uv must be (N, 2), got {uv.shape}")
    if len(uv) == 0:
        return uv.copy()
    xy = colmap_camera(src).cam_from_img(uv + 0.5)
    out = colmap_camera(dst).img_from_cam(np.c_[xy, np.ones(len(xy))], check_cheirality=False)
    return np.asarray(out, dtype=np.float64) - 0.5
