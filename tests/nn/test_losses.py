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


def _reference_depthwise(x, kernel2d):
    """The 2D per-channel convolution with replicated borders that the fast paths replace."""
    c, pad = x.shape[1], kernel2d.shape[-1] // 2
    k = kernel2d[None, None].expand(c, 1, *kernel2d.shape)
    return torch.nn.functional.conv2d(torch.nn.functional.pad(x, (pad,) * 4, mode="replicate"), k,
                                      groups=c)


@pytest.mark.parametrize("size,sigma", [(11, 1.5), (5, 1.0)])
def test_separable_gaussian_matches_the_2d_kernel(size, sigma):
    from ibr_pipeline.nn.losses import gaussian_blur
    g = torch.Generator().manual_seed(3)
    x = torch.rand(2, 3, 37, 29, generator=g).contiguous(memory_format=torch.channels_last)
    r = torch.arange(size, dtype=torch.float32) - (size - 1) / 2
    yy, xx = torch.meshgrid(r, r, indexing="ij")
    k2 = torch.exp(-(xx ** 2 + yy ** 2) / (2 * sigma ** 2))   # the 2D Gaussian, normalised
    ref = _reference_depthwise(x, k2 / k2.sum())
    out = gaussian_blur(x, size, sigma)
    assert out.shape == ref.shape == x.shape
    assert float((out - ref).abs().max()) < 1e-6


def test_filter_bank_grouped_matches_one_channel_at_a_time():
    g = torch.Generator().manual_seed(4)
    x = torch.rand(2, 3, 40, 36, generator=g)
    fb = FilterBank()
    feats = fb(x)
    for level, y in enumerate(feats):
        xs = torch.nn.functional.avg_pool2d(x, 2 ** level) if level else x
        for c in range(3):   # channel c's five responses are outputs 5c .. 5c+4
            ref = torch.cat([_reference_depthwise(xs[:, c:c + 1], fb.bank[f, 0]) for f in range(5)], 1)
            assert float((y[:, 5 * c:5 * c + 5] - ref).abs().max()) < 1e-5
