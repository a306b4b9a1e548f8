"""The numba value noise against its numpy reference: the same bits, negative lattice cells and
large coordinates included."""
import numpy as np
import pytest

from ibr_pipeline.synthetic import textures


@pytest.mark.parametrize("scale,freq,seed", [(1.0, 4.0, 0), (50.0, 37.5, 12345), (1e4, 0.3, 39612),
                                             (3.0, 2.5, 2 ** 40 + 7)])
def test_value_noise_is_the_numpy_reference(scale, freq, seed):
    p = np.random.default_rng(seed % 1000).standard_normal((5000, 2)) * scale
    ref = textures.value_noise_np(p, freq, seed)
    got = textures.value_noise(p, freq, seed)
    assert np.array_equal(got, ref)
    assert got.min() >= 0.0 and got.max() <= 1.0


def test_value_noise_rejects_bad_shapes():
    with pytest.raises(ValueError, match="points"):
        textures.value_noise(np.zeros((4, 3)), 1.0, 0)
