"""decompose_terms.nanmedian0: numpy's nanmedian over the first axis, bit for bit."""
import warnings

import numpy as np
import pytest

from ibr_pipeline.geometry.decompose_terms import nanmedian0


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("k", [1, 2, 3, 4, 7])
def test_equals_numpy_nanmedian(dtype, k):
    rng = np.random.default_rng(k)
    a = rng.random((k, 3000, 3)).astype(dtype)
    a[rng.random(a.shape) < 0.4] = np.nan   # some columns all-NaN when k is small
    a[0, :5] = np.inf
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        ref = np.nanmedian(a, axis=0)
    got = nanmedian0(a)
    assert got.dtype == ref.dtype and np.array_equal(got, ref, equal_nan=True)
    assert np.isnan(got).any() == np.isnan(ref).any()


def test_rejects_an_empty_first_axis():
    with pytest.raises(ValueError, match="first axis"):
        nanmedian0(np.zeros((0, 4)))


@pytest.mark.parametrize("shape", [(7, 3), (5, 4, 3), (9, 2), (4, 1)])
def test_all_last_and_any_last_equal_numpy(shape):
    from ibr_pipeline.geometry.decompose_terms import all_last, any_last
    b = np.random.default_rng(len(shape)).random(shape) < 0.6
    assert np.array_equal(all_last(b), np.all(b, axis=-1))
    assert np.array_equal(any_last(b), np.any(b, axis=-1))
    with pytest.raises(ValueError, match="last axis"):
        all_last(np.zeros((3, 0), bool))
