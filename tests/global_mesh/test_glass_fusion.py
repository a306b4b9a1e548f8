"""What G keeps behind a reflector: a mirror's depth becomes its plane (the mirror world is not
real), a pane of glass keeps what was measured behind it (the transmitted scene is)."""
import numpy as np
import pytest

from ibr_pipeline.geometry.fusion import apply_reflectors, mirror_world_points
from ibr_pipeline.scene import Camera, Reflector

W, H = 40, 30
# camera at the origin looking down +z at the plane z = 2 (n = (0, 0, -1), d = 2: camera side
# positive), a 2 x 2 polygon in that plane filling the middle of the image
PLANE = (0.0, 0.0, -1.0, 2.0)
POLY = ((-0.5, -0.5, 2.0), (0.5, -0.5, 2.0), (0.5, 0.5, 2.0), (-0.5, 0.5, 2.0))


def _camera():
    return Camera.look_at([0, 0, 0], [0, 0, 1], [0, -1, 0], Camera.intrinsics_from_fov(W, H, 60),
                          W, H)


def _reflector(material):
    return Reflector("pane", PLANE, beta=0.08, polygon=POLY, material=material)


@pytest.mark.parametrize("material", [None, "mirror", "glossy"])
def test_depth_behind_a_mirror_becomes_its_plane(material):
    cam = _camera()
    depth = np.full((H, W), 3.5, np.float32)  # everything seen 1.5 behind the plane
    out, n = apply_reflectors(cam, depth, [_reflector(material)])
    inside = np.abs(out - 2.0) < 1e-4
    assert n == inside.sum() > 0.1 * W * H   # the polygon's pixels, on the plane
    assert np.all(out[~inside] == 3.5)       # outside it nothing changes


def test_depth_behind_glass_is_kept():
    cam = _camera()
    depth = np.full((H, W), 3.5, np.float32)
    out, n = apply_reflectors(cam, depth, [_reflector("glass")])
    assert n == 0 and np.array_equal(out, depth)
    # and a mirror beside the pane is still applied
    out, n = apply_reflectors(cam, depth, [_reflector("glass"), _reflector("mirror")])
    assert n > 0 and np.isclose(out[H // 2, W // 2], 2.0)


def test_points_behind_glass_are_not_mirror_world():
    cam = _camera()
    pts = np.array([[0.0, 0.0, 3.5], [0.0, 0.0, 1.0]])  # behind the polygon, in front of it
    assert mirror_world_points(pts, [_reflector("mirror")], [cam]).tolist() == [True, False]
    assert mirror_world_points(pts, [_reflector("glass")], [cam]).tolist() == [False, False]
