"""The GL renderer against the numpy reference formulas, and against ground truth."""
from pathlib import Path

import numpy as np
import pytest

from ibr_pipeline import metrics
from ibr_pipeline.io.images import read_image
from ibr_pipeline.render import blend
from ibr_pipeline.render.oracle import GroundTruth
from ibr_pipeline.scene import cameras_from_json


@pytest.fixture(scope="module")
def tiny(tiny_scene):
    root = tiny_scene[0]
    gt = GroundTruth(root)
    return root, gt, gt.model(layers=True), cameras_from_json(root / "gt" / "test_cameras.json")


def test_gl_blend_matches_numpy_reference(tiny):
    root, gt, model, test = tiny
    m = model.with_settings(fill_holes=False)
    cam = test["test_000.png"]
    frame = m.render(cam)
    sel, d = m.select(cam)
    per = [m.render_single_view(cam, k) for k in sel]
    # GL cost shader vs blend.ibr_cost on the unprojected GL depth
    for k, p in zip(sel, per):
        cov = p["covered"]
        x = cam.unproject(cam.pixel_grid()[cov], p["z"][cov])
        ref_cost = blend.ibr_cost(m.views[k].camera.center, cam.center, x)
        assert np.percentile(np.abs(ref_cost - p["cost"][cov]), 99) < 2e-3
    Z = np.stack([p["z"] for p in per])
    front, contrib = blend.fuzzy_depth_test(Z, np.stack([p["cost"] for p in per]))
    W = contrib * blend.view_weights(d[sel])[:, None, None] * np.stack([p["alpha"] for p in per])
    color, wsum = blend.blend(np.stack([p["rgb"] for p in per]), W)
    both = (wsum > 0) & frame.covered
    assert (frame.covered == (wsum > 0)).mean() > 0.995
    assert (np.abs(frame.depth - front)[both] < 1e-3).mean() > 0.99
    assert (np.abs(frame.color - color)[both].max(-1) < 2 / 255).mean() > 0.99
    # no pixel left uncovered where any selected view saw a surface
    assert frame.covered[(Z > 0).any(0)].all()


def test_self_render_reproduces_capture_view(tiny):
    root, gt, model, _ = tiny
    name = "0000.png"
    frame = model.render(gt.cameras[name])
    ref = read_image(root / "images" / name)
    assert frame.selected[0] == name
    assert frame.covered.mean() > 0.95  # the outermost half pixel is outside the grid mesh
    assert metrics.psnr(ref, frame.color) > 30.0
    depth = gt.geom(name)["depth"]
    ok = frame.depth > 0
    assert np.median(np.abs(frame.depth[ok] - depth[ok])) < 0.01


def _seen_by(root, test_name, cam, names) -> np.ndarray:
    """(H, W) bool: the test camera's GT surface point is inside, and not occluded in, one of the
    captured views `names` (GT depth of both; 2 % + 1 cm depth tolerance)."""
    d = np.load(root / "gt" / "test" / "geom" / f"{Path(test_name).stem}.npz")["depth"]
    pts = cam.unproject(cam.pixel_grid().reshape(-1, 2), d.ravel().astype(np.float64))
    caps = cameras_from_json(root / "cameras.json")
    seen = np.zeros(len(pts), bool)
    for n in names:
        c = caps[n]
        dk = np.load(root / "gt" / "geom" / f"{Path(n).stem}.npz")["depth"]
        uv, z = c.project(pts)
        u, v = np.round(np.nan_to_num(uv)).astype(int).T
        ok = (z > 0) & (u >= 0) & (u < c.width) & (v >= 0) & (v < c.height)
        ok[ok] &= np.abs(dk[v[ok], u[ok]] - z[ok]) < 0.02 * z[ok] + 0.01
        seen |= ok
    return seen.reshape(d.shape) & (d > 0)


def test_heldout_views_against_ground_truth(tiny):
    root, gt, model, test = tiny
    for name, cam in test.items():
        frame = model.render(cam)
        ref = read_image(root / "gt" / "test" / "images" / name)
        assert frame.color.shape == ref.shape and np.isfinite(frame.color).all()
        # covered wherever a selected view saw the surface, from GT depth and cameras
        seen = _seen_by(root, name, cam, frame.selected)
        assert seen.mean() > 0.3
        assert frame.covered[seen].mean() > 0.97
        assert metrics.psnr(ref, frame.color, frame.covered) > 26.0  # where a view saw the surface
        assert (frame.color.max(-1) > 0).mean() > 0.999  # holes are filled, nothing black


def test_two_layers_beat_single_layer_in_the_mirror(sample_scene):
    gt = GroundTruth(sample_scene)
    names = ["0000.png", "0001.png", "0002.png", "0003.png", "0023.png"]
    two = gt.model(layers=True, names=names)
    one = gt.model(layers=False, names=names)
    n = "0001.png"
    ref = read_image(sample_scene / "images" / n)
    mirror = read_image(sample_scene / "gt" / "beta" / n)[..., 0] > 0.5
    assert mirror.sum() > 1000
    p2 = metrics.psnr(ref, two.render(gt.cameras[n], exclude=(n,)).color, mirror)
    p1 = metrics.psnr(ref, one.render(gt.cameras[n], exclude=(n,)).color, mirror)
    assert p2 > p1 + 3.0
    two.release()
    one.release()


def test_oracle_views_built_in_workers_match_in_process(tiny):
    """GroundTruth.submit_model on a 2-worker pool (evaluate's oracle) builds each view in a
    worker process: the same meshes, textures, alphas and betas, in the same order, as the
    in-process build."""
    from ibr_pipeline.executors import LocalExecutor
    root, gt, model, _ = tiny
    names = list(gt.cameras)[:3]
    one = gt.model(layers=True, names=names)
    with LocalExecutor(2) as ex:
        two = gt.submit_model(ex.submit, layers=True, names=names)()
    assert [v.name for v in two.views] == [v.name for v in one.views] == names
    for a, b in zip(one.views, two.views):
        assert len(a.layers) == len(b.layers)
        for la, lb in zip(a.layers, b.layers):
            assert (la is None) == (lb is None)
            if la is None:
                continue
            np.testing.assert_array_equal(la.vertices, lb.vertices)
            np.testing.assert_array_equal(la.faces, lb.faces)
            np.testing.assert_array_equal(la.rgb, lb.rgb)
            np.testing.assert_array_equal(la.beta, lb.beta)
            np.testing.assert_array_equal(la.alpha, lb.alpha)
    one.release()
    two.release()


def test_model_of_the_needed_views_renders_as_the_model_of_all(sample_scene):
    """evaluate builds the oracle of only the views the renderer selects for its cameras
    (views_needed): that model selects the same views and renders the same pixels as the model
    of every view, also for leave-one-out cameras."""
    from dataclasses import replace

    from ibr_pipeline.render.ibr import RenderSettings, views_needed
    gt = GroundTruth(sample_scene)
    names = list(gt.cameras)
    s = replace(RenderSettings(), scene_depth=1.3)
    test = cameras_from_json(sample_scene / "gt" / "test_cameras.json")
    frames = [(c, ()) for c in test.values()] + [(gt.cameras[n], (n,)) for n in names[::6]]
    needed = views_needed(gt.cameras, s, frames)
    assert 0 < len(needed) < len(names) and needed == [n for n in names if n in needed]
    full = gt.model(layers=True, settings=s)
    part = gt.model(layers=True, settings=s, names=needed)
    for cam, excl in frames:
        a, b = full.render(cam, exclude=excl), part.render(cam, exclude=excl)
        assert a.selected == b.selected and not set(excl) & set(a.selected)
        np.testing.assert_array_equal(a.color, b.color)
    full.release()
    part.release()
    with pytest.raises(ValueError, match="scene_depth"):
        views_needed(gt.cameras, RenderSettings(), frames)
