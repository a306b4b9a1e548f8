"""Eq. 14 view distance and §5.1.2 view selection (72 sub-regions, limits, hysteresis)."""
import math

import numpy as np
import pytest

from ibr_pipeline.render import selection


def test_view_distance_matches_eq14_by_hand():
    axes = np.array([[0, 0, 1.0], [1.0, 0, 0], [0, 0, 1.0]])
    centers = np.array([[2.0, 0, 0], [2.0, 0, 0], [2.0, 1.0, 0]])
    d = selection.view_distance(axes, centers, np.array([0, 0, 1.0]), np.array([2.0, 0, 0]),
                                lam=1.0, scene_depth=4.0)
    # same pose: 0; 90° turn: π/2; 1 sideways at a scene depth of 4: the parallax angle 1 / 4
    assert d == pytest.approx([0.0, math.pi / 2, 0.25])


def test_view_distance_does_not_depend_on_the_origin_or_the_units():
    rng = np.random.default_rng(1)
    centers = rng.uniform(-1, 1, (20, 3))
    axes = rng.normal(size=(20, 3))
    axis_n, center_n = np.array([0.1, 0, 1.0]), np.array([0.2, -0.1, 0.3])
    d = selection.view_distance(axes, centers, axis_n, center_n, scene_depth=2.5)
    shift = np.array([40.0, -7.0, 3.0])  # the same capture in a frame with its origin elsewhere
    assert selection.view_distance(axes, centers + shift, axis_n, center_n + shift,
                                   scene_depth=2.5) == pytest.approx(d)
    # and in millimetres, with its scene depth in millimetres
    assert selection.view_distance(axes, 1000 * centers, axis_n, 1000 * center_n,
                                   scene_depth=2500.0) == pytest.approx(d)
    with pytest.raises(ValueError, match="scene_depth"):
        selection.view_distance(axes, centers, axis_n, center_n, scene_depth=0.0)


def test_view_distance_rejects_bad_shapes():
    with pytest.raises(ValueError, match="shape|must"):
        selection.view_distance(np.zeros((3, 2)), np.zeros((3, 2)), np.zeros(3), np.zeros(3))


def _ring(n=200, seed=0):
    rng = np.random.default_rng(seed)
    centers = rng.uniform(-1.5, 1.5, (n, 3))
    yaw = rng.uniform(-0.8, 0.8, n)
    axes = np.stack([np.sin(yaw), np.zeros(n), np.cos(yaw)], 1)
    return centers, axes


def test_one_view_per_sub_region_and_limits():
    centers, axes = _ring()
    R = np.eye(3)
    c = np.zeros(3)
    d = selection.view_distance(axes, centers, R[2], c)
    sel = selection.select_views(R, c, axes, centers, d)
    region = selection.sub_regions(R, c, axes, centers)
    assert len(sel) <= 72
    regs = region[sel]
    assert (regs >= 0).all() and len(set(regs.tolist())) == len(sel)  # one per sub-region
    for r in set(region[region >= 0].tolist()):  # ...and the one of smallest d_k
        members = np.flatnonzero(region == r)
        assert members[np.argmin(d[members])] in sel
    ang = selection.axis_angle_deg(axes[sel], R[2])
    assert (ang <= 30 + 1e-9).all() and (np.linalg.norm(centers[sel], axis=1) <= 1.8 + 1e-9).all()


def test_hysteresis_keeps_previous_views_within_widened_limits():
    centers, axes = _ring()
    R0, c0 = np.eye(3), np.zeros(3)
    d0 = selection.view_distance(axes, centers, R0[2], c0)
    sel0 = selection.select_views(R0, c0, axes, centers, d0)
    c1 = np.array([0.05, 0, 0])  # small motion: previous views mostly still within the limits
    d1 = selection.view_distance(axes, centers, R0[2], c1)
    plain = selection.select_views(R0, c1, axes, centers, d1)
    kept = selection.select_views(R0, c1, axes, centers, d1, previous=(R0, c0, sel0))
    assert set(plain) <= set(kept)
    extra = set(kept) - set(plain)
    assert extra <= set(sel0)
    for k in extra:  # limits widened by the motion (0° and 5 cm)
        assert np.linalg.norm(centers[k] - c1) <= 1.8 + 0.05 + 1e-9


def test_fallback_when_nothing_within_limits():
    centers = np.array([[10.0, 0, 0], [20.0, 0, 0], [30.0, 0, 0]])
    axes = np.tile([0, 0, 1.0], (3, 1))
    d = selection.view_distance(axes, centers, np.array([0, 0, 1.0]), np.zeros(3))
    sel = selection.select_views(np.eye(3), np.zeros(3), axes, centers, d, fallback=2)
    assert sel == [0, 1]


def test_scene_depth_without_a_measured_one_is_the_global_mesh_seen_by_the_cameras(tiny_scene,
                                                                                  tmp_path):
    """A workspace whose poses report has no median scene depth (a ground-truth workspace):
    Eq. 14's D is the median depth of G in its cameras, and the renderer, the naive warp and
    the web viewer take the same one."""
    from ibr_pipeline import layout as L
    from ibr_pipeline.gt_workspace import write_gt_workspace
    from ibr_pipeline.render.ibr import RenderSettings, resolve_settings, workspace_scene_depth
    from ibr_pipeline.render.oracle import GroundTruth
    ws = write_gt_workspace(tiny_scene[0], tmp_path / "ws", "global_mesh")
    assert L.poses_report(ws).get("median_scene_depth") is None
    d = workspace_scene_depth(ws)
    gt = GroundTruth(tiny_scene[0])
    z = [np.median(g[g > 0]) for g in (gt.geom(n)["depth"] for n in gt.cameras)]
    assert d == pytest.approx(float(np.median(z)), rel=0.15)  # G is the GT surface, fused
    assert resolve_settings(ws, RenderSettings()).scene_depth == d
