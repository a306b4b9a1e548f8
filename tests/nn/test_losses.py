"""Losses of Xu §5.2.2: SSIM term agrees with ibr_pipeline.metrics, filter bank, warp loss, VGG file."""
import pytest
import torch

from ibr_pipeline import metrics
from ibr_pipeline.nn.losses import (_VGG16, FilterBank, VGGFeatures, image_loss, perceptual, ssim,
                                    warp_loss)


def test_ssim_matches_metrics():
    g = torch.Generator().manual_seed(1)
    a = torch.rand(1, 3, 40, 50, generator=g)
    b = (a + 0.1 * torch.randn(1, 3, 40, 50, generator=g)).clamp(0, 1)
    ref = metrics.ssim(a[0].permute(1, 2, 0).numpy(), b[0].permute(1, 2, 0).numpy())
    assert abs(float(ssim(a, b)) - ref) < 0.01
    assert abs(float(ssim(a, a)) - 1.0) < 1e-5


def test_filter_bank_sees_blur_and_is_zero_for_equal_images():
    g = torch.Generator().manual_seed(2)
    a = torch.rand(2, 3, 64, 64, generator=g)
    blurred = torch.nn.functional.avg_pool2d(a, 3, 1, 1)
    fb = FilterBank()
    assert len(fb(a)) == 5  # conv_1..conv_5
    assert float(perceptual(fb, a, a)) == 0.0
    assert float(perceptual(fb, a, blurred)) > 1e-3
    assert float(image_loss(fb, a, a)) < 1e-5


def test_warp_loss():
    a = torch.rand(1, 3, 16, 16)
    assert float(warp_loss(a, a)) == 0.0
    b = a + 0.2
    assert abs(float(warp_loss(a, b)) - 0.4) < 1e-5  # L1 of G(.) and of the images: 0.2 + 0.2
    mask = torch.zeros(1, 1, 16, 16)
    assert float(warp_loss(a, b, mask)) == 0.0
    with pytest.raises(ValueError):
        warp_loss(a, torch.rand(1, 3, 8, 8))


def test_user_vgg_weights_file(tmp_path):
    """A VGG-16 features state dict in torchvision's key layout is accepted (random weights here:
    none can be downloaded)."""
    torch.manual_seed(0)
    state, c, i = {}, 3, 0
    for v in _VGG16:
        if v != "M":
            state[f"features.{i}.weight"] = torch.randn(v, c, 3, 3) * 0.01
            state[f"features.{i}.bias"] = torch.zeros(v)
            c, i = v, i + 2
        else:
            i += 1
    path = tmp_path / "vgg16_features.pt"
    torch.save(state, path)
    vgg = VGGFeatures(path)
    feats = vgg(torch.rand(1, 3, 32, 32))
    assert [f.shape[1] for f in feats] == [64, 128, 256, 512, 512]
    bad = tmp_path / "bad.pt"
    torch.save({"features.0.weight": torch.zeros(1)}, bad)
    with pytest.raises(RuntimeError):
        VGGFeatures(bad)
