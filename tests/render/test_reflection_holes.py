"""Eq. 3 in hole-filled pixels (§5.1.4): where the push-pull fill carries beta into a hole, the
filled reflection layer is added there too, as in every covered pixel of the reflector."""
import dataclasses

import numpy as np

from ibr_pipeline.render.ibr import IBRModel, LayerData, RenderSettings, ViewData
from tests.render.test_per_view import _camera, _view

I1_GREY = 0.3


def _reflective_view(name, cam):
    """test_per_view's wall mesh with beta 0.8 everywhere and a grey reflection layer on it."""
    s = _view(name, cam).layers[0]
    beta = np.full(s.alpha.shape, 0.8, np.float32)
    surface = LayerData(s.vertices, s.faces, s.rgb, s.alpha, beta=beta)
    reflection = LayerData(s.vertices, s.faces, np.full(s.rgb.shape, I1_GREY, np.float32), s.alpha)
    return ViewData(name, cam, (surface, reflection))


def test_holes_next_to_a_reflector_get_its_reflection_layer():
    src, novel = _camera(0.0), _camera(0.3)  # the novel view sees past the source's edge
    m = IBRModel([_reflective_view("src", src)],
                 dataclasses.replace(RenderSettings(), max_dist=10.0, feather_px=0.0))
    two = m.render(novel)
    one = m.render(novel, layers=False)
    m.release()
    holes = ~two.covered
    assert 0.05 < holes.mean() < 0.5, holes.mean()
    deep = holes & (two.beta > 0.5)  # the fill carried the reflector's beta there
    assert deep.sum() > 0.5 * holes.sum()
    added = (two.color - one.color)[deep]
    np.testing.assert_allclose(added, (two.beta[deep] * I1_GREY)[:, None].repeat(3, 1), atol=0.02)
    # and in covered pixels, as a check that the scene is what the test thinks it is
    cov = two.covered
    np.testing.assert_allclose((two.color - one.color)[cov], 0.8 * I1_GREY, atol=0.02)
