"""A reflector given by its outline in one photograph (reflectors.json "outline"): the plane is
fitted to the depth around the outline, not to the reflector's own depth (the mirror world)."""
import numpy as np
import pytest

from ibr_pipeline.geometry.planes import plane_from_outline, ray_plane_hits
from ibr_pipeline.scene import Camera

K = np.array([[200.0, 0, 159.5], [0, 200.0, 119.5], [0, 0, 1]])
CAM = Camera.look_at([0.2, -0.1, 0.0], [0.3, 0.0, 3.0], (0, -1, 0), K, 320, 240)
WALL = np.r_[np.array([0.12, 0.08, -1.0]) / np.linalg.norm([0.12, 0.08, -1.0]), 0.0]
WALL[3] = -WALL[:3] @ np.array([0.3, 0.0, 3.2])   # through a point 3.2 ahead
OUTLINE = np.array([[110.0, 80.0], [230.0, 84.0], [228.0, 150.0], [112.0, 146.0]])


def _depth(size=(240, 320), seed=0):
    """The wall's depth with noise and outliers; inside the outline the mirror world (deeper) or
    nothing, as multi-view stereo gives for a screen or a mirror."""
    rng = np.random.default_rng(seed)
    cam = CAM.resized(size[1], size[0])
    _, z = ray_plane_hits(cam, WALL)
    d = z * (1 + 0.003 * rng.standard_normal(z.shape))
    out = rng.random(z.shape) < 0.05
    d[out] = rng.uniform(1.0, 6.0, out.sum())
    from matplotlib.path import Path
    s = size[1] / 320
    uv = np.stack(np.meshgrid(np.arange(size[1]), np.arange(size[0])), -1).reshape(-1, 2)
    inside = Path((OUTLINE + 0.5) * s - 0.5).contains_points(uv).reshape(size)
    d[inside] = np.where(rng.random(inside.sum()) < 0.5, 1.7 * z[inside], 0.0)
    return d, inside


@pytest.mark.parametrize("size", [(240, 320), (120, 160)])
def test_the_plane_is_the_wall_around_the_outline_not_the_mirror_world(size):
    depth, inside = _depth(size)
    assert inside.mean() > 0.08                       # a real share of the view is the reflector
    plane, poly = plane_from_outline(CAM, depth, OUTLINE)
    n = plane[:3] if plane[:3] @ WALL[:3] > 0 else -plane[:3]
    assert np.degrees(np.arccos(min(1.0, n @ WALL[:3]))) < 0.5
    assert CAM.center @ plane[:3] + plane[3] > 0      # the camera on the reflecting side
    want, z = ray_plane_hits(CAM, WALL, OUTLINE)      # the corners on the true wall
    assert np.all(np.linalg.norm(poly - want, axis=1) < 0.01 * z)
    uv, _ = CAM.project(poly)
    assert np.abs(uv - OUTLINE).max() < 1e-6          # the polygon projects onto the outline


def test_no_depth_around_the_outline_is_refused():
    depth, inside = _depth()
    with pytest.raises(ValueError, match="depth samples around the outline"):
        plane_from_outline(CAM, np.where(inside, depth, 0.0), OUTLINE)
    with pytest.raises(ValueError, match="outline must be"):
        plane_from_outline(CAM, depth, OUTLINE[:2])


def test_a_screen_standing_proud_of_the_wall_moves_the_plane_onto_it():
    """A TV's screen 6 cm in front of its wall, seen by a depth sensor (its own depth valid), with
    a box below it in the band: the plane is the screen's, not the wall's or the box's."""
    rng = np.random.default_rng(1)
    _, z = ray_plane_hits(CAM, WALL)
    screen = np.r_[WALL[:3], WALL[3] - 0.06]          # n . x + d = 0.06 on the wall: 6 cm nearer
    _, zs = ray_plane_hits(CAM, screen)
    depth, inside = _depth()
    depth = z * (1 + 0.001 * rng.standard_normal(z.shape))
    depth[inside] = zs[inside]
    depth[152:175, 100:240] = 0.7 * z[152:175, 100:240]  # a box in front of the wall, below
    plane, poly = plane_from_outline(CAM, depth, OUTLINE)
    want, zc = ray_plane_hits(CAM, screen, OUTLINE)
    assert np.degrees(np.arccos(min(1.0, abs(plane[:3] @ WALL[:3])))) < 0.5
    assert np.all(np.linalg.norm(poly - want, axis=1) < 0.004 * zc)
    mirror, _ = _depth()                               # the mirror world inside: no move
    _, poly2 = plane_from_outline(CAM, np.where(inside, mirror, depth), OUTLINE)
    wall, zw = ray_plane_hits(CAM, WALL, OUTLINE)
    assert np.all(np.linalg.norm(poly2 - wall, axis=1) < 0.004 * zw)
