"""The numba CPU backend of ibr_pipeline.raytree agrees with the torch reference (same algorithm,
float64 registers instead of float32 tensors: a handful of pixels may take another discrete
branch, everything else agrees to float precision)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from ibr_pipeline.errors import InputError
from ibr_pipeline.raytree import ops
from ibr_pipeline.raytree.backend import resolve
from ibr_pipeline.raytree.decode import decode
from ibr_pipeline.raytree.fill import push_pull
from ibr_pipeline.raytree.scenarios import make_case
from ibr_pipeline.raytree.warp import WarpOptions, naive_warp, warp, warp_decoded

pytest.importorskip("numba")
from ibr_pipeline.raytree import nbkernels as nk  # noqa: E402
from ibr_pipeline.raytree import warp_nb  # noqa: E402

torch.set_num_threads(1)
NB, TO = WarpOptions(backend="numba"), WarpOptions(backend="torch")


@pytest.fixture(scope="module", params=["mirror", "chrome", "pane"])
def case(request):
    return make_case(request.param, 128, 96, supersample=1)


def test_backend_choice():
    assert resolve("auto", "cpu") == "numba" and resolve("torch", "cpu") == "torch"
    assert resolve("auto", "cuda") == "torch"
    with pytest.raises(InputError, match="CPU only"):
        resolve("numba", "cuda")
    with pytest.raises(InputError, match="backend"):
        WarpOptions(backend="fast").validate()


def _close_frac(a, b, atol=1e-4):
    """Fraction of pixels whose vectors agree within atol."""
    return float(((a - b).abs().amax(-1) <= atol).float().mean())


def test_decode_matches_torch(case):
    a, b = decode(case.tree, backend="numba"), decode(case.tree, backend="torch")
    assert a.box == b.box
    for i in range(case.tree.n_nodes):
        assert torch.equal(a.valid[i], b.valid[i])
        assert torch.equal(a.rgb[i], b.rgb[i])
        # float64 vs float32 normals; the edge-aware normals' depth test (normal_edge_rel) may
        # flip for a tap right at the threshold: a handful of pixels differ more
        assert _close_frac(a.pos[i], b.pos[i]) > 0.999
        assert _close_frac(a.dirs[i], b.dirs[i]) > 0.999
    assert _close_frac(a.normal[0], b.normal[0]) > 0.999
    assert b.normal[0].abs().sum() > 0


def test_quad_smoothness_matches_sampler(case):
    """Root (depth + node-set / Fresnel label) and node (ray-spread slack) quad tests."""
    from ibr_pipeline.raytree.warp import _node_tables, _root_tables
    dec = decode(case.tree, backend="torch")
    R = warp_nb.root_tables(dec, 0.05)
    assert np.array_equal(R["qok"], _root_tables(dec, 0.05)[0].quad_ok.numpy())
    for i in range(1, case.tree.n_nodes):
        T = warp_nb.node_tables(dec, i, 0.1, 8.0)
        ref = _node_tables(dec, i, 0.1, 8.0)[0].quad_ok.numpy()
        assert (T["qok"] != ref).mean() < 1e-4 and ref.any() == T["qok"].any()


def test_push_pull_matches_torch():
    g = torch.Generator().manual_seed(0)
    for H, W in ((37, 53), (64, 64), (5, 9), (1, 7)):
        img = torch.rand(H, W, 4, generator=g)
        valid = torch.rand(H, W, generator=g) > 0.7
        ref = push_pull(img, valid).numpy()
        out = warp_nb.push_pull(img.numpy(), valid.numpy())
        assert np.allclose(out, ref, atol=1e-5), (H, W)
    full = np.ones((4, 4), bool)
    assert warp_nb.push_pull(np.ones((4, 4, 2), np.float32), full).sum() == 32
    assert warp_nb.push_pull(np.ones((4, 4, 2), np.float32), ~full).sum() == 0


def test_splat_and_fill_match_torch(case):
    from ibr_pipeline.raytree.diffuse import closest_3x3, projection_matrix, splat_keys
    dec = decode(case.tree, backend="torch")
    cam = case.new
    P = projection_matrix(cam.K, cam.cam_from_world, "cpu")
    uv, z = ops.project(P, dec.pos[0])
    keys = splat_keys(uv, z, dec.valid[0], cam.size)
    filled = closest_3x3(keys, cam.size)
    n_old = dec.valid[0].numel()
    ref_d = torch.where(keys == torch.iinfo(torch.int64).max, -1, keys % n_old).numpy()
    ref_f = torch.where(filled == torch.iinfo(torch.int64).max, -1, filled % n_old).numpy()
    R = warp_nb.root_tables(dec, 0.05)
    uv2, keys2, d = nk.project_splat(R["pos"], R["valid"], P.numpy().astype(np.float64), *cam.size)
    f = nk.closest_3x3(keys2, d, *cam.size)
    assert np.allclose(uv2, uv.reshape(-1, 2).numpy(), atol=1e-3)
    assert (d != ref_d).mean() < 1e-3 and (f != ref_f).mean() < 1e-3


def _agree(a, b, frac):
    return (np.asarray(a) != np.asarray(b)).mean() <= frac


def test_warp_matches_torch(case):
    rn = warp(case.tree, case.new, NB, record_history=True)
    rt = warp(case.tree, case.new, TO, record_history=True)
    assert set(rn.timings) == set(rt.timings)
    assert _agree(rn.diffuse_ok, rt.diffuse_ok, 2e-3)
    for i in range(case.tree.n_nodes):
        assert _agree(rn.region[i], rt.region[i], 2e-3)
        assert _agree(rn.defined[i], rt.defined[i], 2e-3)
        assert _agree(rn.filled[i], rt.filled[i], 2e-3)   # position-domain fill (our extension)
    same = rn.diffuse_ok == rt.diffuse_ok
    for i in range(1, case.tree.n_nodes):
        same &= (rn.defined[i] == rt.defined[i]) & (rn.filled[i] == rt.filled[i])
    assert same.mean() > 0.99
    d = np.abs(rn.image - rt.image).max(-1)
    assert np.median(d[same]) < 1e-5 and (d[same] > 1e-3).mean() < 5e-3
    assert np.abs(rn.fresnel - rt.fresnel)[same].max() < 1e-4
    # the per-pixel specular search: same searched pixels, final Delta within float precision
    assert set(rn.history) == set(rt.history)
    for i in rn.history:
        pn, hn, En = rn.history[i]
        pt, ht, Et = rt.history[i]   # torch lists the fixed-point fallback pixels last
        on = np.argsort(pn[:, 1] * 100000 + pn[:, 0])
        ot = np.argsort(pt[:, 1] * 100000 + pt[:, 0])
        pn, hn, En, pt, ht, Et = pn[on], hn[:, on], En[on], pt[ot], ht[:, ot], Et[ot]
        assert np.array_equal(pn, pt) and hn.shape == ht.shape
        eps = math.radians(1.0)
        assert _agree(En <= eps, Et <= eps, 5e-3)
        close = np.isclose(En, Et, atol=1e-4, rtol=1e-3)
        assert close.mean() > 0.98


def test_naive_warp_matches_torch(case):
    a = naive_warp(decode(case.tree, backend="numba"), case.new, NB)
    b = naive_warp(decode(case.tree, backend="torch"), case.new, TO)
    d = np.abs(a - b).max(-1)
    assert np.median(d) < 1e-5 and (d > 1e-3).mean() < 5e-3


def test_mixed_backends_share_decoded_trees(case):
    """A tree decoded by one backend warps with the other (Decoded is the same format)."""
    dec = decode(case.tree, backend="torch")
    a = warp_decoded(dec, case.new, NB)
    b = warp_decoded(decode(case.tree, backend="numba"), case.new, NB)
    d = np.abs(a.image - b.image).max(-1)
    assert np.median(d) < 1e-6 and (d > 1e-3).mean() < 5e-3


def test_closest_3x3_border_is_padded_with_empty_slots():
    """Regression (torch reference): F.pad(value=int64 max) padded with int64 min, so border
    pixels took a garbage key; both backends now equal the straightforward 3x3 minimum."""
    from ibr_pipeline.raytree.diffuse import _BIG, closest_3x3
    g = np.random.default_rng(0)
    Hn, Wn = 5, 7
    keys = g.permutation(1000)[:Hn * Wn].astype(np.int64)   # unique keys
    keys[g.random(Hn * Wn) < 0.5] = _BIG
    ref = np.full(Hn * Wn, _BIG)
    for y in range(Hn):
        for x in range(Wn):
            ref[y * Wn + x] = keys.reshape(Hn, Wn)[max(y - 1, 0):y + 2, max(x - 1, 0):x + 2].min()
    assert (ref != _BIG).any() and np.array_equal(closest_3x3(torch.from_numpy(keys), (Wn, Hn)).numpy(), ref)
    idx = np.where(keys == _BIG, -1, np.arange(Hn * Wn)).astype(np.int32)
    where = {int(k): j for j, k in enumerate(keys) if k != _BIG}
    expect = np.array([where[int(r)] if r != _BIG else -1 for r in ref])
    assert np.array_equal(nk.closest_3x3(keys, idx, Wn, Hn), expect)
