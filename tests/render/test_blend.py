"""Numpy reference formulas of §5.1.3–5.1.4 against hand-computed values."""
import math

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
    # no decay (per-view visibility): the edge pixels themselves keep their full weight
    assert np.array_equal(blend.edge_decay(edges, 0), np.ones((40, 40), np.float32))
    assert blend.texture_alpha(edges, feather_px=0, decay_px=0).min() == 1.0


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
