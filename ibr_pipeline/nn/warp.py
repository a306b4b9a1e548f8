"""Motion vectors from depth + poses and backward warping (Xu et al. §5.2.1, the `M_d` of Eq. 16).

Convention: a motion field `M` (H, W, 2) (numpy) or (B, 2, H, W) (torch) is given *at the pixels of
the current frame* and points to where that surface point is seen in the previous frame, in pixels
(u right, v down, pixel centre (0, 0) as in scene.py):  p_prev = p + M(p).  Backward warping
(`M ⊙ I_{n-1}` in the paper) then reads the previous frame at p + M(p):
    (M ⊙ I_{n-1})(p) = I_{n-1}(p + M(p))   (bilinear, grid_sample).

`depth_motion` computes the base motion `M_d` from the current z-depth and the two cameras
(unproject with D_n, project with the previous camera) and flags pixels whose surface point is not
visible in the previous frame (outside it, or occluded: its projected depth disagrees with D_{n-1}).
"""
from __future__ import annotations

import numpy as np

from ..scene import Camera


def depth_motion(depth_cur: np.ndarray, cam_cur: Camera, cam_prev: Camera,
                 depth_prev: np.ndarray | None = None,
                 occlusion_tol: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Base motion M_d (Eq. 16) from D_n and the poses; returns (flow (H,W,2) float32, valid (H,W)).

    depth_cur: (H, W) z-depth of the current frame in the units of the poses, 0 = hole (flow 0).
    cam_cur / cam_prev: cameras at the resolution of the depth maps (same size).
    depth_prev: (H, W) z-depth of the previous frame (D_{n-1}); when given, a pixel whose projected
    depth differs from D_{n-1} at its target by more than `occlusion_tol` (relative) is invalid.
    valid: the point has depth, lies in front of the previous camera and inside its image
    (and passed the occlusion test).
    """
    d = np.asarray(depth_cur, dtype=np.float64)
    if d.ndim != 2:
        raise ValueError(f"depth_cur must be (H, W), got {d.shape}")
    h, w = d.shape
    if (cam_cur.width, cam_cur.height) != (w, h) or (cam_prev.width, cam_prev.height) != (w, h):
        raise ValueError(f"cameras must match the depth size {w}x{h}, got "
                         f"{cam_cur.width}x{cam_cur.height} and {cam_prev.width}x{cam_prev.height}")
    if depth_prev is not None and np.shape(depth_prev) != (h, w):
        raise ValueError(f"depth_prev must be {(h, w)}, got {np.shape(depth_prev)}")
    has = np.isfinite(d) & (d > 0)
    uv = cam_cur.pixel_grid().reshape(-1, 2)
    z = np.where(has, d, 1.0).reshape(-1)
    world = cam_cur.unproject(uv, z)
    uv_prev, z_prev = cam_prev.project(world)
    flow = (uv_prev - uv).reshape(h, w, 2)
    z_prev = z_prev.reshape(h, w)
    valid = has & (z_prev > 1e-6) & np.all(np.isfinite(flow), axis=-1)
    up, vp = uv_prev[:, 0].reshape(h, w), uv_prev[:, 1].reshape(h, w)
    valid &= (up >= -0.5) & (up <= w - 0.5) & (vp >= -0.5) & (vp <= h - 0.5)
    if depth_prev is not None:
        dp = np.asarray(depth_prev, dtype=np.float64)
        ui = np.clip(np.rint(up), 0, w - 1).astype(np.int64)
        vi = np.clip(np.rint(vp), 0, h - 1).astype(np.int64)
        target = dp[vi, ui]
        with np.errstate(invalid="ignore", divide="ignore"):
            agree = np.abs(target - z_prev) <= occlusion_tol * np.maximum(z_prev, 1e-9)
        valid &= (target > 0) & agree
    # Only motions that land in the previous image are kept; elsewhere M_d = 0 (the MVR input and
    # the warp stay bounded: a point just in front of the previous camera projects millions of
    # pixels away, and such values made single training steps explode on real IBR renders).
    flow = np.where(valid[..., None], flow, 0.0)
    return flow.astype(np.float32), valid


def pixel_grid(h: int, w: int, device=None, dtype=None):
    """(1, 2, H, W) torch tensor of pixel-centre coordinates (u, v)."""
    import torch

    v, u = torch.meshgrid(torch.arange(h, device=device, dtype=dtype),
                          torch.arange(w, device=device, dtype=dtype), indexing="ij")
    return torch.stack([u, v])[None]


def backward_warp(image, flow, padding_mode: str = "zeros"):
    """`M ⊙ I` of Eq. 16: sample image (B, C, H, W) at p + flow(p), flow (B, 2, H, W) in pixels.

    Returns (warped (B, C, H, W), inside (B, 1, H, W) float: 1 where p + flow lies in the image)."""
    import torch
    import torch.nn.functional as F

    if image.ndim != 4 or flow.ndim != 4 or flow.shape[1] != 2 or \
            flow.shape[0] != image.shape[0] or flow.shape[2:] != image.shape[2:]:
        raise ValueError(f"image must be (B, C, H, W) and flow (B, 2, H, W) of the same B, H, W; "
                         f"got {tuple(image.shape)} and {tuple(flow.shape)}")
    b, _, h, w = image.shape
    pos = pixel_grid(h, w, image.device, flow.dtype) + flow
    # pixel centres 0..W-1 map to -1..1 (align_corners=True keeps the scene.py pixel convention)
    gx = pos[:, 0] * (2.0 / max(w - 1, 1)) - 1.0
    gy = pos[:, 1] * (2.0 / max(h - 1, 1)) - 1.0
    grid = torch.stack([gx, gy], dim=-1)
    warped = F.grid_sample(image, grid.to(image.dtype), mode="bilinear", padding_mode=padding_mode,
                           align_corners=True)
    inside = ((pos[:, 0] >= -0.5) & (pos[:, 0] <= w - 0.5) & (pos[:, 1] >= -0.5) &
              (pos[:, 1] <= h - 0.5)).unsqueeze(1).to(image.dtype)
    return warped, inside
