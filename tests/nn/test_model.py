"""DSRNet architecture (Xu §5.2.1, Fig. 10, Eq. 16): shapes, the ±5 px MVR limit, ablation switch."""
import pytest
import torch

from ibr_pipeline.nn.model import DSRNet, DSRNetConfig, count_parameters, preset


def _inputs(b=2, h=30, w=44, flow=0.0):
    g = torch.Generator().manual_seed(0)
    return (torch.rand(b, 3, h, w, generator=g), torch.rand(b, 1, h, w, generator=g) + 1,
            torch.rand(b, 3, h, w, generator=g), torch.rand(b, 1, h, w, generator=g) + 1,
            torch.full((b, 2, h, w), flow))


@pytest.mark.parametrize("scale", [2, 3])
def test_output_size_and_residual_start(scale):
    torch.manual_seed(0)
    net = DSRNet(DSRNetConfig(scale=scale)).eval()
    x = _inputs(h=30, w=44)  # not multiples of the U-Net's 4: padded and cropped
    with torch.no_grad():
        out = net(*x)
    assert out["image"].shape == (2, 3, 30 * scale, 44 * scale)
    up = torch.nn.functional.interpolate(x[0], scale_factor=scale, mode="bicubic")
    assert torch.allclose(out["image"], up, atol=1e-6)  # untrained = bicubic (zero-init head)


def test_mvr_output_limited_to_5px():
    torch.manual_seed(0)
    net = DSRNet(DSRNetConfig()).eval()
    with torch.no_grad():
        for p in net.mvr.parameters():
            p.normal_(0, 5.0)  # absurd weights: the correction must still stay within [-5, 5]
        x = _inputs(flow=3.0)
        out = net(*x)
    delta = out["flow"] - x[4]
    assert delta.abs().max() <= 5.0 + 1e-5
    assert delta.abs().max() > 1.0  # and it is not trivially zero


def test_without_mvr_uses_depth_motion():
    net = DSRNet(DSRNetConfig(use_mvr=False)).eval()
    x = _inputs(flow=1.5)
    with torch.no_grad():
        out = net(*x)
    assert torch.equal(out["flow"], x[4])
    assert net.mvr is None
    assert 0 <= out["weight"].min() and out["weight"].max() <= 10.0


def test_paper_preset_is_wider():
    assert count_parameters(DSRNet(preset("paper"))) > 3 * count_parameters(DSRNet(preset("cpu")))


def test_bad_input_shape():
    net = DSRNet(DSRNetConfig())
    x = list(_inputs())
    x[1] = torch.rand(2, 2, 30, 44)
    with pytest.raises(ValueError, match="depth must be"):
        net(*x)


def test_depth_normalisation_is_bounded_when_the_reference_is_all_hole():
    import torch

    from ibr_pipeline.nn.model import normalise_depth
    ref = torch.zeros(2, 1, 8, 8)
    ref[1] = 2.0
    depth = torch.full((2, 1, 8, 8), 3.0)
    out = normalise_depth(depth, ref)
    assert torch.allclose(out[0], torch.ones(1, 8, 8))  # own mean when the reference has no depth
    assert torch.allclose(out[1], torch.full((1, 8, 8), 1.5))
    assert float(normalise_depth(torch.zeros(1, 1, 4, 4), torch.zeros(1, 1, 4, 4)).abs().max()) == 0
