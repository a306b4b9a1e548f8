"""Position-domain filling of undefined specular pixels (our extension after §3.4's search,
specular.position_fill / nbsearch.position_fill): properties, not copied outputs."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from ibr_pipeline.metrics import psnr
from ibr_pipeline.raytree.decode import decode
from ibr_pipeline.synthetic.raytree_cases import make_case
from ibr_pipeline.raytree.specular import SpecularOptions, position_fill
from ibr_pipeline.raytree.warp import WarpOptions, warp_decoded

torch.set_num_threads(1)
BACKENDS = ["torch"]
try:
    from ibr_pipeline.raytree import nbsearch as ns
    BACKENDS.append("numba")
except ImportError:   # pragma: no cover - numba is optional
    ns = None


def _fill(backend, q, known, pix, size, radius, rounds):
    if backend == "torch":
        qo, f = position_fill(torch.from_numpy(q), torch.from_numpy(known), torch.from_numpy(pix),
                              size, radius, rounds)
        return qo.numpy(), f.numpy()
    return ns.position_fill(q, known, pix, size[0], size[1], radius, rounds)


def _affine_field(W, H, seed=0):
    g = np.random.default_rng(seed)
    A = g.normal(size=(2, 2)) * 0.7
    b = g.uniform(20, 80, size=2)
    ys, xs = np.mgrid[0:H, 0:W]
    q = (np.stack([xs, ys], -1) @ A.T + b).reshape(-1, 2).astype(np.float32)
    return q, np.arange(W * H, dtype=np.int64)


@pytest.mark.parametrize("backend", BACKENDS)
def test_affine_flow_is_recovered_and_known_pixels_untouched(backend):
    """A planar mirror's flow is affine: a rim band and holes of it are filled exactly (up to
    float32), defined pixels keep their q, and only undefined pixels are marked filled."""
    W, H = 40, 30
    q, pix = _affine_field(W, H)
    g = np.random.default_rng(1)
    known = g.random(W * H) > 0.15
    known.reshape(H, W)[:, :4] = False          # a 4-px band at the border (extrapolation)
    known.reshape(H, W)[10:16, 20:26] = False   # a 6x6 hole (two rounds from the outside)
    q_in = np.where(known[:, None], q, np.float32(-7.0))   # garbage at undefined pixels
    qo, filled = _fill(backend, q_in.copy(), known, pix, (W, H), 3, 4)
    assert not (filled & known).any()
    np.testing.assert_array_equal(qo[known], q_in[known])
    assert filled.sum() == (~known).sum()      # every hole is reachable in 4 rounds of radius 3
    assert np.abs(qo[filled] - q[filled]).max() < 1e-3


@pytest.mark.parametrize("backend", BACKENDS)
def test_isolated_and_sparse_pixels_stay_undefined(backend):
    """Fewer than 3 known neighbours inside the window, or only collinear ones: no fit, the
    pixel stays undefined; rounds = 0 or radius = 0 change nothing."""
    W, H = 20, 20
    q, _ = _affine_field(W, H, 2)
    pix = np.array([5 * W + 5, 5 * W + 6, 15 * W + 15], np.int64)   # two known, far apart from m
    qq = q[pix].copy()
    known = np.array([True, True, False])
    qo, filled = _fill(backend, qq.copy(), known, pix, (W, H), 3, 4)
    assert not filled.any() and np.array_equal(qo, qq)
    for r, n in ((0, 4), (3, 0)):
        _, f = _fill(backend, qq.copy(), np.array([True, False, False]), pix, (W, H), r, n)
        assert not f.any()
    # three known pixels on one row next to m: collinear, the fit across the row is undetermined
    pix = np.array([3 * W + 2, 3 * W + 3, 3 * W + 4, 5 * W + 3], np.int64)
    qq = np.array([[1, 2], [3, 4], [5, 9], [0, 0]], np.float32)
    qo, filled = _fill(backend, qq.copy(), np.array([True, True, True, False]), pix, (W, H), 3, 4)
    assert not filled.any() and np.array_equal(qo, qq)


@pytest.mark.skipif(ns is None, reason="numba not installed")
def test_position_fill_backends_agree():
    W, H = 64, 48
    g = np.random.default_rng(3)
    ys, xs = np.mgrid[0:H, 0:W]
    q = np.stack([xs + 3 * np.sin(ys / 7.0), ys + 2 * np.cos(xs / 5.0)], -1).reshape(-1, 2).astype(np.float32)
    sel = np.flatnonzero(g.random(W * H) > 0.3)          # the searched set (a sparse subset)
    known = g.random(len(sel)) > 0.3
    a, fa = _fill("torch", q[sel].copy(), known, sel.astype(np.int64), (W, H), 3, 4)
    b, fb = _fill("numba", q[sel].copy(), known, sel.astype(np.int64), (W, H), 3, 4)
    assert np.array_equal(fa, fb) and fa.any()
    assert np.abs(a - b).max() < 1e-3


@pytest.fixture(scope="module", params=["mirror", "chrome"])
def case(request):
    # anti-aliased (3x3 supersampled) like the bench: on aliased renders the ground truth's own
    # aliasing dominates the rim error and the fill neither helps nor hurts noticeably
    return make_case(request.param, 160, 120, supersample=3)


@pytest.mark.parametrize("backend", BACKENDS)
def test_fill_raises_specular_psnr_and_keeps_defined_pixels(case, backend):
    """Against the paper's push-pull alone (fill_radius = 0) on the same search: the defined
    pixels (Delta <= eps) and their node values are unchanged, no pixel loses its value, the
    undefined pixels without a value do not increase, and specular PSNR rises (the rims carry
    much of the specular error)."""
    base = WarpOptions(backend=backend, specular=SpecularOptions(fill_radius=0))
    ext = WarpOptions(backend=backend)
    dec = decode(case.tree, backend=backend)
    a, b = warp_decoded(dec, case.new, base), warp_decoded(dec, case.new, ext)
    keep = ~case.disoccluded
    spec = case.specular & keep
    for i in range(1, case.tree.n_nodes):
        assert np.array_equal(a.defined[i], b.defined[i]) and not a.filled[i].any()
        assert not (b.filled[i] & b.defined[i]).any()
        d = b.defined[i]
        assert np.array_equal(a.nodes[i][d], b.nodes[i][d])
        und_a = (a.region[i] & ~a.defined[i]).sum()
        und_b = (b.region[i] & ~b.defined[i] & ~b.filled[i]).sum()
        assert und_b <= und_a and (b.filled[i].sum() > 0 or und_a == 0)
    assert b.filled[1].sum() > 0
    pa = psnr(np.clip(a.image, 0, 1), case.gt_image, spec)
    pb = psnr(np.clip(b.image, 0, 1), case.gt_image, spec)
    assert pb >= pa + 0.05, (pa, pb)
