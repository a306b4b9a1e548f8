"""fusion.plane_depth reads camera-space rays shared by cameras with the same intrinsics."""
import numpy as np

from ibr_pipeline.geometry.fusion import plane_depth
from ibr_pipeline.scene import Camera


def _cam(f, w, h, eye):
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
    return Camera.look_at(np.asarray(eye, float), np.array([0.0, 3.0, 0.0]), (0, 0, 1), K, w, h)


def test_plane_depth_is_exact_for_every_camera_of_a_shared_model():
    """A tilted plane (x + y = 3) seen from cameras that share K (the cached rays) and from ones that do not
    (another focal length, another size): each pixel's z-depth puts its ray's point on the
    plane, computed independently from the camera's own unprojection."""
    r = 1 / np.sqrt(2)
    plane = (r, r, 0.0, -3.0 * r)
    cams = [_cam(100, 40, 30, (0, 0, 0)), _cam(100, 40, 30, (0.5, 0.2, 0.3)),
            _cam(80, 40, 30, (0, 0, 0)), _cam(100, 24, 18, (0.1, 0, 0))]
    for cam in cams:
        z = plane_depth(cam, plane)
        assert z.shape == (cam.height, cam.width) and np.isfinite(z).all()
        uv = cam.pixel_grid().reshape(-1, 2)
        X = cam.unproject(uv, z.reshape(-1))
        np.testing.assert_allclose(X[:, 0] + X[:, 1], 3.0, atol=1e-9)
    a, b = plane_depth(cams[0], plane), plane_depth(cams[2], plane)
    assert not np.allclose(a, b)  # another focal length: other rays, other depths
