"""Depth in front of a reflector: an object standing before it is where every frame that sees it
puts it and stays; a surface seen by one frame only, where the others look through it at the
mirror world (MVS's wrong matches of a screen's highlights), is taken as the reflector."""
import numpy as np
import pytest

from ibr_pipeline.geometry.fusion import apply_reflectors, plane_depth, polygon_mask, reflector_floaters
from ibr_pipeline.scene import Camera, Reflector

W, H = 80, 60
# cameras on the x axis looking down +z at a mirror in the plane z = 2 (2 x 2, camera side
# positive); the mirror world 1.5 behind it; a 0.4 x 0.4 card standing before it at z = 1.5
MIRROR = Reflector("tv", (0.0, 0.0, -1.0, 2.0), beta=1.0, material="mirror",
                   polygon=((-1, -1, 2.0), (1, -1, 2.0), (1, 1, 2.0), (-1, 1, 2.0)))
CARD_PLANE = (0.0, 0.0, -1.0, 1.5)
CARD = np.array([(-0.2, -0.2, 1.5), (0.2, -0.2, 1.5), (0.2, 0.2, 1.5), (-0.2, 0.2, 1.5)])


def _frames():
    K = Camera.intrinsics_from_fov(W, H, 90)
    frames = {}
    for i, x in enumerate((-0.3, -0.15, 0.0, 0.15, 0.3)):
        cam = Camera.look_at([x, 0, 0], [x, 0, 1], [0, -1, 0], K, W, H)
        depth = np.full((H, W), 3.5)
        card = polygon_mask(cam, CARD)
        depth[card] = plane_depth(cam, CARD_PLANE)[card]
        frames[f"v{i}"] = (depth, cam)
    floater = np.zeros((H, W), bool)
    floater[14:20, 24:36] = True       # only frame v2 sees it: 0.4 in front of the mirror
    frames["v2"][0][floater] = 1.6
    return frames, floater


def test_a_floater_is_refuted_the_object_before_the_mirror_is_not():
    frames, floater = _frames()
    flagged = reflector_floaters(frames, MIRROR)
    assert np.array_equal(flagged["v2"] & floater, floater)
    for name, (depth, cam) in frames.items():
        card = polygon_mask(cam, CARD)
        # the card's pixels are confirmed by the other frames (its rim may round onto the
        # mirror world behind it in another frame)
        assert np.count_nonzero(flagged.get(name, np.zeros_like(card)) & card) <= 0.1 * card.sum()
        assert not (flagged.get(name, np.zeros_like(card)) & ~card & ~floater).any()


def test_refuted_depth_becomes_the_mirror_plane():
    frames, floater = _frames()
    flagged = reflector_floaters(frames, MIRROR)
    depth, cam = frames["v2"]
    out, _ = apply_reflectors(cam, depth, [MIRROR], refuted={"tv": flagged["v2"]})
    assert np.allclose(out[floater], 2.0, atol=1e-3)
    card = polygon_mask(cam, CARD) & ~flagged["v2"]
    assert np.allclose(out[card], depth[card])            # the card keeps its measurement
    kept, _ = apply_reflectors(cam, depth, [MIRROR])      # without: the floater stays
    assert np.all(kept[floater] == 1.6)


def test_glass_and_unbounded_reflectors_flag_nothing():
    frames, _ = _frames()
    glass = Reflector("pane", MIRROR.plane, beta=0.1, polygon=MIRROR.polygon, material="glass")
    plane_only = Reflector("wall", MIRROR.plane, beta=1.0, polygon=None, material="mirror")
    assert reflector_floaters(frames, glass) == {} and reflector_floaters(frames, plane_only) == {}


def test_max_views_checks_against_the_frames_that_see_the_points():
    """Bounded to 2 other frames, the check still refutes the floater and keeps the card; the
    frames looking away from the mirror, listed first, are not among the 2."""
    frames, floater = _frames()
    K = Camera.intrinsics_from_fov(W, H, 90)
    away = {f"a{i}": (np.full((H, W), 5.0), Camera.look_at([0.1 * i, 0, 0], [0.1 * i, 0, -1],
                                                            [0, -1, 0], K, W, H)) for i in range(3)}
    frames = {**away, **frames}
    flagged = reflector_floaters(frames, MIRROR, max_views=2)
    assert np.array_equal(flagged["v2"] & floater, floater)
    for name in ("v0", "v2", "v4"):
        depth, cam = frames[name]
        card = polygon_mask(cam, CARD)
        assert np.count_nonzero(flagged.get(name, np.zeros_like(card)) & card) <= 0.1 * card.sum()
    assert reflector_floaters(frames, MIRROR, max_views=0).keys() == flagged.keys()


def test_a_depth_frame_of_the_wrong_size_is_named():
    frames, _ = _frames()
    frames["v3"] = (frames["v3"][0][:-1], frames["v3"][1])
    with pytest.raises(ValueError, match="v3"):
        reflector_floaters(frames, MIRROR)
