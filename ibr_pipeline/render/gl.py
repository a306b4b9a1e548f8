"""The OpenGL context: moderngl, standalone, headless EGL — ONE per process, created on first use.

On a CPU-only machine EGL gives Mesa's llvmpipe; on an NVIDIA machine the same code gets the
NVIDIA driver. `IBR_GL_BACKEND` (env) overrides the backend ("egl" by default; "" = moderngl's
platform default). Nothing here is imported at package import time (moderngl is loaded lazily).

Camera → GL conventions: OpenCV intrinsics with pixel centre (0, 0); clip-space x = (u + 0.5)·2/W − 1,
y = (v + 0.5)·2/H − 1, so image row v is framebuffer row v and a read-back array is in image order
(no flip). Triangles are not culled (per-view meshes have no consistent winding from every view).
"""
from __future__ import annotations

import os
import threading

import numpy as np

from ..scene import Camera

NEAR_M = 0.02   # near clipping plane (metres)
FAR_M = 1000.0  # far clipping plane (metres)

_lock = threading.Lock()
_ctx = None


def get_context():
    """The process's moderngl context (created once, then reused)."""
    global _ctx
    with _lock:
        if _ctx is None:
            import moderngl

            backend = os.environ.get("IBR_GL_BACKEND", "egl")
            kwargs = {"backend": backend} if backend else {}
            try:
                _ctx = moderngl.create_standalone_context(require=330, **kwargs)
            except Exception as e:  # no EGL/GL driver: say which system libraries are needed
                raise RuntimeError(
                    f"cannot create an OpenGL 3.3 context (backend {backend or 'default'}): {e}. "
                    "Headless rendering needs EGL: apt-get install libegl1 libegl-mesa0 "
                    "libgl1-mesa-dri libgbm1") from e
        return _ctx


def renderer_name() -> str:
    ctx = get_context()
    return f"{ctx.info.get('GL_RENDERER', '?')} ({ctx.info.get('GL_VERSION', '?')})"


def projection(camera: Camera, near: float = NEAR_M, far: float = FAR_M) -> np.ndarray:
    """4x4 world → clip matrix of an OpenCV camera (see module docstring for the axes)."""
    K, W, H = camera.K, camera.width, camera.height
    P = np.zeros((4, 4))
    P[0, 0] = 2 * K[0, 0] / W
    P[0, 1] = 2 * K[0, 1] / W
    P[0, 2] = (2 * K[0, 2] + 1) / W - 1
    P[1, 1] = 2 * K[1, 1] / H
    P[1, 2] = (2 * K[1, 2] + 1) / H - 1
    P[2, 2] = (far + near) / (far - near)
    P[2, 3] = -2 * far * near / (far - near)
    P[3, 2] = 1.0
    return P @ camera.cam_from_world


def source_matrix(camera: Camera) -> np.ndarray:
    """4x4 world → (u·z, v·z, z, 1) of a source camera (projective texturing)."""
    S = np.eye(4)
    S[:3, :4] = camera.K @ camera.cam_from_world[:3, :4]
    return S


def mat_bytes(m: np.ndarray) -> bytes:
    """A numpy 4x4 (row-major) as a GLSL mat4 uniform (column-major float32)."""
    m = np.asarray(m, dtype=np.float64)
    if m.shape != (4, 4):
        raise ValueError(f"expected a 4x4 matrix, got {m.shape}")
    return np.ascontiguousarray(m.T, dtype="f4").tobytes()


def float_target(size: tuple[int, int], components: int = 4):
    """A float32 texture usable as a render target (NEAREST sampling, for texelFetch)."""
    import moderngl

    ctx = get_context()
    tex = ctx.texture(size, components, dtype="f4")
    tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
    return tex


def read_float(fbo, attachment: int, box, components: int = 4) -> np.ndarray:
    """Read a float attachment back as an (h, w, C) array in image row order; `box` is the size
    (W, H) of the whole target or a sub-rectangle (x, y, w, h)."""
    x, y, w, h = (0, 0, *box) if len(box) == 2 else box
    out = np.empty((h, w, components), np.float32)  # written in place: no bytes object to copy
    fbo.read_into(out, viewport=(x, y, w, h), attachment=attachment, components=components,
                  dtype="f4")
    return out


def upload_texture(image: np.ndarray):
    """(H, W, C) float [0, 1] (C = 1..4) → a bilinear float16 texture (row 0 = image row 0).

    float16 rather than 8 bits so that small decayed weights in the alpha survive."""
    import moderngl

    arr = np.asarray(image, dtype=np.float32)
    if arr.ndim == 2:
        arr = arr[..., None]
    if arr.ndim != 3 or arr.shape[2] not in (1, 2, 3, 4):
        raise ValueError(f"texture image must be (H, W) or (H, W, 1..4), got {arr.shape}")
    h, w, c = arr.shape
    tex = get_context().texture((w, h), c, np.ascontiguousarray(arr, dtype=np.float16).tobytes(),
                                dtype="f2")
    tex.filter = (moderngl.LINEAR, moderngl.LINEAR)
    tex.repeat_x = tex.repeat_y = False
    return tex
