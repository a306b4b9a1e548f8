"""Issue #5 addition: steps the global mesh rounded into ramps (geometry/depth_rounded.py)."""
from __future__ import annotations

import numpy as np

from ibr_pipeline.geometry.depth_rounded import canny_edges, rounded_steps
from ibr_pipeline.geometry.normals import normals_from_points, pixel_rays, points_from_depth
from ibr_pipeline.scene import Camera

W, H = 80, 60


def _cam():
    return Camera(Camera.intrinsics_from_fov(W, H, 60.0), np.eye(4), W, H)


def _detect(depth, colour_col=40):
    cam = _cam()
    P = points_from_depth(depth, cam.K)
    N = normals_from_points(P, depth > 0)
    col = np.zeros((H, W), bool)
    col[:, colour_col] = True  # a long colour edge (e.g. a poster border)
    return rounded_steps(depth, P, N, col)


def test_ramp_between_parallel_planes_is_found():
    # a 4 cm step at 2 m (lambda = 2 cm) smoothed into a 4 px ramp, as a TSDF would: Eq. 1 on
    # adjacent pixels misses it (1 cm per pixel), the 2s-apart test finds it at the colour edge
    d = np.full((H, W), 2.0)
    d[:, :38] = 1.96
    d[:, 38:42] = np.linspace(1.96, 2.0, 6)[1:5]
    found = _detect(d)
    assert found[:, 40].sum() >= H - 8
    assert not found[:, :30].any() and not found[:, 50:].any()


def test_plane_and_crease_are_not_steps():
    cam = _cam()
    rays = pixel_rays(cam.K, H, W)
    slant = 3.0 / (1 - 0.8 * rays[..., 0])  # slanted wall with a (texture) colour edge
    assert not _detect(slant).any()
    # a 90-degree corner between two walls: continuous depth, normals differ -> not a step
    x = rays[..., 0]
    corner = np.minimum(2.0 / (1 + x), 2.0 / (1 - x))
    assert not _detect(corner, colour_col=W // 2).any()


def test_short_texture_pieces_are_dropped():
    d = np.full((H, W), 2.0)
    d[:, :38] = 1.96
    d[:, 38:42] = np.linspace(1.96, 2.0, 6)[1:5]
    cam = _cam()
    P = points_from_depth(d, cam.K)
    N = normals_from_points(P, d > 0)
    col = np.zeros((H, W), bool)
    col[10:20, 40] = True  # a 10 px piece: shorter than min_length_px
    assert not rounded_steps(d, P, N, col).any()
    assert rounded_steps(d, P, N, col, min_length_px=5).sum() == 10


def test_canny_edges_of_a_step_image():
    img = np.zeros((H, W, 3), np.float32)
    img[:, 40:] = 0.8
    e = canny_edges(img)
    assert e[:, 38:42].any(1).mean() > 0.9 and not e[:, :30].any()
