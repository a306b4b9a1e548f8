"""geometry/depth_complete.py: filling what the global mesh leaves empty."""
import numpy as np
import pytest

from ibr_pipeline.geometry.depth_complete import (PlaneOptions, complete_depth, edge_weights,
                                                  membrane_fill, remove_speckles, segment_planes)
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
    # the edge map computed once without strokes (view_depth shares it with Eq. 2) and strokes
    # added here: the same completion as computing it inside
    from ibr_pipeline.geometry.geodesic import colour_edge_map
    strokes = np.zeros((H, W), bool)
    strokes[:, 40] = True
    for st in (None, strokes):
        ref, _ = complete_depth(depth, cam, image, cost_edge=15.0, strokes=st)
        got, _ = complete_depth(depth, cam, image, cost_edge=15.0, strokes=st,
                                base_edges=colour_edge_map(image, None))
        assert np.array_equal(got, ref)
    assert not np.array_equal(complete_depth(depth, cam, image, cost_edge=15.0, strokes=strokes)[0],
                              out)  # the stroke changes the fill: it reached the map


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


def _two_region_scene(seed=0):
    """Two colour regions (x < W/2 dark, else bright), each a different slanted plane; depth known
    on 10 % random pixels of each (MVS on texture), the rest a hole."""
    cam = _camera()
    left = _plane_depth(cam, np.array([0.3, -0.4, 1.0]) / np.linalg.norm([0.3, -0.4, 1]), 2.0)
    right = _plane_depth(cam, np.array([-0.5, 0.2, 1.0]) / np.linalg.norm([-0.5, 0.2, 1]), 3.5)
    is_left = np.arange(W)[None, :] < W // 2
    truth = np.where(is_left, left, right)
    image = np.where(is_left[..., None], 0.2, 0.8) * np.ones((H, W, 3))
    known = np.random.default_rng(seed).random((H, W)) < 0.1
    return cam, truth, image, known, is_left


def test_segment_planes_fill_each_region_with_its_own_plane():
    cam, truth, image, known, is_left = _two_region_scene()
    depth = np.where(known, truth, 0.0)
    # a fifth of the left region's known depths are outliers: RANSAC keeps the plane
    rng = np.random.default_rng(1)
    bad = known & is_left & (rng.random((H, W)) < 0.2)
    depth[bad] = rng.uniform(1.0, 5.0, int(bad.sum()))
    out, filled = segment_planes(depth, image, PlaneOptions())
    hole = ~known
    # the blurred colour edge itself forms thin segments of its own, too small to fit
    inner = hole & (np.abs(np.arange(W) - W // 2 + 0.5) > 3)[None, :]
    assert filled[inner].all() and not filled[known].any()
    err = np.abs(out - truth) / truth
    assert err[inner & ~is_left].max() < 1e-6      # exact known depths: the plane itself
    # outliers that happen to fall within tol_rel of the plane join the least-squares fit
    assert err[inner & is_left].max() < 0.005
    # through complete_depth the membrane has nothing left to do inside the regions
    out2, which = complete_depth(depth, cam, image, planes=PlaneOptions())
    assert which["planes"].sum() == filled.sum() and np.allclose(out2[filled], out[filled])


def test_a_segment_no_plane_explains_is_left_to_the_membrane():
    cam, truth, image, known, _ = _two_region_scene()
    depth = np.where(known, np.random.default_rng(2).uniform(1.0, 4.0, (H, W)), 0.0)
    out, filled = segment_planes(depth, image, PlaneOptions())
    assert not filled.any() and np.array_equal(out, depth)
    _, which = complete_depth(depth, cam, image, planes=PlaneOptions())
    assert not which["planes"].any() and which["interpolated"][~known].mean() > 0.95


def test_a_plane_is_not_extrapolated_beyond_its_known_depth_range():
    """Known depths on a 3-pixel strip at the left edge of a steep plane: the rest of the segment
    lies far outside their range and is not filled from them."""
    cam = _camera()
    truth = _plane_depth(cam, np.array([-0.9, 0.0, 0.45]) / np.linalg.norm([-0.9, 0, 0.45]), 1.0)
    truth = np.where(truth > 0, truth, 0.0)
    depth = np.zeros((H, W))
    depth[:, :3] = truth[:, :3]
    out, filled = segment_planes(depth, np.full((H, W, 3), 0.5), PlaneOptions())
    inv = np.where(truth > 0, 1.0 / np.where(truth > 0, truth, 1.0), 0.0)
    lo, hi = inv[:, :3].min(), inv[:, :3].max()
    assert filled.any() and not filled[:, W // 2:].any()
    assert np.all(1.0 / out[filled] > 0.8 * lo - 1e-9) and np.all(1.0 / out[filled] < 1.25 * hi + 1e-9)


def test_segment_planes_checks_shapes():
    with pytest.raises(ValueError, match="disagree"):
        segment_planes(np.zeros((H, W)), np.zeros((H, W + 1, 3)), PlaneOptions())


def test_speckles_of_wrong_depth_are_removed_surfaces_are_kept():
    cam = _camera()
    truth = _plane_depth(cam, np.array([0.3, -0.4, 1.0]) / np.linalg.norm([0.3, -0.4, 1]), 2.0)
    d = truth.copy()
    d[5, 5] = 9.0                 # one wrong pixel
    d[20:23, 30:33] = 0.7         # a 3x3 blob of wrong matches
    d[30:45, 5:25] = 1.2          # an object of 300 px in front of the plane: a surface
    d[0, :] = 0                   # no depth
    out = remove_speckles(d, 20)
    assert out[5, 5] == 0 and np.all(out[20:23, 30:33] == 0)
    keep = np.ones((H, W), bool)
    keep[5, 5] = False
    keep[20:23, 30:33] = False
    keep[0] = False
    # the slanted plane (neighbours < 2 % apart) stays one region, the object stays too
    assert np.array_equal(out[keep], d[keep]) and np.all(out[0] == 0)
    # through complete_depth: the speckles are not used, their pixels are interpolated
    depth = np.zeros((H, W))
    _, which = complete_depth(depth + np.where(np.arange(W) < 3, truth, 0), cam,
                              np.full((H, W, 3), 0.5), d, speckle_px=20)
    assert not which["mvs"][5, 5] and not which["mvs"][21, 31] and which["mvs"][35, 10]
