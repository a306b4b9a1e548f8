"""Holes through a plane pooled over the views (geometry/plane_holes.py): a mirror that no view
sees whole, each view cutting it with its frame, is still one hole on the wall once the views'
evidence shares one grid; a plain wall, the space beyond a wall's edge and a shallow niche are
not holes; the result does not depend on the capture's unit of length."""
import numpy as np
import pytest

from ibr_pipeline.geometry.behind_detect import (BehindOptions, behind_outlines, find_candidates,
                                                 view_planes)
from ibr_pipeline.geometry.plane_holes import (find_plane_holes, grid_holes, pooled_grid,
                                               view_samples)
from ibr_pipeline.geometry.planes import plane_basis, ray_plane_hits
from ibr_pipeline.scene import Camera

K = np.array([[200.0, 0, 159.5], [0, 200.0, 119.5], [0, 0, 1]])
WALL = np.r_[np.array([0.12, 0.08, -1.0]) / np.linalg.norm([0.12, 0.08, -1.0]), 0.0]
CENTRE = np.array([0.3, 0.0, 3.2])
WALL[3] = -WALL[:3] @ CENTRE
HALF = (0.9, 0.6)  # the opening's half sizes along the wall's u and v axes
D = BehindOptions()


def _holes(cams, depths):
    """find_plane_holes with the stage's defaults and each view's planes."""
    planes = {n: view_planes(cams[n], d) for n, d in depths.items()}
    return find_plane_holes(cams, depths, planes, behind=D.behind, enclosed=D.enclosed)


def _views(scale=1.0, factor=1.6, half=HALF, edge=None, n=4):
    """Close views of the wall, each aimed at another corner of a 1.8 x 1.2 opening whose depth
    is `factor` x the wall's: every view cuts it with its frame. `edge`: the wall ends at
    u = edge, and beyond it everything is `factor` x deeper (no opening)."""
    origin, u, v = plane_basis(WALL)
    cams, depths = {}, {}
    for i in range(n):
        su, sv = (1 if i % 2 else -1), (1 if i // 2 else -1)
        aim = CENTRE + 0.6 * su * u + 0.4 * sv * v
        eye = np.array([0.3 + 0.2 * su, -0.1 * sv, 1.6])
        cam = Camera.look_at(eye * scale, aim * scale, (0, -1, 0), K, 320, 240)
        X, z = ray_plane_hits(cam, WALL * [1, 1, 1, scale])
        a, b = (X / scale - CENTRE) @ u, (X / scale - CENTRE) @ v
        rng = np.random.default_rng(i)
        d = z * (1 + 0.003 * rng.standard_normal(z.shape))
        if edge is None:
            d[(np.abs(a) < half[0]) & (np.abs(b) < half[1])] *= factor
        else:
            d[a > edge] *= factor
        d[rng.random(z.shape) < 0.1] = 0.0                  # MVS leaves some pixels empty
        cams[f"v{i}"], depths[f"v{i}"] = cam, d
    return cams, depths


def test_no_view_sees_the_opening_whole_so_no_view_outlines_it():
    cams, depths = _views()
    for n, cam in cams.items():
        for pl in view_planes(cam, depths[n]):
            assert behind_outlines(cam, depths[n], pl) == [], n


@pytest.mark.parametrize("scale", [1.0, 1000.0])
def test_the_views_pooled_find_one_hole_the_size_of_the_opening(scale):
    cams, depths = _views(scale)
    (h,) = _holes(cams, depths)
    assert h["views"] == ["v0", "v1", "v2", "v3"] and h["enclosed"] > 0.9
    assert h["behind"] == pytest.approx(0.6, abs=0.03)
    poly = h["polygon"] / scale
    assert np.abs(poly @ WALL[:3] + WALL[3]).max() < 0.01
    origin, u, v = plane_basis(WALL)
    a, b = (poly - CENTRE) @ u, (poly - CENTRE) @ v
    # cells are 1 % of the median depth (~3 cm): the outline within two of them
    assert np.ptp(a) == pytest.approx(2 * HALF[0], abs=0.08), np.ptp(a)
    assert np.ptp(b) == pytest.approx(2 * HALF[1], abs=0.08), np.ptp(b)
    assert abs(a.max() + a.min()) < 0.1 and abs(b.max() + b.min()) < 0.1


def test_find_candidates_adds_the_pooled_hole_only_when_asked():
    cams, depths = _views()
    (c,) = find_candidates(cams, depths)
    assert c["kept"] and c["name"].startswith("hole_") and "pooled" in c["reason"], c
    assert len(c["outline"]) >= 3 and c["view"] in cams
    assert find_candidates(cams, depths, pooled=False) == []


@pytest.mark.parametrize("kw, why", [
    (dict(factor=1.0), "a plain wall"),
    (dict(factor=1.05), "a niche 5 % deep"),
    (dict(edge=0.5), "beyond the wall's edge: not enclosed by it"),
])
def test_what_is_not_a_hole_through_the_wall_is_none(kw, why):
    cams, depths = _views(**kw)
    assert _holes(cams, depths) == [], why


def test_a_hole_seen_by_one_view_only_is_none():
    cams, depths = _views(n=1)
    assert _holes(cams, depths) == []


def test_grid_holes_needs_a_ring_of_surface():
    surface = np.full((40, 60), 5.0)
    through = np.zeros((40, 60))
    surface[10:25, 20:40], through[10:25, 20:40] = 0, 5        # enclosed
    surface[0:12, 50:60], through[0:12, 50:60] = 0, 5          # on the grid's corner
    # 3x3 counts round the hole's four corners off
    (h,) = grid_holes(surface, through, enclosed=D.enclosed)
    assert abs(h["cells"] - 15 * 20) <= 4 and h["mask"][15, 30] and not h["mask"][5, 55]
    # a ring mostly unobserved is no evidence of a hole
    surface2 = np.zeros_like(surface)
    surface2[10:25, 20:40] = 0
    assert grid_holes(surface2, through, enclosed=D.enclosed) == []
    with pytest.raises(ValueError, match="surface"):
        grid_holes(surface, through[:, :10], enclosed=D.enclosed)


def test_pooled_grid_counts_surface_and_through_samples():
    cams, depths = _views(n=2)
    lattice = view_samples(cams, depths)
    s, t, r, (origin, u, v, u0, v0, cell), seen = pooled_grid(WALL, lattice, 0.03, behind=D.behind)
    assert s.shape == t.shape == r.shape and set(seen) == {"v0", "v1"} and cell == 0.03
    inside = t > 0
    assert inside.any() and np.allclose(r[inside] / t[inside], 0.6, atol=0.05)
    # every lattice sample with depth lands in one of the two counts or neither, never both
    n = sum(len(z) for _, _, z in view_samples(cams, depths).values())
    assert s.sum() + t.sum() <= n and s.sum() > 0.5 * n
    # a grid capped at fewer cells takes larger ones, the same samples in them
    s2, t2, _, (*_, cell2), _ = pooled_grid(WALL, lattice, 0.03, behind=D.behind,
                                            max_cells=s.size // 4)
    assert s2.size < s.size / 3 and cell2 == pytest.approx(0.06, rel=0.05), (s2.shape, cell2)
    assert s2.sum() == pytest.approx(s.sum(), rel=0.01)
    assert t2.sum() == pytest.approx(t.sum(), rel=0.01)
    with pytest.raises(ValueError, match="v0"):
        view_samples(cams, {"v0": depths["v0"][None]})
    with pytest.raises(ValueError, match="plane"):
        pooled_grid(WALL[:3], view_samples(cams, depths), 0.03, behind=D.behind)


def _close_capture(src):
    """An RGB-D input of test_behind_detect's ray-cast room whose mirror no view sees whole:
    six narrow views each aimed at a part of it, and three that see the right-hand wall, which
    the mirror shows (the mirror warp needs the reflected room in G)."""
    from tests.reflection.test_behind_detect import write_capture
    narrow = np.array([[300.0, 0, 79.5], [0, 300.0, 59.5], [0, 0, 1]])
    wide = np.array([[150.0, 0, 79.5], [0, 150.0, 59.5], [0, 0, 1]])
    aims = [[1.75, 4, 1.25], [2.25, 4, 1.25], [2.25, 4, 1.75], [1.75, 4, 1.75], [2.0, 4, 1.3],
            [2.0, 4, 1.7]]
    cams = {f"m{i}.png": Camera.look_at([0.6 + 0.12 * i, 1.4 + 0.1 * (i % 2), 1.3 + 0.04 * i],
                                        a, (0, 0, 1), narrow, 160, 120) for i, a in enumerate(aims)}
    cams.update({f"w{i}.png": Camera.look_at([1.0 + 0.3 * i, 1.5, 1.4], [4.0, 2.5 + 0.5 * i, 1.5],
                                             (0, 0, 1), wide, 160, 120) for i in range(3)})
    write_capture(src, cams, mirror=True)


@pytest.mark.parametrize("pooled", [True, False])
def test_global_mesh_finds_a_mirror_no_view_sees_whole(pooled, tmp_path):
    """No reflectors.json, every view of the mirror cut by its frame: only the pooled grid
    finds it; found, it is verified and its mirror world is fused out of G."""
    import json

    from ibr_pipeline.cli import main
    from ibr_pipeline.io.mesh import read_ply
    from tests.reflection.test_behind_detect import HOLE, MIRROR
    src = tmp_path / "input"
    _close_capture(src)
    ws = tmp_path / "ws"
    assert main(["run", str(ws), "--input", str(src), "--until", "global_mesh",
                 "--set", "global_mesh.progress=false",
                 "--set", f"global_mesh.behind.pooled={str(pooled).lower()}"]) == 0
    found = json.loads((ws / "global" / "found_reflectors.json").read_text())
    report = json.loads((ws / "global" / "report.json").read_text())
    Vg = read_ply(ws / "global" / "mesh.ply").vertices
    behind = ((Vg[:, 1] > 4.2) & (np.abs(Vg[:, 0] - 2.0) < 0.5)).mean()
    if not pooled:
        assert found["reflectors"] == [] and report["mirror_world"].startswith("NOT masked")
        assert behind > 0.005, behind
        return
    (r,) = found["reflectors"]
    assert r["name"].startswith("hole_")
    n = np.asarray(r["plane"][:3])
    assert np.degrees(np.arccos(min(1.0, abs(n @ MIRROR[:3])))) < 1.0
    poly = np.asarray(r["polygon"])
    assert np.abs(poly @ MIRROR[:3] + MIRROR[3]).max() < 0.02
    assert np.all(np.abs(poly.min(0) - HOLE.min(0)) < 0.1), poly.min(0)
    assert np.all(np.abs(poly.max(0) - HOLE.max(0)) < 0.1), poly.max(0)
    assert report["mirror_world"].startswith("masked in 1")
    assert behind < 1e-4, behind
