"""Numpy reference formulas of §5.1.3–5.1.4 against hand-computed values."""
import math

import cv2
import numpy as np
import pytest

from ibr_pipeline.render import blend


def test_ibr_cost_by_hand():
    x = np.zeros(3)
    # same direction, twice as far from t_n as from t_k: angle 0, penalty max(0, 1 - 2/1) = 0
    assert blend.ibr_cost(np.array([1.0, 0, 0]), np.array([2.0, 0, 0]), x) == pytest.approx(0)
    # t_n closer than t_k by half: 1 - 0.5 = 0.5; perpendicular rays add π/2
    assert blend.ibr_cost(np.array([2.0, 0, 0]), np.array([1.0, 0, 0]), x) == pytest.approx(0.5)
    assert blend.ibr_cost(np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), x) == pytest.approx(math.pi / 2)


def test_view_weights_eq15_ratios():
    w = blend.view_weights(np.array([0.1, 0.133, 5.0]))
    assert w[0] == 1.0
    assert w[1] / w[0] == pytest.approx(math.exp(-0.033 / 0.033))
    assert w[2] == blend.VIEW_WEIGHT_FLOOR  # exp(-148) would underflow float32


def test_fuzzy_depth_test_removes_floating_geometry():
    # view 0: good (cost 0.1) surface at 2 m; view 1: floater at 1 m with high cost (0.5);
    # view 2: the surface 2 cm behind view 0's (within 3 cm: contributes); view 3: far behind
    depth = np.array([2.0, 1.0, 2.02, 2.5]).reshape(4, 1, 1)
    cost = np.array([0.1, 0.5, 0.2, 0.1]).reshape(4, 1, 1)
    front, contrib = blend.fuzzy_depth_test(depth, cost)
    assert front[0, 0] == pytest.approx(2.0)
    assert contrib[:, 0, 0].tolist() == [True, False, True, False]
    # a floater with a cost within the margin *is* the front-most surface
    front, contrib = blend.fuzzy_depth_test(depth, np.array([0.1, 0.2, 0.2, 0.1]).reshape(4, 1, 1))
    assert front[0, 0] == pytest.approx(1.0) and contrib[:, 0, 0].tolist() == [False, True, False, False]


def test_feather_and_edge_decay():
    f = blend.feather_weight(60, 80, 20)
    assert f[0, 0] < 0.01 and f[30, 40] == 1.0 and f[30, 21] == 1.0 and 0 < f[30, 10] < 1
    edges = np.zeros((40, 40), bool)
    edges[:, 20] = True
    e = blend.edge_decay(edges, 5)
    assert e[10, 20] == 0 and e[10, 26] == 1 and 0 < e[10, 23] < 1 and 0 < e[10, 17] < 1
    a = blend.texture_alpha(edges)
    assert a.min() == pytest.approx(blend.WEIGHT_FLOOR)


def test_blend_and_fill_holes():
    colors = np.stack([np.full((4, 4, 3), 0.2), np.full((4, 4, 3), 0.8)])
    w = np.stack([np.full((4, 4), 3.0), np.full((4, 4), 1.0)])
    w[:, 0, 0] = 0
    out, wsum = blend.blend(colors, w)
    assert out[1, 1] == pytest.approx([0.35] * 3) and wsum[0, 0] == 0 and out[0, 0].sum() == 0
    img = np.full((32, 32, 3), 0.5, np.float32)
    covered = np.ones((32, 32), bool)
    covered[10:14, 10:14] = False
    img[~covered] = 0
    filled = blend.fill_holes(img, covered)
    assert np.allclose(filled, 0.5, atol=1e-4)


def test_compose_eq3_and_shape_errors():
    i0, i1 = np.full((2, 2, 3), 0.2), np.full((2, 2, 3), 0.5)
    beta = np.array([[0, 1.0], [0.5, 0.1]])
    assert blend.compose(i0, beta, i1)[1, 0, 0] == pytest.approx(0.45)
    with pytest.raises(ValueError, match="shape|need"):
        blend.compose(i0, beta[:1], i1)
    with pytest.raises(ValueError, match="K, H, W"):
        blend.fuzzy_depth_test(np.zeros((2, 2)), np.zeros((2, 2)))


def _textured(h=192, w=256, seed=0):
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w]
    img = np.stack([0.5 + 0.4 * np.sin(x / 9.0), 0.5 + 0.4 * np.cos(y / 7.0),
                    0.3 + 0.2 * np.sin((x + y) / 13.0)], -1)
    return (img + 0.02 * rng.standard_normal(img.shape)).astype(np.float32)


def test_windowed_fill_matches_the_whole_frame_fill():
    """Small holes: the push-pull over windows around them gives the whole-frame fill's pixels
    (issue #28: the same pixels within tolerance), and leaves pixels far from holes alone."""
    img = _textured()
    covered = np.ones(img.shape[:2], bool)
    covered[10:13, 20:23] = False      # a speck
    covered[50:58, 70:75] = False      # a blob
    covered[80, 5:40] = False          # a thin scratch
    covered[0:4, 248:256] = False      # at a corner
    assert blend.hole_windows(~covered) is not None  # the windowed path is the one tested
    a = blend.fill_holes(img, covered)
    b = blend.fill_holes_frame(img, covered)
    assert np.abs(a - b).max() < 0.02
    assert np.abs(a - b)[~covered].mean() < 2e-3
    far = cv2.distanceTransform(covered.astype(np.uint8), cv2.DIST_L2, 3) > 3
    assert np.array_equal(a[far], img[far])
    lo, hi = img[covered].min(0), img[covered].max(0)  # push-pull averages covered colours
    assert np.all(a[~covered] >= lo - 1e-5) and np.all(a[~covered] <= hi + 1e-5)


def test_fill_only_where_needed_and_whole_frame_for_big_holes():
    """The reflection layer's case: colour only inside a box (where it was rendered), needed
    only where beta > 0: the fill of that box equals the whole frame's, the rest is left alone."""
    img = _textured(seed=1)
    covered = np.zeros(img.shape[:2], bool)
    covered[20:100, 30:150] = True
    covered[50:56, 60:66] = False            # a hole inside the reflector
    need = np.zeros(covered.shape, bool)
    need[25:95, 35:145] = True
    marked = img.copy()
    marked[~covered] = 7.0  # a value no fill produces
    out = blend.fill_holes(marked, covered, need=need)
    assert np.all(out[150:, 200:] == 7.0)                       # far from it: left alone
    ref = blend.fill_holes_frame(marked, covered)
    hole = np.s_[50:56, 60:66]
    assert np.all(out[hole] < 1.0)                              # the needed hole is filled
    far = cv2.distanceTransform(covered.astype(np.uint8), cv2.DIST_L2, 3) > 3
    assert np.allclose(out[need & far], img[need & far], atol=1e-5)  # blendLinear rounding
    # in the hole the fills differ (pyramids of another extent): the box's is about as close to
    # the true texture there as the whole frame's (0.022 vs 0.019 mean error on this texture)
    err, err_ref = np.abs(out[hole] - img[hole]).mean(), np.abs(ref[hole] - img[hole]).mean()
    assert err < 1.25 * err_ref
    big = np.ones(img.shape[:2], bool)
    big[:, :140] = False  # more than half of the frame: the whole-frame push-pull itself
    assert blend.hole_windows(~big) is None
    assert np.array_equal(blend.fill_holes(img, big), blend.fill_holes_frame(img, big))
