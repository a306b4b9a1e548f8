"""RGBZ ray-tree output for Lochmann et al. 2014 (§3.2 "Encoding").

For one camera the tree has three nodes, each an RGB image plus a Z channel:
  D (diffuse / root): radiance of the first surface's own (diffuse) shading; Z = z-depth to the
      camera (an ordinary depth image, our convention).
  R (reflective):     radiance arriving along the reflected ray, pre-multiplied by the
      view-independent reflectance kr (mirror 1, chrome 0.85, glossy coat) but NOT by Fresnel;
      Z = distance from the parent (first) hit to the reflected hit, i.e. depth relative to the
      parent node (w_r = w_d + Z r, Lochmann Eq. 1).
  T (refractive):     radiance arriving along the refracted / transmitted ray, pre-multiplied by
      the filter colour (tint) but not by Fresnel; Z = distance from the parent hit.
Plus the validity bit mask (bit 0 D, bit 1 R, bit 2 T), the per-pixel index of refraction (0 where
there is no refractive node), the per-pixel Fresnel model code (materials.FRESNEL_*), the exact
first-hit normal, and the camera matrices (K, cam_from_world; OpenCV conventions).
Compositing with Fresnel F (recomputed from the view direction, normal and IOR):
  I = D + R                       where code == FRESNEL_NONE (mirror, glossy)
  I = D + F R + (1 - F) T         otherwise (dielectric interface / thin pane)
which reproduces the full render (`composite_ray_tree`).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..scene import Camera
from .materials import FRESNEL_NONE, fresnel_weight

BIT_D, BIT_R, BIT_T = 1, 2, 4


def ray_tree_from_render(render: dict[str, np.ndarray], camera: Camera) -> dict[str, np.ndarray]:
    """Ray-tree nodes (float32 / small ints) from a `Tracer.trace` result of `camera`."""
    kind = render["kind"]
    hit = kind >= 0
    has_r = (kind >= 1) & (render["R_range"] > 0)
    has_t = (kind >= 3) & (render["T_range"] > 0)
    valid = (hit * BIT_D + has_r * BIT_R + has_t * BIT_T).astype(np.uint8)
    return {
        "D": render["D"].astype(np.float16), "D_z": render["depth"].astype(np.float32),
        "R": np.where(has_r[..., None], render["kr"][..., None] * render["R"], 0).astype(np.float16),
        "R_z": np.where(has_r, render["R_range"], 0).astype(np.float32),
        "T": np.where(has_t[..., None], render["T"], 0).astype(np.float16),
        "T_z": np.where(has_t, render["T_range"], 0).astype(np.float32),
        "valid": valid, "ior": np.where(kind >= 3, render["ior"], 0).astype(np.float32),
        "fresnel_code": render["fresnel_code"].astype(np.uint8),
        "normal": render["normal"].astype(np.float16),
        "K": camera.K, "cam_from_world": camera.cam_from_world,
        "size": np.array([camera.width, camera.height]),
    }


def view_directions(camera: Camera) -> np.ndarray:
    """(H, W, 3) unit world-space viewing directions through the pixel centres."""
    uv = camera.pixel_grid().reshape(-1, 2)
    d = np.linalg.solve(camera.K, np.c_[uv, np.ones(len(uv))].T).T @ camera.R
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d.reshape(camera.height, camera.width, 3)


def composite_ray_tree(tree: dict[str, np.ndarray]) -> np.ndarray:
    """(H, W, 3) image from the nodes, weighting R and T by the view-dependent Fresnel term."""
    for key in ("D", "R", "T", "normal"):
        if tree[key].ndim != 3 or tree[key].shape[2] != 3:
            raise ValueError(f"ray tree node {key} must be (H, W, 3), got {tree[key].shape}")
    w, h = (int(x) for x in tree["size"])
    cam = Camera(tree["K"], tree["cam_from_world"], w, h)
    d = view_directions(cam)
    cos_i = np.abs(np.sum(d * tree["normal"].astype(np.float64), axis=2))
    F = fresnel_weight(tree["fresnel_code"], cos_i, tree["ior"])
    valid = tree["valid"]
    R = np.where((valid & BIT_R)[..., None] > 0, tree["R"].astype(np.float64), 0.0)
    T = np.where((valid & BIT_T)[..., None] > 0, tree["T"].astype(np.float64), 0.0)
    none = (tree["fresnel_code"] == FRESNEL_NONE)[..., None]
    D = tree["D"].astype(np.float64)
    return D + np.where(none, R, F[..., None] * R + (1 - F[..., None]) * T)


def write_ray_tree(path: Path, tree: dict[str, np.ndarray], image: np.ndarray,
                   new_camera: Camera, new_image: np.ndarray, new_depth: np.ndarray) -> None:
    """One .npz: the tree of the old camera, its full render `image` and, for scoring a warp,
    the ground-truth render (`new_image`, `new_depth`) at `new_camera`."""
    from .writers import save_npz  # deterministic bytes

    save_npz(path, **tree, image=image.astype(np.float16), new_K=new_camera.K,
             new_cam_from_world=new_camera.cam_from_world,
             new_size=np.array([new_camera.width, new_camera.height]),
             new_image=new_image.astype(np.float16), new_depth=new_depth.astype(np.float32))


def read_ray_tree(path: Path) -> dict[str, np.ndarray]:
    with np.load(path) as z:
        return {k: z[k] for k in z.files}
