"""Applications of one ray tree (Lochmann et al. 2014, Fig. 10 and §1): a stereo pair, depth of
field and motion blur, each synthesised by warping the same decoded tree to several cameras.

The tree is decoded once (§3.3) and warped per camera (§3.4-3.5); depth of field averages the
warps from sample positions on a thin-lens aperture whose principal points are shifted so that
the focal plane stays fixed; motion blur averages warps along the camera path (translation
interpolated linearly, rotation by slerp).
"""
from __future__ import annotations

import numpy as np

from ..scene import Camera
from .decode import Decoded
from .warp import WarpOptions, naive_warp, warp_decoded


def _warp(dec: Decoded, cam: Camera, options: WarpOptions | None, naive: bool) -> np.ndarray:
    return naive_warp(dec, cam, options) if naive else warp_decoded(dec, cam, options).image


def offset_camera(cam: Camera, offset_cam: np.ndarray, focus_depth: float | None = None) -> Camera:
    """`cam` moved by `offset_cam` (3,) metres in its own axes; with `focus_depth` the principal
    point is shifted so that points at that z-depth keep their pixel (thin-lens aperture sample:
    c' = c + f * o / z_focus)."""
    o = np.asarray(offset_cam, np.float64)
    if o.shape != (3,):
        raise ValueError(f"offset must be (3,), got {o.shape}")
    T = cam.cam_from_world.copy()
    T[:3, 3] = cam.t - o  # centre moves by R^T o in world coordinates
    K = cam.K.copy()
    if focus_depth is not None:
        if focus_depth <= 0:
            raise ValueError(f"focus_depth must be > 0, got {focus_depth}")
        K[0, 2] += K[0, 0] * o[0] / focus_depth
        K[1, 2] += K[1, 1] * o[1] / focus_depth
    return Camera(K, T, cam.width, cam.height)


def stereo_pair(dec: Decoded, cam: Camera, baseline: float = 0.064, options: WarpOptions | None = None,
                naive: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(left, right) images for eyes at -/+ baseline/2 along the camera's x axis."""
    return tuple(_warp(dec, offset_camera(cam, np.array([s * baseline / 2, 0, 0])), options, naive)
                 for s in (-1, 1))


def lens_samples(n: int) -> np.ndarray:
    """n points on the unit disk (Vogel / golden-angle spiral): even coverage, deterministic."""
    k = np.arange(n) + 0.5
    r = np.sqrt(k / n)
    a = k * np.pi * (3 - np.sqrt(5))
    return np.stack([r * np.cos(a), r * np.sin(a)], 1)


def depth_of_field(dec: Decoded, cam: Camera, aperture: float = 0.02, focus_depth: float = 2.0,
                   samples: int = 16, options: WarpOptions | None = None, naive: bool = False) -> np.ndarray:
    """Thin-lens depth of field: mean of the warps from `samples` points on an aperture of
    radius `aperture` metres, focused at z-depth `focus_depth` metres."""
    if samples < 1 or aperture < 0:
        raise ValueError(f"need samples >= 1 and aperture >= 0, got {samples}, {aperture}")
    acc = None
    for x, y in lens_samples(samples) * aperture:
        img = _warp(dec, offset_camera(cam, np.array([x, y, 0.0]), focus_depth), options, naive)
        acc = img if acc is None else acc + img
    return acc / samples


def interpolate_cameras(a: Camera, b: Camera, t: float) -> Camera:
    """Camera at fraction t in [0, 1] from a to b (linear centre, slerp rotation, K of a)."""
    from scipy.spatial.transform import Rotation, Slerp
    rots = Rotation.from_matrix(np.stack([a.R, b.R]))
    R = Slerp([0.0, 1.0], rots)([t]).as_matrix()[0]
    c = (1 - t) * a.center + t * b.center
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ c
    return Camera(a.K, T, a.width, a.height)


def motion_blur(dec: Decoded, start: Camera, end: Camera, samples: int = 8,
                options: WarpOptions | None = None, naive: bool = False) -> np.ndarray:
    """Mean of the warps to `samples` cameras evenly spaced from `start` to `end` (shutter)."""
    if samples < 1:
        raise ValueError(f"samples must be >= 1, got {samples}")
    ts = [0.5] if samples == 1 else np.linspace(0, 1, samples)
    acc = None
    for t in ts:
        img = _warp(dec, interpolate_cameras(start, end, float(t)), options, naive)
        acc = img if acc is None else acc + img
    return acc / len(ts)
