"""The view's own MVS depth in front of G (view_depth step 1b): a surface the fusion missed is
taken, MVS depth behind G (a reflection's virtual depth, a wrong match) and small regions are not."""
import json
import shutil

import numpy as np
import pytest

from ibr_pipeline import layout as L
from ibr_pipeline.geometry.depth_complete import mvs_in_front, view_mvs

H, W = 60, 80


def _maps():
    g = np.full((H, W), 3.0)
    g[:, :10] = 0.0                      # G empty: left to completion, never "in front"
    m = g.copy()
    m[10:30, 16:46] = 1.5                # a placard half-way to the camera: 600 px
    m[40:55, 50:75] = 6.0                # behind G (a mirror world): 375 px
    m[45:48, 20:23] = 1.0                # a 9 px speck in front
    m[4:8, 60:75] = 3.0 * 0.95           # 5 % in front only: 60 px
    return g, m


def test_regions_well_in_front_of_g_are_taken():
    g, m = _maps()
    d, front = mvs_in_front(g, m, rel=0.1, min_px=50)
    assert front.sum() == 600 and front[10:30, 16:46].all()
    assert np.array_equal(d[front], m[front])
    assert np.array_equal(d[~front], g[~front])          # behind, speck, 5 %, G-empty: G's
    assert (d[:, :10] == 0).all()


def test_small_regions_and_speckles_are_not_taken():
    g, m = _maps()
    _, front = mvs_in_front(g, m, rel=0.1, min_px=1)
    assert front[45:48, 20:23].all()                     # no size rule: the speck counts
    _, front = mvs_in_front(g, view_mvs(m, W, H, speckle_px=20), rel=0.1, min_px=1)
    assert not front[45:48, 20:23].any()                 # dropped as a speckle first
    _, front = mvs_in_front(g, m, rel=0.01, min_px=50)
    assert front[4:8, 60:75].all()                       # within rel of G decides


def test_mvs_map_at_another_size_is_resampled_and_shapes_are_checked():
    g, m = _maps()
    _, front = mvs_in_front(g, m[::2, ::2], rel=0.1, min_px=50)
    assert front[10:30, 16:46].all() and front.sum() == 600
    with pytest.raises(ValueError):
        mvs_in_front(g[0], m, 0.1, 50)
    with pytest.raises(ValueError):
        mvs_in_front(g, m[:, :30], 0.1, 50)              # another aspect


@pytest.fixture(scope="module")
def tiny_ws(tiny_scene, tmp_path_factory):
    from vd_fixtures import make_view_ws
    return make_view_ws(tiny_scene[0], tmp_path_factory.mktemp("front") / "ws")


def test_view_depth_takes_a_surface_g_misses(tiny_ws, tmp_path):
    """The stage on the tiny scene: an MVS map with a box at 0.6 x G's depth puts the box into
    depth.npy; depth_init.npy stays G; off (mvs_front_rel = 0) the box is not there."""
    from ibr_pipeline.cli import main
    from ibr_pipeline.geometry.grid_mesh import render_depth
    from ibr_pipeline.io.mesh import read_ply
    from ibr_pipeline.scene import cameras_from_json

    g_mesh = read_ply(tiny_ws / L.GLOBAL_MESH)
    cams = cameras_from_json(tiny_ws / L.REGISTERED_CAMERAS)
    name, g = max(((n, render_depth(g_mesh.vertices, g_mesh.faces, c)) for n, c in cams.items()),
                  key=lambda t: (t[1] > 0).mean())
    ys, xs = np.nonzero(g > 0)
    cy, cx = int(np.median(ys)), int(np.median(xs))
    box = (slice(cy - 12, cy + 12), slice(cx - 16, cx + 16))
    assert (g[box] > 0).all()
    mvs = g.astype(np.float32).copy()
    mvs[box] *= 0.6
    results = {}
    for rel in (0.1, 0.0):
        ws = tmp_path / f"ws{rel}"
        shutil.copytree(tiny_ws, ws)
        (ws / L.MVS_DEPTH_DIR).mkdir(parents=True, exist_ok=True)
        np.save(ws / L.mvs_depth_file(name), mvs)
        assert main(["view_depth", str(ws), "--no-progress", "--force",
                     "--mvs-front-rel", str(rel)]) == 0
        vd = ws / "views" / name
        results[rel] = (np.load(vd / "depth.npy"), np.load(vd / "depth_init.npy"),
                        json.loads((vd / "depth_report.json").read_text())["mvs_in_front"])
    (on, init_on, n_on), (off, init_off, n_off) = results[0.1], results[0.0]
    inner = (slice(box[0].start + 4, box[0].stop - 4), slice(box[1].start + 4, box[1].stop - 4))
    assert n_on >= 24 * 32 and n_off == 0
    # the box's outline is an Eq. 1 edge now: its 4 cm mask band is refined (Eq. 2), the inside kept
    assert np.mean(np.abs(on[inner] / mvs[inner] - 1) < 0.02) > 0.9
    assert np.median(np.abs(off[inner] / g[inner] - 1)) < 0.05      # G's surface without it
    both = (init_on > 0) & (g > 0)
    assert np.array_equal(init_on, init_off) and np.median(np.abs(init_on - g)[both]) < 1e-3
