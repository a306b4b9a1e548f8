"""The numba bilinear sampler against the numpy one: the same bits, clamping included."""
import numpy as np
import pytest

from ibr_pipeline.geometry.decompose_terms import sample_bilinear, sample_bilinear_np


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("shape", [(37, 53, 3), (5, 4, 1), (1, 7, 2), (6, 1, 3)])
def test_numba_sampler_gives_the_numpy_bits(dtype, shape):
    rng = np.random.default_rng(0)
    img = rng.random(shape).astype(dtype)
    H, W = shape[:2]
    pos = rng.uniform(-3, 1, (4000, 2)) * [W + 4, H + 4]  # inside, on and beyond the border
    pos[:4] = [[0, 0], [W - 1, H - 1], [W - 1, 0], [0.5, H - 1]]
    fast, ref = sample_bilinear(img, pos), sample_bilinear_np(img, pos)
    assert fast.dtype == ref.dtype == np.float64 and fast.shape == ref.shape == (4000, shape[2])
    assert np.array_equal(fast, ref)
    inside = (pos[:, 0] > 1) & (pos[:, 0] < W - 2) & (pos[:, 1] > 1) & (pos[:, 1] < H - 2)
    if inside.any():  # interpolates: between the corner values, not equal to a single one
        assert np.all(fast[inside] >= img.min() - 1e-7) and np.all(fast[inside] <= img.max() + 1e-7)


def test_float32_positions_take_the_numpy_path():
    img = np.arange(12.0).reshape(3, 4, 1)
    pos = np.array([[1.5, 1.0], [2.25, 0.5]], np.float32)
    assert np.array_equal(sample_bilinear(img, pos), sample_bilinear_np(img, pos))
    assert np.allclose(sample_bilinear(img, pos)[:, 0], [5.5, 4.25])
