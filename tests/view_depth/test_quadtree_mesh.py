"""view_mesh v3: planar pre-merge of the cut pixel grid (geometry/quadtree_mesh.py). The merged
mesh must cover the same pixels as the grid mesh, render the same depth within the tolerance, keep
every cut, have no T-junction cracks, and be smaller where the view is planar."""
from __future__ import annotations

import numpy as np
import pytest

from ibr_pipeline.geometry import depth_edges as de
from ibr_pipeline.geometry.grid_faces import grid_faces, planar_leaves, quadtree_faces
from ibr_pipeline.geometry.grid_mesh import depth_error, grid_mesh, render_depth, simplify_adaptive
from ibr_pipeline.geometry.normals import normals_from_depth, pixel_rays, points_from_depth
from ibr_pipeline.scene import Camera
from ibr_pipeline.stages.view_mesh import ViewMeshConfig

PREMERGE = ViewMeshConfig().premerge_tol  # the stage's default

W, H = 131, 97   # not multiples of any block size: partial blocks at the right and bottom


def _cam():
    return Camera(Camera.intrinsics_from_fov(W, H, 60.0), np.eye(4), W, H)


def _scene():
    """A slanted wall (planar), a nearer box (planar, occlusion step), a curved bump, a hole
    with an isolated valid pixel in it."""
    cam = _cam()
    rays = pixel_rays(cam.K, H, W)
    d = 3.0 / (1 - 0.3 * rays[..., 0] + 0.1 * rays[..., 1])        # plane: 1/z affine in (u, v)
    d[20:60, 15:55] = 1.5                                           # fronto-parallel box
    yy, xx = np.mgrid[0:H, 0:W]
    r2 = ((xx - 100) ** 2 + (yy - 60) ** 2) / 15.0 ** 2
    bump = r2 < 1
    d[bump] = 2.0 - 0.3 * np.sqrt(1 - r2[bump])                     # a sphere cap: not planar
    d[70:80, 10:30] = 0.0
    d[75, 20] = 1.0
    return cam, d


def _edges(cam, d):
    P = points_from_depth(d, cam.K)
    return de.depth_edges(P, normals_from_depth(d, cam.K), d)


def _boundary_length(faces, w):
    """Total length (pixels) of the edges used by exactly one face."""
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    u, n = np.unique(e, axis=0, return_counts=True)
    b = u[n == 1]
    dy, dx = b[:, 0] // w - b[:, 1] // w, b[:, 0] % w - b[:, 1] % w
    return float(np.hypot(dx, dy).sum()), int((n > 2).sum())


def _signed_areas(faces, w):
    y, x = faces // w, faces % w
    return (x[:, 1] - x[:, 0]) * (y[:, 2] - y[:, 0]) - (x[:, 2] - x[:, 0]) * (y[:, 1] - y[:, 0])


@pytest.mark.parametrize("tol", [1e-4, 1e-3])
def test_premerge_is_a_crack_free_copy_of_the_grid_mesh(tol):
    cam, d = _scene()
    e = _edges(cam, d)
    g = grid_faces(d > 0, e)
    q, grid_used, rep = quadtree_faces(d, e, tol)
    assert len(q) < 0.25 * len(g)                      # the planes are merged ...
    assert rep["leaves"].get(2, 0) + rep["leaves"].get(4, 0) > 0 and max(rep["leaves"]) >= 16
    assert 0.5 < rep["merged_fraction"] < 1.0          # ... the bump is not (all of it)
    # same borders (cuts, frame, hole), no T-junction: a crack would add boundary length
    lg, bad_g = _boundary_length(g, W)
    lq, bad_q = _boundary_length(q, W)
    assert bad_g == bad_q == 0                         # manifold: no edge in 3 faces
    assert lq == pytest.approx(lg, abs=1e-6)
    # same orientation as the grid's faces, none degenerate
    ag, aq = _signed_areas(g, W), _signed_areas(q, W)
    assert (ag < 0).all() and (aq < 0).all()
    # the vertices the grid uses are reported exactly
    used_g = np.zeros(H * W, bool)
    used_g[g.reshape(-1)] = True
    assert np.array_equal(grid_used, used_g)
    # rendered: the same pixels covered, depth within ~2 tol of the grid mesh's
    v, f, gd0, _ = grid_mesh(d, cam, e, return_depth=True)
    vq, fq, gd, _ = grid_mesh(d, cam, e, return_depth=True, premerge_tol=tol)
    assert np.array_equal(gd, gd0)                     # the reported depth is the grid mesh's own
    rg, rq = render_depth(v, f, cam), render_depth(vq, fq, cam)
    assert np.array_equal(rg > 0, rq > 0)
    both = rg > 0
    rel = np.abs(rq[both] - rg[both]) / rg[both]
    assert rel.max() <= 2.5 * tol


def test_curved_depth_is_not_merged_at_a_tight_tolerance():
    cam, d = _scene()
    full = np.ones((H - 1, W - 1), bool)
    leaves = planar_leaves(d, full, 1e-5, 64)
    covered = np.zeros((H - 1, W - 1), bool)
    for s, org in leaves.items():
        for y0, x0 in org:
            covered[y0:y0 + s, x0:x0 + s] = True
    yy, xx = np.mgrid[0:H - 1, 0:W - 1]
    inner = ((xx - 100) ** 2 + (yy - 60) ** 2) < 10.0 ** 2       # well inside the sphere cap
    assert not covered[inner].any()
    assert covered[40:50, 25:45].all()                           # inside the box: merged
    # leaves never overlap
    count = np.zeros((H - 1, W - 1), int)
    for s, org in leaves.items():
        for y0, x0 in org:
            count[y0:y0 + s, x0:x0 + s] += 1
    assert count.max() == 1


def test_premerged_simplification_keeps_the_accuracy():
    """The adaptive simplification from the merged mesh ends within the same tolerance of the
    refined depth as from the full grid (its score is measured against the same reference)."""
    cam, d = _scene()
    e = _edges(cam, d)
    v, f, gd, _ = grid_mesh(d, cam, e, return_depth=True)
    vq, fq, _, _ = grid_mesh(d, cam, e, return_depth=True, premerge_tol=PREMERGE)
    ra = simplify_adaptive(v, f, cam, d, 2000, 50, 0.002, mesh_depth=gd)
    rb = simplify_adaptive(vq, fq, cam, d, 2000, 50, 0.002, mesh_depth=gd)
    base = depth_error(gd, d)["score"]
    for r in (ra, rb):   # rendered independently of the loop's own bookkeeping
        assert depth_error(render_depth(r.vertices, r.faces, cam), d)["score"] <= base + 0.002 + 1e-9
    assert len(rb.vertices) <= 1.25 * len(ra.vertices)   # no bloat from the fans


def test_bad_arguments():
    cam, d = _scene()
    with pytest.raises(ValueError):
        planar_leaves(d, np.ones((3, 3), bool))
    with pytest.raises(ValueError):
        planar_leaves(d, np.ones((H - 1, W - 1), bool), max_block=12)


def test_rasteriser_equals_the_ray_cast():
    """simplify_adaptive scores candidates with the numba scan converter; open3d's ray cast (the
    benchmark's measurement) is the independent reference: same covered pixels up to the
    re-cast slack, same depths."""
    from ibr_pipeline.geometry.rasterize import raster_depth

    cam, d = _scene()
    e = _edges(cam, d)
    v, f = grid_mesh(d, cam, e)
    res = simplify_adaptive(v, f, cam, d, 600, 50, 0.01)         # a coarse, irregular mesh
    rng = np.random.default_rng(0)
    for vv, ff, slack in ((v, f, 0.002), (res.vertices, res.faces, 0.002),
                          (v + rng.normal(0, 0.002, v.shape), f, 0.01)):  # jittered: off-centre
        rc, rr = render_depth(vv, ff, cam), raster_depth(vv, ff, cam)
        assert (rc > 0).sum() > 0.8 * d.size
        assert not ((rr > 0) & (rc == 0)).any()
        # the ray cast also counts pixels up to 0.01 px outside the mesh (its re-cast offsets),
        # the rasteriser 0.001 px: with vertices jittered by ~0.1 px a few border pixels differ
        assert ((rc > 0) & (rr == 0)).sum() <= slack * d.size
        both = (rc > 0) & (rr > 0)
        rel = np.abs(rr[both] - rc[both]) / rc[both]
        # float32 ray cast vs float64; slipped rays are re-cast 0.01 px off the centre, which
        # moves their depth by 0.01 px of the depth gradient: ~3e-5 on the slanted wall, more on
        # the sphere cap's rim
        assert np.median(rel) < 1e-6 and np.quantile(rel, 0.99) < 5e-5 and rel.max() < 2e-3
    _, _, gd, _ = grid_mesh(d, cam, e, return_depth=True)
    rr = raster_depth(v, f, cam)
    assert np.array_equal(rr > 0, gd > 0)                     # no slipped pixel centre at all
    assert np.allclose(rr, gd, rtol=1e-9)                     # and exactly the grid's depth
    with pytest.raises(ValueError):
        raster_depth(v - np.array([0, 0, 10.0]), f, cam)         # behind the camera


def test_report_counts_the_grid_faces():
    cam, d = _scene()
    e = _edges(cam, d)
    g = grid_faces(d > 0, e)
    _, fq, _, rep = grid_mesh(d, cam, e, return_depth=True, premerge_tol=PREMERGE)
    _, f0, _, rep0 = grid_mesh(d, cam, e, return_depth=True)
    assert rep["grid_faces"] == rep0["grid_faces"] == len(g) == len(f0) > len(fq)
