"""Videos (MP4 through imageio-ffmpeg) and camera paths.

Frames are our linear renders; a video is for people, so frames are encoded to sRGB for display
(`to_display`). Writes are atomic (temporary name in the same folder, then rename).
"""
from __future__ import annotations

from pathlib import Path
from typing import Iterable

import numpy as np

from ..scene import Camera
from ..workspace import atomic_path


def to_display(linear: np.ndarray) -> np.ndarray:
    """Linear [0, 1] → sRGB-encoded uint8 (IEC 61966-2-1), for viewing only."""
    x = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    s = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.clip(np.rint(s * 255.0), 0, 255).astype(np.uint8)


def write_mp4(path: Path, frames: Iterable[np.ndarray], fps: float = 24.0,
              linear: bool = True) -> int:
    """Write (H, W, 3) frames (linear floats, or uint8 when linear=False) as H.264 MP4; returns the
    number of frames. yuv420p needs even sizes: imageio resizes odd ones up by one pixel."""
    import imageio.v2 as imageio

    n = 0
    with atomic_path(Path(path)) as tmp:
        writer = imageio.get_writer(str(tmp), format="FFMPEG", mode="I", fps=fps, codec="libx264",
                                    quality=8, macro_block_size=2, pixelformat="yuv420p",
                                    ffmpeg_log_level="error")
        try:
            for f in frames:
                arr = to_display(f) if linear else np.asarray(f, dtype=np.uint8)
                if arr.ndim != 3 or arr.shape[2] != 3:
                    raise ValueError(f"video frames must be (H, W, 3), got {arr.shape}")
                writer.append_data(arr)
                n += 1
        finally:
            writer.close()
        if n == 0:
            raise ValueError(f"{path}: no frames to write")
    return n


def interpolate_path(cameras: list[Camera], frames: int) -> list[Camera]:
    """A smooth fly-through along a sequence of cameras (for inputs without a given path):
    positions by a periodic-free cubic spline through the centres, rotations by slerp; the
    intrinsics and size of the first camera."""
    from scipy.interpolate import CubicSpline
    from scipy.spatial.transform import Rotation, Slerp

    if len(cameras) < 2 or frames < 2:
        raise ValueError(f"need >= 2 cameras and >= 2 frames, got {len(cameras)}, {frames}")
    key_t = np.arange(len(cameras), dtype=np.float64)
    centres = np.array([c.center for c in cameras])
    rots = Rotation.from_matrix(np.array([c.R for c in cameras]))
    spline = CubicSpline(key_t, centres, axis=0)
    slerp = Slerp(key_t, rots)
    ts = np.linspace(0, len(cameras) - 1, frames)
    out = []
    ref = cameras[0]
    for t, R in zip(ts, slerp(ts).as_matrix()):
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = -R @ spline(t)
        out.append(Camera(ref.K, T, ref.width, ref.height))
    return out
