"""Plane RANSAC of reflector detection (geometry/ransac_nb.py, planes.ransac_planes): the numba
inlier count against its numpy reference, planes recovered through outliers, and two surfaces
closer than the inlier distance giving the plane of one of them, not one tilted between both."""
from __future__ import annotations

import numpy as np
import pytest

from ibr_pipeline.geometry.planes import ransac_planes
from ibr_pipeline.geometry.ransac_nb import best_plane, count_inliers, count_inliers_np, hypotheses


def _rect(rng, n, x, z, y):
    """n points uniform on the rectangle x0..x1, z0..z1 at height y (a plane y = const)."""
    return np.c_[rng.uniform(*x, n), np.full(n, y), rng.uniform(*z, n)]


def test_count_matches_the_numpy_reference():
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(5000, 3))
    planes = hypotheses(pts, rng.integers(0, len(pts), (200, 3)))
    planes[::17] = 0.0  # no plane
    planes[5] = [0.0, 0.0, 1.0, -0.25]
    got = count_inliers(pts, planes, 0.05)
    assert np.array_equal(got, count_inliers_np(pts, planes, 0.05))
    assert (got[::17] == -1).all() and (got[1:17] >= 3).all()  # a hypothesis counts its 3 points
    assert got[5] == int(np.count_nonzero(np.abs(pts[:, 2] - 0.25) < 0.05))


def test_degenerate_triples_are_no_plane():
    pts = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0]])
    planes = hypotheses(pts, np.array([[0, 1, 2], [0, 0, 3], [0, 1, 3]]))
    assert np.all(planes[:2] == 0.0)
    assert np.allclose(np.abs(planes[2]), [0, 0, 1, 0])


def test_best_plane_through_outliers():
    rng = np.random.default_rng(0)
    wall = _rect(rng, 3000, (0, 2), (0, 1), 0.5) + rng.normal(0, 0.001, (3000, 3)) * [0, 1, 0]
    pts = np.r_[wall, rng.uniform(-1, 3, (2000, 3))]
    pl, idx = best_plane(pts, 0.008, 300, np.random.default_rng(1))
    n = pl[:3] * np.sign(pl[1])
    assert np.degrees(np.arccos(min(1.0, n[1]))) < 1.0 and abs(abs(pl[3]) - 0.5) < 0.008
    assert set(range(3000)) <= set(idx.tolist())  # every wall point (noise 1 mm) is an inlier
    assert len(idx) < 3000 + 2000 * 0.05
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        best_plane(np.zeros((10, 2)), 0.01, 10, np.random.default_rng(0))


def test_two_close_surfaces_give_one_of_them():
    """A screen 5 mm in front of the body it sits on (the synthetic TV): both fall in one
    inlier band; the candidate's plane is one surface, parallel, not a plane between them."""
    rng = np.random.default_rng(2)
    body = _rect(rng, 4000, (0, 1.1), (0, 0.7), 0.060)
    screen = _rect(rng, 3000, (0.05, 1.05), (0.05, 0.65), 0.065)
    floor = np.c_[rng.uniform(-1, 2, 8000), rng.uniform(0.5, 2, 8000), np.zeros(8000)]
    out = ransac_planes(np.r_[body, screen, floor], distance=0.008, max_planes=4, min_points=200)
    near = [c for c in out if abs(c["plane"][1]) > 0.9]
    assert len(near) == 1, [np.round(c["plane"], 4) for c in out]
    pl = near[0]["plane"] * np.sign(near[0]["plane"][1])
    assert np.degrees(np.arccos(min(1.0, pl[1]))) < 0.05, pl
    assert min(abs(pl[3] + 0.060), abs(pl[3] + 0.065)) < 0.0005, pl
    floors = [c for c in out if abs(c["plane"][2]) > 0.9]
    assert len(floors) == 1 and abs(floors[0]["plane"][3]) < 1e-9


def test_same_seed_same_planes():
    rng = np.random.default_rng(4)
    pts = np.r_[_rect(rng, 2000, (0, 1), (0, 1), 0.0), rng.uniform(-1, 1, (1000, 3))]
    a = ransac_planes(pts, max_planes=3, seed=7)
    b = ransac_planes(pts, max_planes=3, seed=7)
    assert len(a) == len(b) >= 1
    for x, y in zip(a, b):
        assert np.array_equal(x["plane"], y["plane"]) and x["count"] == y["count"]
