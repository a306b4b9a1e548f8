"""tsdf_fuse's component filter (`FusionOptions.min_component`) with its default: a small object
near a camera is few voxels but many pixels, and must survive; specks of a few depth pixels are
fusion noise and must not. On llff_horns the old default (0.2 % of the faces) dropped the placard
in the foreground of most photos (docs/BENCHMARKS.md, "Real captures", session 41)."""
import numpy as np
import pytest

from ibr_pipeline.geometry.fusion import (FusionOptions, plane_depth, polygon_mask,
                                         triangle_components, tsdf_fuse)
from ibr_pipeline.io.images import read_depth_png
from ibr_pipeline.scene import cameras_from_json

VOXEL = 0.02


def _frames(root, cams, edit=None):
    for i, n in enumerate(sorted(cams)):
        d = read_depth_png(root / "depth" / n).astype(np.float64)
        c = cams[n].resized(d.shape[1], d.shape[0])
        if edit is not None:
            d = edit(i, c, d)
        yield d.astype(np.float32), cams[n], None


def _fuse(root, cams, edit, **kw):
    return tsdf_fuse(_frames(root, cams, edit), FusionOptions(voxel_size=VOXEL, depth_max=10.0, **kw))


@pytest.fixture(scope="module")
def scene(tiny_scene):
    root = tiny_scene[0]
    return root, cameras_from_json(root / "cameras.json")


def test_a_small_card_near_one_camera_survives_the_default_filter(scene):
    root, cams = scene
    c0 = cams[sorted(cams)[0]]
    d0 = read_depth_png(root / "depth" / sorted(cams)[0]).astype(np.float64)
    fwd, right, up = c0.viewing_direction, c0.R[0], c0.R[1]
    mid = c0.center + fwd * 0.4 * float(np.median(d0[d0 > 0]))   # well in front of the room
    half = 0.05
    card = np.array([mid + half * (a * right + b * up) for a, b in [(-1, -1), (1, -1), (1, 1), (-1, 1)]])
    plane = np.r_[fwd, -fwd @ mid]

    def with_card(i, cam, d):
        pd = plane_depth(cam, plane)
        m = polygon_mask(cam, card) & ((pd < d) | (d <= 0))
        return np.where(m, pd, d)

    def card_vertices(mesh):
        v = mesh.vertices
        rel = v - mid
        on = (np.abs(v @ plane[:3] + plane[3]) < 1.5 * VOXEL) & (np.abs(rel @ right) < half) \
            & (np.abs(rel @ up) < half)
        return on, on[mesh.faces].all(1)

    unfiltered, _ = _fuse(root, cams, with_card, min_component=0.0)
    on_all, faces_all = card_vertices(unfiltered)
    assert faces_all.sum() > 10
    # the regime that matters: the card's components (its face and the truncation band's rim) are
    # a small share of the mesh's faces; the old default, 0.2 %, dropped them
    label, counts = triangle_components(unfiltered.faces)
    assert counts[np.unique(label[faces_all])].sum() < 0.002 * len(unfiltered.faces)
    mesh, _ = _fuse(root, cams, with_card)
    on, faces = card_vertices(mesh)
    assert faces.sum() >= 0.9 * faces_all.sum() and on.sum() >= 0.9 * on_all.sum()


def test_specks_of_a_few_depth_pixels_are_removed(scene):
    root, cams = scene
    rng = np.random.default_rng(0)
    specks = []

    def with_specks(i, cam, d):
        if i != 1:
            return d
        d = d.copy()
        for _ in range(10):   # 2 x 2 pixels at half the depth there: floating in the room
            y, x = int(rng.integers(5, d.shape[0] - 5)), int(rng.integers(5, d.shape[1] - 5))
            z = 0.5 * d[y, x]
            d[y:y + 2, x:x + 2] = z
            specks.append(cam.unproject(np.array([[x + 1.0, y + 1.0]]), np.array([z]))[0])
        return d

    def near_specks(mesh, pts):
        dist = np.linalg.norm(mesh.vertices[None] - np.asarray(pts)[:, None], axis=2).min(1)
        return int((dist < 2 * VOXEL).sum())

    unfiltered, _ = _fuse(root, cams, with_specks, min_component=0.0)
    assert near_specks(unfiltered, specks) > 0   # they do make surface: the filter removes it
    first = list(specks)
    specks.clear()
    rng = np.random.default_rng(0)
    mesh, _ = _fuse(root, cams, with_specks)
    assert np.allclose(first, specks)
    assert near_specks(mesh, specks) == 0
