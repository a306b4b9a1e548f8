"""geometry/depth_complete.py: filling what the global mesh leaves empty."""
import numpy as np
import pytest

from ibr_pipeline.geometry.depth_complete import complete_depth, edge_weights, membrane_fill
from ibr_pipeline.scene import Camera

W, H = 64, 48


def _camera():
    return Camera(Camera.intrinsics_from_fov(W, H, 60.0), np.eye(4), W, H)


def _plane_depth(cam, n, d):
    """z-depth of the plane n . x = d seen by a camera at the origin looking along +z."""
    rays = np.linalg.solve(cam.K, np.c_[cam.pixel_grid().reshape(-1, 2), np.ones(W * H)].T).T
    return (d / (rays @ n)).reshape(H, W)


def test_a_hole_in_a_slanted_plane_is_filled_with_the_plane():
    cam = _camera()
    truth = _plane_depth(cam, np.array([0.0, -0.5, 1.0]) / np.linalg.norm([0, -0.5, 1]), 2.0)
    depth = truth.copy()
    depth[10:40, 15:50] = 0          # a hole of 30 x 35 pixels
    image = np.full((H, W, 3), 0.5)  # no colour edges
    out, which = complete_depth(depth, cam, image)
    hole = depth == 0
    assert which["interpolated"][hole].all() and not which["mvs"].any()
    # inverse depth of a plane is affine in the pixel: the membrane reproduces it to rounding
    assert np.abs(out[hole] - truth[hole]).max() < 1e-6 * truth.max()


def test_colour_edges_keep_two_surfaces_apart():
    """A hole straddling a strong colour edge: each side takes the depth of its own surface."""
    cam = _camera()
    depth = np.where(np.arange(W)[None, :] < W // 2, 1.0, 4.0) * np.ones((H, 1))
    image = np.where(np.arange(W)[None, :, None] < W // 2, 0.1, 0.9) * np.ones((H, 1, 3))
    depth[12:36, 20:44] = 0
    out, _ = complete_depth(depth, cam, image, cost_edge=15.0)
    left, right = out[12:36, 20:W // 2 - 2], out[12:36, W // 2 + 2:44]
    assert np.abs(left - 1.0).max() < 0.05 and np.abs(right - 4.0).max() < 0.2
    # without edge weights the two sides blend across the middle
    flat, _ = complete_depth(depth, cam, image, cost_edge=0.0)
    assert np.abs(flat[24, W // 2 - 3] - 1.0) > 0.1


def test_mvs_depth_comes_first_and_unreachable_holes_stay_empty():
    cam = _camera()
    depth = np.zeros((H, W))
    depth[:, :8] = 2.0
    mvs = np.zeros((H // 2, W // 2))      # half size, upsampled by nearest neighbour
    mvs[:, 10:14] = 3.0                   # columns 20..27 of the view
    image = np.full((H, W, 3), 0.5)
    out, which = complete_depth(depth, cam, image, mvs)
    assert which["mvs"][:, 20:28].all() and np.allclose(out[:, 20:28], 3.0)
    # the interpolated pixels between 2 and 3 lie between them (harmonic: no overshoot)
    mid = which["interpolated"]
    assert mid[:, 8:20].all() and out[mid].min() >= 2.0 - 1e-9 and out[mid].max() <= 3.0 + 1e-9
    # a component of the hole that touches no depth keeps 0
    v = np.zeros((6, 6))
    unknown = np.zeros((6, 6), bool)
    unknown[:, :] = True
    filled, reached = membrane_fill(v, unknown, edge_weights(np.zeros((6, 6)), 15.0))
    assert not reached.any() and np.all(filled == 0)


def test_bad_arguments_are_named():
    cam = _camera()
    with pytest.raises(ValueError, match="camera"):
        complete_depth(np.zeros((H + 1, W)), cam, np.zeros((H + 1, W, 3)))
    with pytest.raises(ValueError, match="aspect"):
        complete_depth(np.zeros((H, W)), cam, np.zeros((H, W, 3)), np.ones((10, 30)))
