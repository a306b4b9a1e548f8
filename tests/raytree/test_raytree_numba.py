"""The numba CPU backend of ibr_pipeline.raytree agrees with the torch reference: the same
algorithm, in float64 registers instead of float32 tensors.

Float model of every comparison here. Both backends read the same float32 buffers and differ
only by rounding. A discrete decision (a bound tested, a bilinear cell chosen, a search step
accepted) may therefore differ only where its input lies within float noise of the bound; outside
that margin the two must decide alike, exactly. Where the margin can be written down (a quad's
depth spread against its tolerance) the tests compute it; the specular search chains dozens of
decisions per pixel, so its margin is measured instead: the torch search is rerun on inputs
perturbed by a stated number of float32 ulps (_probe), and a pixel whose outcome moves under
those perturbations is inside the margin.

`test_raytree_numba_generic.py` reruns this module with numba's generic CPU target and torch's
scalar kernels, the other floating-point details a user's CPU may have."""
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
from ibr_pipeline.synthetic.raytree_cases import make_case
from ibr_pipeline.raytree.specular import SpecularOptions
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


def _quad_margin(dec, i, rel_tol, div_tol):
    """(H*W,) distance of each quad's decision input (depth spread - tolerance, warp._node_tables)
    from its bound, in float32 ulps of the quantities compared (float64 arithmetic here)."""
    y0, y1, x0, x1 = dec.box
    c = (slice(y0, y1), slice(x0, x1))
    k = np.pad(dec.depth[i][c].numpy().astype(np.float64), ((0, 1), (0, 1)), mode="edge")
    d = np.pad(dec.dirs[i][c].numpy().astype(np.float64), ((0, 1), (0, 1), (0, 0)), mode="edge")
    a, b, cc, dd = k[:-1, :-1], k[:-1, 1:], k[1:, :-1], k[1:, 1:]
    kmin = np.minimum(np.minimum(a, b), np.minimum(cc, dd))
    kmax = np.maximum(np.maximum(a, b), np.maximum(cc, dd))
    chord = np.sqrt(np.maximum(((d[:-1, :-1] - d[1:, 1:]) ** 2).sum(-1), ((d[:-1, 1:] - d[1:, :-1]) ** 2).sum(-1)))
    tol = rel_tol * np.maximum(np.abs(kmin), 1e-6) + div_tol * chord * np.abs(kmax)
    return (np.abs(kmax - kmin - tol) / (F32 * (np.abs(kmax) + tol))).reshape(-1)


def test_quad_smoothness_matches_sampler(case):
    """Root (depth + node-set / Fresnel label) and node (ray-spread slack) quad tests."""
    from ibr_pipeline.raytree.warp import _node_tables, _root_tables
    dec = decode(case.tree, backend="torch")
    R = warp_nb.root_tables(dec, 0.05)
    # the root test is the same float32 arithmetic in both (nbkernels.quad_ok rounds like torch)
    assert np.array_equal(R["qok"], _root_tables(dec, 0.05)[0].quad_ok.numpy())
    for i in range(1, case.tree.n_nodes):
        T = warp_nb.node_tables(dec, i, 0.1, 8.0)
        ref = _node_tables(dec, i, 0.1, 8.0)[0].quad_ok.numpy()
        # the slack's chord is float32 in torch, float64 in numba (~4 roundings of the chord,
        # the product and the sum): quads within 16 ulps of the bound may differ, no other
        near = _quad_margin(dec, i, 0.1, 8.0) <= 16
        assert np.array_equal(T["qok"][~near], ref[~near])
        assert near.mean() < 1e-3 and ref.any() == T["qok"].any()   # measured: no quad near


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


F32 = float(np.finfo(np.float32).eps)
EPS_RAD = math.radians(SpecularOptions().eps_deg)
# Identical inputs: the backends differ by torch's float32 rounding only. The search computes
# Delta from (w, n, q_d) through ~30 chained float32 operations (reflection, projection of the
# specular guess, bilinear W_s, angle), whose backward error is at most ~30 u = 15 ulps of each
# input (u = eps/2, the standard n*u bound); 64 ulps is that bound with 4x headroom.
PROBE_ULPS_SAME = 64
# End to end the inputs themselves differ: numba's float64 diffuse flow hands the search w, n
# and q_d that differ from torch's by up to 10, 94 and 448 ulps (|w|, unit normals, pixels;
# measured on the three cases); 1024 ulps is 2x the largest.
PROBE_ULPS_E2E = 1024
N_PROBES = 32


def _capture_searches(monkeypatch):
    """Record every torch specular_flow call of a warp: [(args, kwargs, result)]."""
    from ibr_pipeline.raytree import warp as warp_mod
    calls, real = [], warp_mod.specular_flow

    def spy(*a, **k):
        r = real(*a, **k)
        calls.append((a, k, r))
        return r
    monkeypatch.setattr(warp_mod, "specular_flow", spy)
    return calls, real


def _probe(flow, call, ulps, size):
    """Decision margin of the torch search, measured: rerun it N_PROBES times with w, n and q_d
    moved by up to `ulps` float32 ulps of their scale (|w|, 1, the crop's larger side in pixels).
    Returns unstable (M,) (Delta <= eps changed under some probe) and spread (M,) (largest change
    of the final Delta)."""
    a, k, res = call
    E0 = res.energy.numpy()
    g = torch.Generator().manual_seed(0)
    w, n, qd = a[0], a[1], a[4]
    scale = {0: w.norm(dim=-1, keepdim=True), 1: 1.0, 4: float(max(size))}
    unstable, spread = np.zeros(len(E0), bool), np.zeros(len(E0))
    for _ in range(N_PROBES):
        ap = list(a)
        for j, x in ((0, w), (1, n), (4, qd)):
            ap[j] = x + ulps * F32 * scale[j] * (2 * torch.rand(x.shape, generator=g) - 1)
        Ep = flow(*ap, **k).energy.numpy()
        unstable |= (Ep <= EPS_RAD) != (E0 <= EPS_RAD)
        spread = np.maximum(spread, np.abs(Ep - E0))
    return unstable, spread


def test_specular_search_matches_torch(case, monkeypatch):
    """Per-pixel specular search (§3.4) of both backends on identical inputs (torch's w, n, q_d,
    node crop and quad table): outside the measured margin the decision Delta <= eps is the same
    for every pixel and Delta agrees within the probes' own spread; inside it, few pixels."""
    from ibr_pipeline.raytree.warp import _node_tables
    calls, flow = _capture_searches(monkeypatch)
    dec = decode(case.tree, backend="torch")
    warp_decoded(dec, case.new, TO, record_history=True)
    s = TO.specular
    by_ws = {id(_node_tables(dec, i, s.rel_tol, s.div_tol)[1]): i for i in range(1, case.tree.n_nodes)}
    assert calls
    for call in calls:
        a, _, res = call
        w, n, c_new, eta, qd, Ws, _, _, P_c = a[:9]
        i = by_ws[id(Ws)]
        T = warp_nb.node_tables(dec, i, s.rel_tol, s.div_tol)
        e = np.ones(len(w), np.float32) if eta is None else eta.numpy()
        out = warp_nb.ns.specular_search(
            w.numpy(), n.numpy(), e, eta is None, qd.numpy(), T["Ws"], T["delta"], T["valid"],
            a[10].quad_ok.numpy(), T["rgb"], T["W"], T["H"], P_c.numpy().astype(np.float64),
            c_new.numpy().astype(np.float64), T["med"], T["has_med"], s.steps, EPS_RAD,
            float(s.step_scale), float(s.max_step_px), float(s.min_step_px), int(s.snap_radius), False)
        En, Et = out[1], res.energy.numpy()
        unstable, spread = _probe(flow, call, PROBE_ULPS_SAME, (T["W"], T["H"]))
        st = ~unstable
        assert np.array_equal(En[st] <= EPS_RAD, Et[st] <= EPS_RAD), (i, np.flatnonzero(st & ((En <= EPS_RAD) != (Et <= EPS_RAD))))
        # measured: |En - Et| <= 1.06 x spread on every stable pixel of the three cases
        assert (np.abs(En - Et)[st] <= 4 * np.maximum(spread[st], 8 * F32)).all()
        assert unstable.mean() <= 0.03   # measured 0.02-0.86 %


def test_warp_matches_torch(case, monkeypatch):
    calls, flow = _capture_searches(monkeypatch)
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
    # the per-pixel specular search end to end: same searched pixels; the decision Delta <= eps
    # differs only inside the margin measured on torch's inputs (numba's come from its own
    # diffuse flow, hence the wider probe), and the final Delta mostly within float precision
    assert set(rn.history) == set(rt.history) and len(calls) == len(rt.history)
    for i, call in zip(rn.history, calls):
        pn, hn, En = rn.history[i]
        pt, ht, Et = rt.history[i]   # torch lists the fixed-point fallback pixels last
        on = np.argsort(pn[:, 1] * 100000 + pn[:, 0])
        ot = np.argsort(pt[:, 1] * 100000 + pt[:, 0])
        assert np.array_equal(pn[on], pt[ot]) and hn.shape == ht.shape
        En = np.empty_like(En)
        En[ot] = rn.history[i][2][on]   # numba's result in torch's pixel order
        Wc, Hc = call[0][5].shape[1], call[0][5].shape[0]
        unstable, _ = _probe(flow, call, PROBE_ULPS_E2E, (Wc, Hc))
        flip = (En <= EPS_RAD) != (Et <= EPS_RAD)
        assert not (flip & ~unstable).any(), np.flatnonzero(flip & ~unstable)
        assert unstable.mean() <= 0.05   # measured 0.5-2.1 %
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
    # the trees differ by the decoders' float32 vs float64 normals (test_decode_matches_torch):
    # radiance within ~80 float32 ulps of 1 for most pixels, as the other backend comparisons
    assert np.median(d) < 1e-5 and (d > 1e-3).mean() < 5e-3


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
