"""M_d from depth + poses and backward warping (Xu §5.2.1), against synthetic ground truth."""
import numpy as np
import pytest
import torch

from ibr_pipeline import metrics
from ibr_pipeline.io.images import read_image
from ibr_pipeline.nn.warp import backward_warp, depth_motion
from ibr_pipeline.scene import cameras_from_json


def _gt(folder, name):
    with np.load(folder / "gt/geom" / (name[:-4] + ".npz")) as z:
        return read_image(folder / "images" / name), z["depth"].astype(np.float32)


def test_same_camera_gives_zero_motion(sample_scene):
    cams = cameras_from_json(sample_scene / "cameras.json")
    _, d = _gt(sample_scene, "0003.png")
    flow, valid = depth_motion(d, cams["0003.png"], cams["0003.png"], d)
    assert np.abs(flow).max() < 1e-3
    assert valid.mean() > 0.99


def test_depth_motion_aligns_consecutive_views(sample_scene):
    """Warping view n-1 to view n with M_d reproduces view n on the non-occluded, non-reflective
    pixels far better than no warp (exact GT depth, so only the mirror/gloss and resampling differ)."""
    cams = cameras_from_json(sample_scene / "cameras.json")
    cur, d_cur = _gt(sample_scene, "0005.png")
    prev, d_prev = _gt(sample_scene, "0004.png")
    flow, valid = depth_motion(d_cur, cams["0005.png"], cams["0004.png"], d_prev)
    assert np.abs(flow[valid]).max() > 5  # the views are 15 degrees apart: a real motion
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a.transpose(2, 0, 1)))[None]  # noqa: E731
    warped = backward_warp(t(prev), t(flow))[0][0].permute(1, 2, 0).numpy()
    assert valid.mean() > 0.5
    p_warp = metrics.psnr(cur, warped, valid)
    p_none = metrics.psnr(cur, prev, valid)
    assert p_warp > 24.0 and p_warp > p_none + 8.0, (p_warp, p_none)


def test_backward_warp_integer_shift():
    img = torch.rand(1, 3, 10, 12)
    flow = torch.zeros(1, 2, 10, 12)
    flow[:, 0] = 2.0  # read 2 px to the right
    out, inside = backward_warp(img, flow)
    assert torch.allclose(out[..., :, :-2], img[..., :, 2:], atol=1e-6)
    assert inside[..., :, :-2].min() == 1 and inside[..., :, -1].max() == 0


def test_bad_shapes_raise(sample_scene):
    cams = cameras_from_json(sample_scene / "cameras.json")
    with pytest.raises(ValueError, match="depth size"):
        depth_motion(np.ones((10, 10), np.float32), cams["0000.png"], cams["0001.png"])
    with pytest.raises(ValueError, match=r"\(B, 2, H, W\)"):
        backward_warp(torch.rand(1, 3, 8, 8), torch.rand(1, 3, 8, 8))
