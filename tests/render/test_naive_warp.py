"""The naïve diffuse-warp baseline (render/naive.py): sampling, visibility and view order."""
import numpy as np

from ibr_pipeline.geometry import raycast
from ibr_pipeline.geometry.decompose_terms import sample_bilinear
from ibr_pipeline.render.naive import NaiveWarp
from ibr_pipeline.scene import Camera


def test_bilinear_matches_opencv_remap():
    import cv2
    rng = np.random.default_rng(0)
    img = rng.random((17, 23, 3)).astype(np.float32)
    u = rng.uniform(0, 22, 500)
    v = rng.uniform(0, 16, 500)
    ref = cv2.remap(img, u.astype(np.float32).reshape(20, 25), v.astype(np.float32).reshape(20, 25),
                    cv2.INTER_LINEAR).reshape(-1, 3)
    assert np.abs(sample_bilinear(img, np.c_[u, v]) - ref).max() < 1e-3  # remap uses 5-bit fixed-point weights


def _quad(x0, x1, y0, y1, z):
    v = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], np.float64)
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def _scene():
    wall_v, wall_f = _quad(-3, 3, -3, 3, 0.0)
    occ_v, occ_f = _quad(0.2, 0.5, -0.15, 0.15, 1.0)  # a small panel half-way to the wall
    return np.vstack([wall_v, occ_v]), np.vstack([wall_f, occ_f + 4])


def _cam(x):
    K = Camera.intrinsics_from_fov(64, 48, 60.0)
    return Camera.look_at((x, 0.0, 2.0), (x, 0.0, 0.0), (0.0, 1.0, 0.0), K, 64, 48)


def test_nearest_view_first_and_occluded_points_from_the_next_view():
    V, F = _scene()
    red, green = np.zeros((48, 64, 3), np.float32), np.zeros((48, 64, 3), np.float32)
    red[..., 0] = 1.0
    green[..., 1] = 1.0
    new = _cam(0.0)
    # A is nearest to the new camera (Eq. 14), B farther; both see the whole wall region in view
    views = {"A": (_cam(0.08), red), "B": (_cam(-0.6), green)}
    img, covered, ms = NaiveWarp(V, F, views).render(new)
    assert img.shape == (48, 64, 3) and ms > 0

    # independent visibility: the new camera's surface points, occluded from A or not
    scene = raycast.build_scene(V, F)
    o, d = raycast.camera_rays(new)
    t = raycast.cast(scene, o, d)["t_hit"]
    pts = o + d * t[:, None]

    def sees(cam):
        occl = raycast.occluded(scene, np.broadcast_to(cam.center, pts.shape).copy(), pts)
        uv, _ = cam.project(pts)
        inside = (uv[:, 0] >= -0.5) & (uv[:, 0] <= 63.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= 47.5)
        return (inside & ~occl).reshape(48, 64), occl.reshape(48, 64)

    sees_a, occl_a = sees(views["A"][0])
    sees_b, _ = sees(views["B"][0])
    assert (occl_a & sees_b).sum() > 10  # a strip of wall the panel hides from A but not from B
    # covered exactly where some view sees the point (up to pixels on the panel's silhouette)
    assert (covered == (sees_a | sees_b)).mean() > 0.98
    from_a = img[..., 0] > 0.9
    from_b = img[..., 1] > 0.9
    assert from_a[sees_a].mean() > 0.98       # the nearest view wherever it sees the point
    assert from_b[~sees_a & sees_b].mean() > 0.98  # the next view where the nearest one cannot


def test_excluded_view_is_not_used():
    V, F = _scene()
    red, green = np.zeros((48, 64, 3), np.float32), np.zeros((48, 64, 3), np.float32)
    red[..., 0] = 1.0
    green[..., 1] = 1.0
    views = {"A": (_cam(0.08), red), "B": (_cam(-0.6), green)}
    img, _, _ = NaiveWarp(V, F, views).render(_cam(0.0), exclude=("A",))
    assert (img[..., 0] > 0.5).mean() < 0.01


def test_depth_files_stand_in_for_casting(tmp_path):
    """Views whose G depth is on disk (view_depth's depth_init.npy) are read, not cast: the same
    frame as casting; a file of the wrong size is cast instead of trusted."""
    V, F = _scene()
    red, green = np.zeros((48, 64, 3), np.float32), np.zeros((48, 64, 3), np.float32)
    red[..., 0] = 1.0
    green[..., 1] = 1.0
    views = {"A": (_cam(0.08), red), "B": (_cam(-0.6), green)}
    scene = raycast.build_scene(V, F)
    np.save(tmp_path / "A.npy", raycast.render_depth(scene, views["A"][0]).astype(np.float32))
    np.save(tmp_path / "B.npy", np.zeros((4, 4), np.float32))      # stale: another size
    cast_img, cast_cov, _ = NaiveWarp(V, F, views).render(_cam(0.0))
    warp = NaiveWarp(V, F, views, depths={"A": tmp_path / "A.npy", "B": tmp_path / "B.npy"})
    img, cov, _ = warp.render(_cam(0.0))
    assert np.array_equal(cov, cast_cov) and np.abs(img - cast_img).max() < 1e-6
    assert warp._view_depth("B").shape == (48, 64)
    # the file is what is used: a depth map that hides everything from A leaves A unused
    np.save(tmp_path / "A.npy", np.full((48, 64), 0.3, np.float32))
    img2, _, _ = NaiveWarp(V, F, views, depths={"A": tmp_path / "A.npy"}).render(_cam(0.0))
    assert (img2[..., 0] > 0.5).mean() < 0.01
