"""render_views.renderer.blend_space: views blended in the encoding their textures hold (sRGB
values for photographs, decoded before Eq. 3) or in linear light. Two views of a wall with flat
textures of sRGB 0.2 and 0.8, seen from half-way between them (equal Eq. 15 weights)."""
import dataclasses

import numpy as np
import pytest

from ibr_pipeline.io.images import srgb_to_linear
from ibr_pipeline.render.ibr import IBRModel, LayerData, RenderSettings, ViewData
from ibr_pipeline.scene import Camera

W, H, Z = 64, 48, 2.0
DARK, BRIGHT = 0.2, 0.8   # the two views' stored sRGB values


def _camera(cx):
    return Camera.look_at([cx, 0, 0], [cx, 0, Z], [0, -1, 0], Camera.intrinsics_from_fov(W, H, 60),
                          W, H)


def _view(name, cx, value, encoding):
    """A two-triangle wall at z = Z covering the view, textured flat with `value` in `encoding`
    (a linear texture holds the decoded value)."""
    cam = _camera(cx)
    s = 3.0
    verts = np.array([[-s, -s, Z], [s, -s, Z], [-s, s, Z], [s, s, Z]], np.float32)
    faces = np.array([[0, 2, 1], [1, 2, 3]])
    v = value if encoding == "srgb" else float(srgb_to_linear(np.float32(value)))
    rgb = np.full((H, W, 3), v, np.float32)
    return ViewData(name, cam, (LayerData(verts, faces, rgb, np.ones((H, W), np.float32),
                                          encoding=encoding), None))


@pytest.mark.parametrize("visibility", ["fuzzy", "per_view"])
def test_srgb_textures_blend_as_stored_values_and_come_out_linear(visibility):
    s = dataclasses.replace(RenderSettings(), visibility=visibility, max_dist=10.0, feather_px=0.0)
    novel = _camera(0.0)
    out = {}
    for enc in ("srgb", "linear"):
        m = IBRModel([_view("a", -0.1, DARK, enc), _view("b", 0.1, BRIGHT, enc)], s)
        assert m.texture_encoding == enc
        f = m.render(novel)
        m.release()
        assert set(f.selected) == {"a", "b"} and f.covered.all()
        out[enc] = f.color[:, W // 4:3 * W // 4]  # both views see the middle of the frame
    stored = float(srgb_to_linear(np.float32((DARK + BRIGHT) / 2)))
    linear = float(srgb_to_linear(np.float32([DARK, BRIGHT])).mean())
    np.testing.assert_allclose(out["srgb"], stored, atol=2e-3)   # 0.214
    np.testing.assert_allclose(out["linear"], linear, atol=2e-3)  # 0.318


def test_a_model_refuses_textures_in_two_encodings():
    with pytest.raises(ValueError, match="mix encodings"):
        IBRModel([_view("a", -0.1, DARK, "srgb"), _view("b", 0.1, BRIGHT, "linear")])


def test_layer_data_names_a_bad_encoding():
    with pytest.raises(ValueError, match="encoding"):
        LayerData(np.zeros((3, 3)), np.array([[0, 1, 2]]), np.zeros((2, 2, 3)), np.ones((2, 2)),
                  encoding="gamma")
