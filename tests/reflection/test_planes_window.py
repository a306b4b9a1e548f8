"""reflector_mask computes plane hits only inside the polygon's projected window
(planes.polygon_window): it must give exactly the mask of testing every pixel."""
import numpy as np
import pytest

from ibr_pipeline.geometry.planes import (polygon_contains, polygon_window, ray_plane_hits,
                                          reflector_mask, reflector_support)
from ibr_pipeline.scene import Camera

K = np.array([[90.0, 0, 63.5], [0, 90.0, 47.5], [0, 0, 1]])
PLANE = np.array([0.0, 0.0, 1.0, 0.0])  # z = 0, normal +z: cameras above it face it
POLY = np.array([[-1.0, -0.6, 0], [1.2, -0.6, 0], [1.2, 0.8, 0], [-1.0, 0.8, 0]])


def _mask_every_pixel(cam, depth, rel_tol=0.02):
    """The mask by testing every pixel: the definition reflector_mask must reproduce."""
    X, z = ray_plane_hits(cam, PLANE)
    ok = np.isfinite(z) & (z > 1e-3) & (depth > 0) & (np.abs(depth - z) < rel_tol * z)
    if (cam.center @ PLANE[:3] + PLANE[3]) <= 0:
        return np.zeros_like(ok)
    inside = np.zeros(ok.size, bool)
    inside[ok.reshape(-1)] = polygon_contains(PLANE, POLY, X.reshape(-1, 3)[ok.reshape(-1)])
    return inside.reshape(ok.shape)


def _cameras():
    rng = np.random.default_rng(0)
    cams = []
    for _ in range(40):  # above the plane, looking at, past or away from the polygon
        eye = np.r_[rng.uniform(-2, 2, 2), rng.uniform(0.05, 2.0)]
        target = np.r_[rng.uniform(-3, 3, 2), rng.uniform(-1.0, 0.5)]
        if np.linalg.norm(np.cross(target - eye, [0, 0, 1])) < 1e-3:
            continue
        cams.append(Camera.look_at(eye, target, (0, 0, 1), K, 128, 96))
    cams.append(Camera.look_at([0, 0, -1.0], [0, 0.1, 0], (0, 1, 0), K, 128, 96))  # from behind
    return cams


@pytest.mark.parametrize("i", range(41))
def test_windowed_mask_equals_the_every_pixel_mask(i):
    cam = _cameras()[i]
    _, z = ray_plane_hits(cam, PLANE)
    depth = np.where(np.isfinite(z) & (z > 0), z, 0.0)  # the plane is the first surface
    depth[:10, :10] = 0.0                                 # no depth there
    want = _mask_every_pixel(cam, depth)
    got = reflector_mask(cam, PLANE, POLY, depth)
    assert np.array_equal(got, want)


def test_some_views_see_the_polygon_partly_and_some_not_at_all():
    """The cameras above cover the cases the window must handle (the test is not vacuous)."""
    seen = [polygon_window(c, POLY) for c in _cameras()]
    n_empty = sum(w == (0, 0, 0, 0) for w in seen)
    cams = _cameras()
    crossing = sum(np.ptp(np.sign(POLY @ c.R.T[:, 2] + c.t[2])) > 0 for c in cams)
    assert n_empty >= 5 and len(seen) - n_empty >= 10 and crossing >= 3


def _inside_rectangle(cam):
    """Pixels whose ray meets z = 0 inside POLY (an axis-aligned rectangle), by hand."""
    X, z = ray_plane_hits(cam, PLANE)
    return (np.isfinite(z) & (z > 0) & (X[..., 0] > -1.0) & (X[..., 0] < 1.2)
            & (X[..., 1] > -0.6) & (X[..., 1] < 0.8))


def test_support_in_a_photograph_without_depth_is_the_polygon_less_what_is_in_front():
    """A held-out photograph has no depth: G empty or holding the mirror world behind the
    plane both leave the whole polygon; geometry in front of the plane hides its pixels."""
    cam = Camera.look_at([0.3, 0.1, 2.5], [0.1, 0.1, 0.0], (0, 1, 0), K, 128, 96)
    want = _inside_rectangle(cam)
    assert 0.2 * want.size < want.sum() < want.size          # partly in view, not vacuous
    _, z = ray_plane_hits(cam, PLANE)
    empty = np.zeros(z.shape)
    assert np.array_equal(reflector_support(cam, PLANE, POLY, empty), want)
    behind = np.where(want, z * 1.5, 0.0)                    # mirror-world points fused into G
    assert np.array_equal(reflector_support(cam, PLANE, POLY, behind), want)
    front = np.where(want, z, 0.0)
    front[40:60, 50:80] *= 0.5                               # an object between camera and plane
    got = reflector_support(cam, PLANE, POLY, front)
    assert np.array_equal(got, want & ~((np.arange(96)[:, None] >= 40) & (np.arange(96)[:, None] < 60)
                                        & (np.arange(128) >= 50) & (np.arange(128) < 80)))
    assert got.sum() < want.sum()


def test_support_is_empty_from_behind_the_plane_and_checks_its_depth_shape():
    cam = Camera.look_at([0, 0, -1.0], [0, 0.1, 0], (0, 1, 0), K, 128, 96)
    assert not reflector_support(cam, PLANE, POLY, np.zeros((96, 128))).any()
    with pytest.raises(ValueError, match="occluder_depth"):
        reflector_support(cam, PLANE, POLY, np.zeros((10, 10)))
