"""`fusion.auto_voxel_size`: the TSDF voxel follows the depth frames' pixel footprint."""
import numpy as np
import pytest

from ibr_pipeline.geometry.fusion import auto_voxel_size
from ibr_pipeline.scene import Camera


def _cam(w=640, h=480, f=500.0):
    K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]])
    return Camera(K=K, cam_from_world=np.eye(4), width=w, height=h)


def _plane(h, w, z):
    d = np.full((h, w), z)
    d[: h // 4] = 0  # some pixels without depth must not count
    return d


def test_voxel_is_two_footprints_at_the_median_depth():
    cam = _cam()
    # 320x240 depth for a 640x480 camera with f = 500: f at the depth size is 250
    for z, expect in ((2.5, 0.02), (1.25, 0.01), (5.0, 0.04)):
        assert auto_voxel_size([(_plane(240, 320, z), cam)]) == pytest.approx(expect)
    # twice the depth resolution halves the footprint
    assert auto_voxel_size([(_plane(480, 640, 2.5), cam)]) == pytest.approx(0.01)


def test_median_over_frames_rounding_and_range():
    cam = _cam()
    frames = [(_plane(240, 320, z), cam) for z in (1.0, 2.6, 9.0)]
    assert auto_voxel_size(frames) == pytest.approx(0.02)                # median frame: 2.08 cm
    assert auto_voxel_size([(_plane(240, 320, 0.05), cam)]) == pytest.approx(0.005)   # floor
    assert auto_voxel_size([(_plane(240, 320, 100.0), cam)]) == pytest.approx(0.05)   # ceiling
    # SfM units: not rounded, not clamped
    assert auto_voxel_size([(_plane(240, 320, 2.6), cam)], metric=False) == pytest.approx(2 * 2.6 / 250)


def test_no_depth_or_bad_shape_is_an_error():
    cam = _cam()
    with pytest.raises(ValueError, match="no depth"):
        auto_voxel_size([(np.zeros((240, 320)), cam), (np.full((240, 320), np.nan), cam)])
    with pytest.raises(ValueError, match="h, w"):
        auto_voxel_size([(np.ones((240, 320, 1)), cam)])
