"""Issue #5, step one of Xu §4.2.2: the geometric check of the masked MVS against G
(`depth_refine.near_consistency`) and the NCC edge guard (`depth_refine.edge_guard`)."""
from __future__ import annotations

import numpy as np
import pytest

from ibr_pipeline.geometry import depth_refine as dr
from ibr_pipeline.scene import Camera

W, H = 64, 48


def _cams(baseline=0.2):
    K = Camera.intrinsics_from_fov(W, H, 60.0)
    ref = Camera(K, np.eye(4), W, H)
    T = np.eye(4)
    T[0, 3] = -baseline  # source centre at x = +baseline (cam_from_world translation = -C)
    return ref, Camera(K, T, W, H)


def _projected_column(ref, src, y, x, z):
    X = np.linalg.inv(ref.K) @ np.array([x * z, y * z, z])
    Xs = src.cam_from_world[:3, :3] @ X + src.cam_from_world[:3, 3]
    p = src.K @ Xs
    return p[0] / p[2], p[1] / p[2]


def test_near_consistency_accepts_surfaces_and_rejects_5_percent_off():
    ref, src = _cams()
    src_depth = np.full((H, W), 2.0)  # wall z = 2 (fronto-parallel in both views)
    d = np.full((H, W), 2.0)
    n = dr.near_consistency(ref, d, [src], [src_depth], 0.05, 1)
    us = np.array([_projected_column(ref, src, 0, x, 2.0)[0] for x in range(W)])
    inside = (us >= 0.5) & (us <= W - 1.5)  # projects well inside the source
    assert (n[:, inside] == 1).all() and inside.sum() > W // 2
    assert (n[:, us < -2] == 0).all()  # outside the source: no evidence
    off = dr.near_consistency(ref, np.full((H, W), 2.0 * 1.08), [src], [src_depth], 0.05, 1)
    assert not off.any()  # 8 % in front of every G surface: rejected (Xu's 5 %)
    assert not dr.near_consistency(ref, np.zeros((H, W)), [src], [src_depth]).any()


def test_near_consistency_tolerates_a_misplaced_g_edge():
    """G's edge in the source is one pixel off: the strict test (radius 0) rejects the correct
    background depth next to it, the 1 px tolerance accepts it; a wrong depth stays rejected."""
    ref, src = _cams()
    y, x, z = 24, 20, 2.0
    u, v = _projected_column(ref, src, y, x, z)
    u0 = int(round(u))
    src_depth = np.full((H, W), 2.0)
    src_depth[:, :u0 + 1] = 1.0  # G's foreground reaches one pixel too far, over the projection
    d = np.zeros((H, W))
    d[y, x] = z
    assert dr.near_consistency(ref, d, [src], [src_depth], 0.05, 0)[y, x] == 0
    assert dr.near_consistency(ref, d, [src], [src_depth], 0.05, 1)[y, x] == 1
    d[y, x] = 1.5  # on no G surface near the projection
    assert dr.near_consistency(ref, d, [src], [src_depth], 0.05, 1)[y, x] == 0
    with pytest.raises(ValueError):
        dr.near_consistency(ref, d, [src], [], 0.05, 1)


def test_edge_guard_only_inside_the_mvs_depth():
    ref, _ = _cams()
    d = np.zeros((H, W))
    d[:, 10:30] = 1.0  # MVS foreground
    d[:, 30:50] = 2.0  # MVS background: an edge between two MVS depths at 29 | 30
    g = dr.edge_guard(d, 3, ref)
    cols = np.flatnonzero(g.any(0))
    assert cols.min() == 26 and cols.max() == 33  # both pixels of the pair, dilated by 3
    # an MVS depth next to pixels without one (where G is kept) is not guarded
    assert not g[:, :20].any() and not g[:, 40:].any()
    assert not dr.edge_guard(d, 0, ref).any()
    flat = np.where(np.arange(W)[None, :] < 40, 1.5, 0.0) * np.ones((H, 1))
    assert not dr.edge_guard(flat, 3, ref).any()


def test_guard_keeps_confirmed_g_depth_only_where_protected(monkeypatch):
    """Step 4's guard around an MVS noise spike: without `protect` it drops the G depth the MVS
    confirmed around the spike; with it, the confirmed G depth survives where protected and the
    spike itself (an MVS depth, not G's) is still dropped."""
    from types import SimpleNamespace

    from ibr_pipeline.geometry import mvs

    ref, src = _cams()
    g = np.full((H, W), 1.0)                       # G: a wall at 1 m (lambda = 1 cm)
    photo = g * (1 + 0.002)                        # the MVS agrees with G within 1.5 lambda...
    photo[24, 20] = photo[24, 44] = 1.03           # ...but for two spikes 3 cm off (within 5 %)
    monkeypatch.setattr(mvs, "plane_sweep", lambda *a, **k: SimpleNamespace(depth=photo, valid=np.ones((H, W), bool)))
    img = np.zeros((H, W, 3))
    mask = np.ones((H, W), bool)
    kw = dict(guard_px=3, min_change=1.5, check_radius=1)
    plain = dr.masked_mvs(img, ref, g, mask, [img], [src], [g], **kw)
    protect = np.zeros((H, W), bool)
    protect[:, :32] = True                         # G reliable on the left half only
    prot = dr.masked_mvs(img, ref, g, mask, [img], [src], [g], protect=protect, **kw)
    win = lambda x: (slice(21, 28), slice(x - 3, x + 4))  # noqa: E731  the guard's 7x7 window
    for r in (plain, prot):
        assert r.accepted[10, 20] and r.accepted[10, 44]                # away from the spikes: kept
        assert not r.accepted[24, 20] and not r.accepted[24, 44]       # the spikes: dropped
        assert not r.accepted[win(44)].any()                            # unprotected: all dropped
    assert not plain.accepted[win(20)].any()
    keep = prot.accepted[win(20)]
    assert keep.sum() == 48 and np.allclose(prot.depth[win(20)][keep], 1.0)  # G's depth kept
    with pytest.raises(ValueError):
        dr.masked_mvs(img, ref, g, mask, [img], [src], [g], protect=protect[:, :10], **kw)
