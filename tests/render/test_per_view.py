"""render_views.renderer.visibility: the fuzzy depth test (§5.1.3) against per-view z-buffering
when one view's mesh is wrong, as multi-view stereo of photographs often is."""
import dataclasses

import numpy as np

from ibr_pipeline.metrics import psnr
from ibr_pipeline.render.ibr import IBRModel, LayerData, RenderSettings, ViewData
from ibr_pipeline.scene import Camera

W, H, Z = 96, 72, 2.0   # image size; the textured wall is the plane z = Z


def _texture(x, y):
    return np.stack([0.5 + 0.4 * np.sin(9 * x) * np.cos(7 * y), 0.5 + 0.4 * np.cos(11 * x + 2 * y),
                     0.5 + 0.3 * np.sin(5 * y)], -1)


def _camera(cx):
    return Camera.look_at([cx, 0, 0], [cx, 0, Z], [0, -1, 0], Camera.intrinsics_from_fov(W, H, 60), W, H)


def _photo(cam):
    """The wall seen by `cam` (ray-plane intersection) and the wall points of its pixels."""
    uv = cam.pixel_grid().reshape(-1, 2)
    rays = np.linalg.solve(cam.K, np.c_[uv, np.ones(len(uv))].T).T @ cam.R
    o = cam.center
    t = (Z - o[2]) / rays[:, 2]
    X = o + rays * t[:, None]
    return _texture(X[:, 0], X[:, 1]).reshape(H, W, 3).astype(np.float32), X.reshape(H, W, 3)


def _view(name, cam, depth_factor=1.0):
    """A per-view grid mesh of the wall; depth_factor < 1 pulls it towards the camera (wrong
    geometry: each vertex stays on its pixel's ray, as a wrong MVS depth does)."""
    img, X = _photo(cam)
    X = cam.center + (X - cam.center) * depth_factor
    idx = np.arange(H * W).reshape(H, W)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.r_[np.c_[a, c, b], np.c_[b, c, d]]
    layer = LayerData(X.reshape(-1, 3), faces, img, np.ones((H, W), np.float32))
    return ViewData(name, cam, (layer, None))


def test_per_view_visibility_survives_a_view_with_wrong_geometry():
    good, bad, novel = _camera(-0.10), _camera(0.10), _camera(0.02)
    truth, _ = _photo(novel)
    views = [_view("good", good), _view("bad", bad, depth_factor=0.8)]
    scores = {}
    for vis in ("fuzzy", "per_view"):
        s = dataclasses.replace(RenderSettings(), visibility=vis, max_dist=10.0, feather_px=0.0)
        m = IBRModel(views, s)
        f = m.render(novel)
        m.release()
        assert set(f.selected) == {"good", "bad"}
        scores[vis] = psnr(truth, np.clip(f.color, 0, 1))
    # fuzzy: the wrong mesh is in front, so only its (misplaced) texture passes the depth test;
    # per view, the good view keeps its share of the blend
    assert scores["per_view"] > scores["fuzzy"] + 1.0, scores
    # with correct geometry everywhere the two agree
    views = [_view("good", good), _view("bad", bad)]
    out = []
    for vis in ("fuzzy", "per_view"):
        m = IBRModel(views, dataclasses.replace(RenderSettings(), visibility=vis, max_dist=10.0))
        out.append(np.clip(m.render(novel).color, 0, 1))
        m.release()
    assert psnr(out[0], out[1]) > 40
