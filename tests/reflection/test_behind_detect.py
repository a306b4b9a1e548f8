"""Reflector candidates from depth behind a plane (geometry/behind_detect.py): what MVS or a
depth camera sees inside a mirror or a screen is the mirror world, well behind the wall around
it. Found: a deep region enclosed by a plane, also where the frame cuts a side of it. Not found:
one mostly cut by the frame, a shallow niche, something in front of the wall, a speck."""
import numpy as np
import pytest

from ibr_pipeline.geometry.behind_detect import (behind_outlines, merge_candidates,
                                                 view_planes)
from ibr_pipeline.geometry.planes import plane_from_outline, ray_plane_hits
from ibr_pipeline.scene import Camera

K = np.array([[200.0, 0, 159.5], [0, 200.0, 119.5], [0, 0, 1]])
CAM = Camera.look_at([0.2, -0.1, 0.0], [0.3, 0.0, 3.0], (0, -1, 0), K, 320, 240)
WALL = np.r_[np.array([0.12, 0.08, -1.0]) / np.linalg.norm([0.12, 0.08, -1.0]), 0.0]
WALL[3] = -WALL[:3] @ np.array([0.3, 0.0, 3.2])


def _wall(seed=0, noise=0.003, holes=0.1):
    """The wall's depth with noise and missing pixels (MVS leaves some)."""
    rng = np.random.default_rng(seed)
    _, z = ray_plane_hits(CAM, WALL)
    d = z * (1 + noise * rng.standard_normal(z.shape))
    d[rng.random(z.shape) < holes] = 0.0
    return d, z, rng


def _box(d, z, rng, rows, cols, factor, fill=0.7):
    """Pixels rows x cols at `factor` x the wall's depth on a share `fill` of them (the rest
    empty, as MVS on a dark screen)."""
    sub = (slice(*rows), slice(*cols))
    keep = rng.random(z[sub].shape) < fill
    d[sub] = np.where(keep, factor * z[sub], 0.0)
    return d


def test_the_walls_plane_is_found():
    d, _, _ = _wall()
    planes = view_planes(CAM, d)
    assert len(planes) == 1                           # one surface: no second plane invented
    n = planes[0][:3] * np.sign(planes[0][:3] @ WALL[:3])
    assert np.degrees(np.arccos(min(1.0, n @ WALL[:3]))) < 0.5
    assert CAM.center @ planes[0][:3] + planes[0][3] > 0


def test_a_deep_region_inside_the_wall_is_outlined():
    d, z, rng = _wall()
    d = _box(d, z, rng, (80, 150), (100, 220), 1.6)
    (plane,) = view_planes(CAM, d)
    found = behind_outlines(CAM, d, plane)
    assert len(found) == 1, found
    c = found[0]
    lo, hi = c["outline"].min(0), c["outline"].max(0)
    assert np.all(np.abs(lo - [100, 80]) <= 4) and np.all(np.abs(hi - [219, 149]) <= 4), (lo, hi)
    assert abs(c["behind"] - 0.6) < 0.02 and c["enclosed"] > 0.9
    assert abs(c["area"] - 120 * 70 / (320 * 240)) < 0.02
    # the same outline a user would give: placed on the wall around it
    pl, poly = plane_from_outline(CAM, d, c["outline"])
    assert np.abs(poly @ WALL[:3] + WALL[3]).max() < 0.01


def test_a_region_the_frame_cuts_on_one_side_is_outlined_up_to_the_frame():
    d, z, rng = _wall()
    d = _box(d, z, rng, (80, 150), (0, 120), 1.6)
    (c,) = behind_outlines(CAM, d, view_planes(CAM, d)[0])
    lo, hi = c["outline"].min(0), c["outline"].max(0)
    assert np.all(np.abs(lo - [0, 80]) <= 4) and np.all(np.abs(hi - [119, 149]) <= 4), (lo, hi)


@pytest.mark.parametrize("rows, cols, factor, why", [
    ((20, 220), (0, 20), 1.6, "a strip along the frame: its outline is unseen"),
    ((80, 150), (100, 220), 1.05, "a niche: 5 % behind the wall"),
    ((80, 150), (100, 220), 0.7, "in front of the wall"),
    ((100, 104), (150, 154), 1.6, "a speck of 16 pixels"),
])
def test_what_is_not_a_hole_through_the_wall_is_not_outlined(rows, cols, factor, why):
    d, z, rng = _wall()
    d = _box(d, z, rng, rows, cols, factor, fill=1.0)
    plane = view_planes(CAM, d)[0]
    assert behind_outlines(CAM, d, plane) == [], why


def test_shape_errors_are_clear():
    with pytest.raises(ValueError, match="depth must be"):
        view_planes(CAM, np.zeros((4, 4, 1)))
    with pytest.raises(ValueError, match="depth must be"):
        behind_outlines(CAM, np.zeros(10), WALL)


def test_the_same_region_in_two_views_is_one_candidate_a_single_view_is_none():
    sq = np.array([[0.0, 0, 3], [1, 0, 3], [1, 0.6, 3], [0, 0.6, 3]])
    pl = [0.0, 0.0, -1.0, 3.0]
    a = {"view": "a", "plane": pl, "polygon": sq, "area": 0.05}
    b = {"view": "b", "plane": pl, "polygon": sq + [0.05, 0.02, 0.01], "area": 0.04}
    other = {"view": "b", "plane": pl, "polygon": sq + [3.0, 0, 0], "area": 0.05}
    tilted = {"view": "c", "plane": [0.0, np.sin(0.3), -np.cos(0.3), 3.0], "polygon": sq,
              "area": 0.03}
    groups = merge_candidates([a, b, other, tilted])
    assert len(groups) == 1 and [f["view"] for f in groups[0]] == ["a", "b"]
    assert merge_candidates([a, b], min_views=3) == []


# --- verification on a ray-cast room: a mirror is kept, a niche is dropped ----------------------
MIRROR = np.array([0.0, -1.0, 0.0, 4.0])          # the wall y = 4, normal towards the cameras
HOLE = np.array([[1.5, 4.0, 1.0], [2.5, 4.0, 1.0], [2.5, 4.0, 2.0], [1.5, 4.0, 2.0]])


def _quad(V, F, *p):
    i = len(V)
    V += [list(x) for x in p]
    F += [[i, i + 1, i + 2], [i, i + 2, i + 3]]


def _room(niche: bool):
    """A 4 x 4 x 3 room; with `niche` the wall y = 4 has HOLE's opening onto a 0.8-deep recess."""
    V, F = [], []
    for a in ([0, 0, 0], [4, 0, 0], [4, 0, 3], [0, 0, 3]), ([0, 0, 0], [0, 4, 0], [0, 4, 3], [0, 0, 3]), \
            ([4, 0, 0], [4, 4, 0], [4, 4, 3], [4, 0, 3]), ([0, 0, 0], [4, 0, 0], [4, 4, 0], [0, 4, 0]), \
            ([0, 0, 3], [4, 0, 3], [4, 4, 3], [0, 4, 3]):
        _quad(V, F, *a)
    y = 4.0
    if not niche:
        _quad(V, F, [0, y, 0], [4, y, 0], [4, y, 3], [0, y, 3])
    else:  # the wall around the opening, then the recess
        for a in ([0, y, 0], [1.5, y, 0], [1.5, y, 3], [0, y, 3]), ([2.5, y, 0], [4, y, 0], [4, y, 3], [2.5, y, 3]), \
                ([1.5, y, 0], [2.5, y, 0], [2.5, y, 1], [1.5, y, 1]), ([1.5, y, 2], [2.5, y, 2], [2.5, y, 3], [1.5, y, 3]):
            _quad(V, F, *a)
        b = y + 0.8
        for a in ([1.5, b, 1], [2.5, b, 1], [2.5, b, 2], [1.5, b, 2]), ([1.5, y, 1], [1.5, b, 1], [1.5, b, 2], [1.5, y, 2]), \
                ([2.5, y, 1], [2.5, b, 1], [2.5, b, 2], [2.5, y, 2]), ([1.5, y, 1], [2.5, y, 1], [2.5, b, 1], [1.5, b, 1]), \
                ([1.5, y, 2], [2.5, y, 2], [2.5, b, 2], [1.5, b, 2]):
            _quad(V, F, *a)
    return np.asarray(V, np.float64), np.asarray(F, np.int32)


def _texture(X):
    """A non-repeating colour on every surface point (N, 3) -> (N, 3) in [0.1, 0.9]."""
    return 0.5 + 0.4 * np.stack([np.sin(5.1 * X[:, 0] + 3.3 * X[:, 2]) * np.cos(4.3 * X[:, 1] - 2.0 * X[:, 2]),
                                 np.sin(3.7 * X[:, 1] + 4.9 * X[:, 2] + 1.0),
                                 np.cos(4.4 * X[:, 0] - 3.1 * X[:, 1] + 2.2 * X[:, 2])], 1)


def _photos(scene, cams, mirror: bool, depth: bool = False):
    """Linear images (and, with `depth`, the z-depth a depth camera measures: the mirror world's
    inside the mirror) of the ray-cast room."""
    from ibr_pipeline.geometry.planes import polygon_contains
    from ibr_pipeline.geometry.raycast import camera_rays, cast
    out, depths = {}, {}
    for n, cam in cams.items():
        o, d = camera_rays(cam)
        t = cast(scene, o, d)["t_hit"]
        X = o + d * t[:, None]
        if mirror:  # rays that meet the mirror go on reflected (beta = 1)
            on = (np.abs(X @ MIRROR[:3] + MIRROR[3]) < 1e-4)
            on[on] = polygon_contains(MIRROR, HOLE, X[on])
            r = d[on] - 2 * (d[on] @ MIRROR[:3])[:, None] * MIRROR[:3]
            start = X[on] + 1e-4 * r
            t2 = cast(scene, start, r)["t_hit"]
            X[on] = start + r * t2[:, None]
            t[on] += t2
        out[n] = _texture(X).reshape(cam.height, cam.width, 3)
        depths[n] = (t * (d @ cam.viewing_direction)).reshape(cam.height, cam.width)
    return (out, depths) if depth else out


@pytest.mark.parametrize("mirror", [True, False])
def test_a_mirror_is_kept_and_a_niche_is_dropped(mirror):
    """The same opening in the wall: a mirror (the photos show the room reflected; G, as MVS
    makes it without the mirror world, is the wall) or a niche (the photos show the recess; G
    holds it). Only the mirror's pixels are explained by the mirrored room."""
    from ibr_pipeline.geometry.behind_detect import verify_candidate
    from ibr_pipeline.geometry.raycast import build_scene
    K = np.array([[150.0, 0, 79.5], [0, 150.0, 59.5], [0, 0, 1]])
    cams = {f"v{i}": Camera.look_at([1.2 + 0.3 * i, 1.0 + 0.1 * (i % 2), 1.4 + 0.05 * i],
                                    [2.0, 4.0, 1.5], (0, 0, 1), K, 160, 120) for i in range(6)}
    V, F = _room(niche=not mirror)
    scene = build_scene(V, F)
    photos = _photos(scene, cams, mirror)
    cand = {"plane": MIRROR.tolist(), "polygon": HOLE.tolist()}
    kept, why, score = verify_candidate(cand, cams, photos, scene, (V.min(0), V.max(0)))
    assert score["pairs"] >= 4, score
    assert kept == mirror, (why, score)
    if mirror:
        assert score["mirror_ratio"] < 0.2 and score["surface_error"] > 0.05, score


def test_a_region_behind_the_wall_in_every_view_is_one_candidate():
    """Four views of the wall with a 0.8 x 0.5 opening onto the mirror world: one candidate,
    found in all four, on the wall; its hull holds what each view saw."""
    from ibr_pipeline.geometry.behind_detect import find_candidates
    from ibr_pipeline.geometry.planes import plane_basis
    origin, u, v = plane_basis(WALL)
    centre = np.array([0.3, 0.0, 3.2])
    cams, depths = {}, {}
    for i in range(4):
        cam = Camera.look_at([0.1 + 0.15 * i, -0.1 + 0.05 * (i % 2), 0.0], [0.3, 0.0, 3.0],
                             (0, -1, 0), K, 320, 240)
        X, z = ray_plane_hits(cam, WALL)
        a, b = (X - centre) @ u, (X - centre) @ v
        rng = np.random.default_rng(i)
        d = z * (1 + 0.003 * rng.standard_normal(z.shape))
        d[(np.abs(a) < 0.4) & (np.abs(b) < 0.25)] *= 1.6
        cams[f"v{i}"], depths[f"v{i}"] = cam, d
    (c,) = find_candidates(cams, depths)
    assert c["kept"] and c["views"] == ["v0", "v1", "v2", "v3"], c["reason"]
    poly = np.asarray(c["polygon"])
    assert np.abs(poly @ WALL[:3] + WALL[3]).max() < 0.01
    a, b = (poly - centre) @ u, (poly - centre) @ v
    assert np.ptp(a) == pytest.approx(0.8, abs=0.05) and np.ptp(b) == pytest.approx(0.5, abs=0.05)
    # seen in one view only: depth noise, not a reflector
    assert find_candidates({"v0": cams["v0"]}, {"v0": depths["v0"]}) == []


def write_capture(src, cams: dict, mirror: bool, niche: bool = False):
    """An RGB-D input folder (images/, depth/, cameras.json) of the ray-cast room seen by
    `cams` (name -> Camera)."""
    from ibr_pipeline.geometry.raycast import build_scene
    from ibr_pipeline.io.images import write_depth_png, write_image
    from ibr_pipeline.scene import cameras_to_json
    V, F = _room(niche=niche)
    photos, depths = _photos(build_scene(V, F), cams, mirror, depth=True)
    (src / "images").mkdir(parents=True)
    (src / "depth").mkdir()
    for n in cams:
        write_image(src / "images" / n, photos[n], "srgb")
        write_depth_png(src / "depth" / n, depths[n])
    (src / "cameras.json").write_text(cameras_to_json(cams))


def _capture(src, mirror: bool):
    K = np.array([[150.0, 0, 79.5], [0, 150.0, 59.5], [0, 0, 1]])
    # seen from the left, the mirror shows the right-hand wall, which the cameras see directly
    # too (a mirror showing only what no camera sees cannot be told from a hole by this cue)
    cams = {f"v{i}.png": Camera.look_at([0.5 + 0.12 * i, 1.4 + 0.1 * (i % 2), 1.3 + 0.04 * i],
                                        [2.4, 3.6, 1.5], (0, 0, 1), K, 160, 120) for i in range(8)}
    write_capture(src, cams, mirror, niche=not mirror)


@pytest.mark.parametrize("mirror", [True, False])
def test_global_mesh_finds_the_mirror_and_removes_its_mirror_world(mirror, tmp_path):
    """An RGB-D capture of the ray-cast room, no reflectors.json: global_mesh finds the mirror
    in the depth, verifies it and fuses G without the room behind it. The niche finds no
    reflector (seen this obliquely its inner wall breaks the ring of wall around it, so it is
    not even a candidate; verification drops one that is: the test above) and G keeps it."""
    import json

    from ibr_pipeline.cli import main
    from ibr_pipeline.io.mesh import read_ply
    src = tmp_path / "input"
    _capture(src, mirror)
    ws = tmp_path / "ws"
    assert main(["run", str(ws), "--input", str(src), "--until", "global_mesh",
                 "--set", "global_mesh.progress=false"]) == 0
    found = json.loads((ws / "global" / "found_reflectors.json").read_text())
    report = json.loads((ws / "global" / "report.json").read_text())
    Vg = read_ply(ws / "global" / "mesh.ply").vertices
    behind = ((Vg[:, 1] > 4.2) & (np.abs(Vg[:, 0] - 2.0) < 0.5)).mean()  # in the opening
    if mirror:
        assert found["candidates"], "the opening was not a candidate"
        (r,) = found["reflectors"]
        n = np.asarray(r["plane"][:3])
        assert np.degrees(np.arccos(min(1.0, abs(n @ MIRROR[:3])))) < 1.0
        poly = np.asarray(r["polygon"])
        assert np.abs(poly @ MIRROR[:3] + MIRROR[3]).max() < 0.02
        assert np.all(np.abs(poly.min(0)[[0, 2]] - [1.5, 1.0]) < 0.1)
        assert np.all(np.abs(poly.max(0)[[0, 2]] - [2.5, 2.0]) < 0.1)
        assert report["mirror_world"].startswith("masked in 1")
        assert behind < 1e-4, behind                 # no room behind the mirror in G
    else:
        assert found["reflectors"] == [] and not any(c["kept"] for c in found["candidates"])
        assert report["mirror_world"].startswith("NOT masked")
        assert behind > 0.005, behind                # the niche's back wall stays


def test_a_candidate_on_a_given_reflector_is_that_reflector():
    from ibr_pipeline.geometry.behind_detect import same_reflector
    cand = {"plane": MIRROR.tolist(), "polygon": (HOLE + [0.1, 0.0, 0.05]).tolist()}
    assert same_reflector(cand, MIRROR, HOLE)
    assert same_reflector(cand, MIRROR, None)                   # a plane without extent
    assert not same_reflector(cand, MIRROR, HOLE + [2.0, 0, 0])  # elsewhere on the wall
    assert not same_reflector(cand, [1.0, 0, 0, -0.5], None)     # another wall
    assert not same_reflector(cand, MIRROR + [0, 0, 0, 3.0], HOLE)  # a parallel plane 3 away


def test_a_mirror_given_in_reflectors_json_is_not_found_again(tmp_path):
    """find_reflectors = on with the mirror in reflectors.json: its candidate is that reflector,
    not a second one on the same glass."""
    import json

    from ibr_pipeline.cli import main
    src = tmp_path / "input"
    _capture(src, True)
    (src / "reflectors.json").write_text(json.dumps({"reflectors": [
        {"name": "mirror", "plane": MIRROR.tolist(), "polygon": HOLE.tolist(), "beta": 1.0}]}))
    ws = tmp_path / "ws"
    assert main(["run", str(ws), "--input", str(src), "--until", "global_mesh",
                 "--set", "global_mesh.progress=false", "--set", "global_mesh.find_reflectors=on"]) == 0
    found = json.loads((ws / "global" / "found_reflectors.json").read_text())
    assert found["reflectors"] == [], found["reflectors"]
    assert any("the given reflector mirror" in c["reason"] for c in found["candidates"]), found
