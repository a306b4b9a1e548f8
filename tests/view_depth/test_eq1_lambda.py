"""Eq. 1's lambda per view: Xu's 0.01 where G was fused from depth frames, lambda_rel_mvs where it
came from multi-view stereo (the view has an MVS depth map from global_mesh)."""
from dataclasses import dataclass

import numpy as np

from ibr_pipeline import layout as L
from ibr_pipeline.geometry import depth_edges as de
from ibr_pipeline.stages.common import eq1_lambda
from ibr_pipeline.stages.view_depth import ViewDepthConfig
from ibr_pipeline.stages.view_mesh import ViewMeshConfig
from ibr_pipeline.workspace import Workspace


@dataclass
class _Ctx:
    ws: Workspace
    config: object


def test_lambda_follows_the_source_of_g(tmp_path):
    ws = Workspace(tmp_path)
    (tmp_path / L.MVS_DEPTH_DIR).mkdir(parents=True)
    np.save(tmp_path / L.mvs_depth_file("b.png"), np.ones((2, 2), np.float32))
    for cfg in (ViewDepthConfig(), ViewMeshConfig()):
        assert cfg.lambda_rel == de.LAMBDA_REL == 0.01 and cfg.lambda_rel_mvs == de.LAMBDA_REL_MVS
        assert de.LAMBDA_REL_MVS > de.LAMBDA_REL
        ctx = _Ctx(ws, cfg)
        assert eq1_lambda(ctx, "a.png") == cfg.lambda_rel        # no MVS depth: RGB-D G
        assert eq1_lambda(ctx, "b.png") == cfg.lambda_rel_mvs    # MVS G


def test_mvs_lambda_ignores_noise_but_keeps_occlusions():
    """A fronto-parallel wall at depth 3 with 2 % depth noise (about what our MVS G has) and a box
    10 % in front of it: Xu's 1 % marks edges all over the noisy wall, the MVS lambda only the box's
    outline."""
    from ibr_pipeline.geometry.normals import normals_from_points, points_from_depth
    from ibr_pipeline.scene import Camera
    rng = np.random.default_rng(0)
    H, W = 60, 80
    depth = 3.0 * (1 + 0.02 * rng.standard_normal((H, W)) / np.sqrt(2))
    depth[20:40, 30:50] = 2.7
    K = Camera.intrinsics_from_fov(W, H, 60)
    P = points_from_depth(depth, K)
    N = normals_from_points(P, depth > 0)
    outline = np.zeros((H, W), bool)
    outline[19:41, 29:51] = True
    outline[21:39, 31:49] = False
    wall = ~outline & ~np.pad(np.ones((18, 18), bool), ((21, 21), (31, 31)))
    xu = de.depth_edges(P, N, depth, de.LAMBDA_REL).pixels()
    mvs = de.depth_edges(P, N, depth, de.LAMBDA_REL_MVS).pixels()
    assert xu[wall].mean() > 0.3 and mvs[wall].mean() < 0.03, (xu[wall].mean(), mvs[wall].mean())
    assert mvs[outline].mean() > 0.9
