"""nn/data.low_res_camera on image sizes the supersampling scale does not divide."""
import numpy as np

from ibr_pipeline.nn.data import low_res_camera, supersampled_size
from ibr_pipeline.scene import Camera


def test_odd_sizes_are_cropped_and_pixels_stay_aligned():
    cam = Camera.look_at([0, 0, 0], [0, 0, 1], [0, -1, 0], Camera.intrinsics_from_fov(498, 373, 60),
                         498, 373)
    assert supersampled_size(498, 373, 2) == (498, 372) and supersampled_size(641, 480, 4) == (640, 480)
    lr = low_res_camera(cam, 2)
    assert lr.size == (249, 186)
    pts = np.random.default_rng(0).uniform([-1, -1, 2], [1, 1, 5], (100, 3))
    uv, _ = cam.project(pts)
    uv_lr, _ = lr.project(pts)
    # a low-res pixel covers 2x2 full-res pixels of the (top-left anchored) crop
    assert np.allclose(uv_lr, (uv + 0.5) / 2 - 0.5, atol=1e-9)
