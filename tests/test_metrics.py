import numpy as np
import pytest
from skimage.metrics import structural_similarity

from ibr_pipeline import metrics


@pytest.fixture
def pair():
    rng = np.random.default_rng(0)
    a = rng.random((48, 64, 3))
    b = np.clip(a + rng.normal(0, 0.05, a.shape), 0, 1)
    return a, b


def test_psnr_matches_mse(pair):
    a, b = pair
    mse = ((a - b) ** 2).mean()
    assert metrics.psnr(a, b) == pytest.approx(10 * np.log10(1 / mse), rel=1e-9)
    assert metrics.psnr(a, a) == float("inf")


def test_masked_metrics_only_see_the_mask(pair):
    a, b = pair
    b2 = b.copy()
    b2[:, 32:] = 1 - a[:, 32:]  # ruin the right half only
    mask = np.zeros(a.shape[:2], bool)
    mask[:, :32] = True
    assert metrics.psnr(a, b2, mask) == pytest.approx(metrics.psnr(a[:, :32], b[:, :32]), rel=1e-9)
    assert metrics.psnr(a, b2) < metrics.psnr(a, b2, mask) - 5
    assert np.isnan(metrics.psnr(a, b, np.zeros_like(mask)))


def test_ssim_agrees_with_scikit_image(pair):
    a, b = pair
    ref = structural_similarity(a, b, channel_axis=2, data_range=1.0, gaussian_weights=True,
                                sigma=1.5, use_sample_covariance=False)
    assert metrics.ssim(a, b) == pytest.approx(ref, abs=0.01)
    assert metrics.ssim(a, a) == pytest.approx(1.0, abs=1e-9)


@pytest.mark.parametrize("shape", [(48, 64), (3, 4), (1, 7), (12, 9)])
def test_gaussian_window_is_scipys_reflect_filter(shape):
    """SSIM's window through OpenCV: scipy's gaussian_filter (truncate 3.5, reflect) to float
    rounding, also on maps smaller than the window (repeated reflections)."""
    from scipy.ndimage import gaussian_filter
    z = np.random.default_rng(1).random(shape)
    for sigma in (1.5, 0.8):
        ref = gaussian_filter(z, sigma, truncate=3.5, mode="reflect")
        assert np.abs(metrics.gaussian_window(z, sigma) - ref).max() < 1e-12


def test_flip_orders_errors(pair):
    a, b = pair
    worse = np.clip(a + 0.3, 0, 1)
    assert metrics.flip(a, a) < 1e-6
    assert 0 < metrics.flip(a, b) < metrics.flip(a, worse) <= 1


def test_shape_mismatch_is_an_error(pair):
    a, _ = pair
    with pytest.raises(ValueError, match="same"):
        metrics.psnr(a, a[:10])


def test_all_metrics_agrees_with_each_metric(pair):
    """all_metrics shares one SSIM and one FLIP map between the whole image and the mask; the
    figures must be those of the single-metric functions."""
    a, b = pair
    mask = np.zeros(a.shape[:2], bool)
    mask[10:30, 5:40] = True
    m = metrics.all_metrics(a, b, mask)
    assert m["psnr"] == pytest.approx(metrics.psnr(a, b), rel=1e-12)
    assert m["ssim"] == pytest.approx(metrics.ssim(a, b), rel=1e-12)
    assert m["flip"] == pytest.approx(metrics.flip(a, b), rel=1e-9)
    assert m["psnr_mask"] == pytest.approx(metrics.psnr(a, b, mask), rel=1e-12)
    assert m["ssim_mask"] == pytest.approx(metrics.ssim(a, b, mask), rel=1e-12)
    assert m["flip_mask"] == pytest.approx(metrics.flip(a, b, mask), rel=1e-9)
    assert m["ssim_mask"] != pytest.approx(m["ssim"], rel=1e-6)  # the mask is applied
    assert "flip" not in metrics.all_metrics(a, b, with_flip=False)
    with pytest.raises(ValueError):
        metrics.all_metrics(a, b, mask[:-1])
