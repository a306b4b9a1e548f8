"""prior_nb.seen_colours (the fused lookup of the reflected-scene prior) against its numpy
reference, reflection_prior.seen_colours_np, and reflected_scene_colour on top of it."""
import numpy as np
import pytest

from ibr_pipeline.geometry.prior_nb import seen_colours
from ibr_pipeline.geometry.reflection_prior import reflected_scene_colour, seen_colours_np
from ibr_pipeline.scene import Camera

W, H = 37, 29


def _camera(eye=(0.3, -0.2, 0.0)):
    K = np.array([[40.0, 0, (W - 1) / 2], [0, 40.0, (H - 1) / 2], [0, 0, 1]])
    return Camera.look_at(np.array(eye), np.array([0.0, 0.0, 3.0]), np.array([0.0, -1.0, 0.0]),
                          K, W, H)


def _view(rng, cam, dtype=np.float32):
    """A depth map of a slanted plane with holes, a reflector mask and an image."""
    ys, xs = np.mgrid[0:H, 0:W]
    depth = (2.5 + 0.02 * xs + 0.01 * ys).astype(np.float32)
    depth[rng.random((H, W)) < 0.1] = 0
    exclude = rng.random((H, W)) < 0.15
    image = rng.random((H, W, 3)).astype(dtype)
    return depth, exclude, image


def _points_on_depth(rng, cam, depth, n):
    """Points on the depth map's surface (some jittered off it), at sub-pixel positions,
    including the image's border, half-pixel ties and positions outside the image."""
    u = rng.uniform(-2.0, W + 1.0, n)
    v = rng.uniform(-2.0, H + 1.0, n)
    u[:20] = np.arange(20) % 4 - 0.5          # ties of the nearest-pixel rounding at the border
    v[20:40] = H - 0.5 - (np.arange(20) % 3)
    xi = np.clip(np.rint(u), 0, W - 1).astype(int)
    yi = np.clip(np.rint(v), 0, H - 1).astype(int)
    z = np.where(depth[yi, xi] > 0, depth[yi, xi], 2.7).astype(np.float64)
    z *= 1 + rng.choice([0.0, 0.0, 0.01, 0.05, -0.05], n)  # in and out of the 3 % tolerance
    pix = np.stack([u, v, np.ones(n)], 1) * z[:, None]
    Xc = pix @ np.linalg.inv(cam.K).T
    X = (Xc - cam.t) @ cam.R  # world = R^T (Xc - t)
    X[-10:-5] = np.nan           # points without a mirror-world point
    X[-5:] = 2 * cam.center - X[-5:] + 1e-3  # behind the camera
    return X


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_matches_the_numpy_reference(seed, dtype):
    rng = np.random.default_rng(seed)
    cam = _camera()
    depth, exclude, image = _view(rng, cam, dtype)
    X = _points_on_depth(rng, cam, depth, 3000)
    got, n = seen_colours(cam, X, depth, exclude, image, 0.03)
    ref, n_ref = seen_colours_np(cam, X, depth, exclude, image, 0.03)
    assert got.shape == ref.shape == (len(X), 3) and got.dtype == np.float64
    # the same points seen (rounding of the projection may differ in the last bit: allow a
    # handful of points whose pixel or depth test sits exactly on a boundary)
    seen, seen_ref = np.isfinite(got[:, 0]), np.isfinite(ref[:, 0])
    assert n == seen.sum() and n_ref == seen_ref.sum()
    assert 0.3 * len(X) < n < 0.9 * len(X)  # the case mixes seen and unseen points
    assert (seen != seen_ref).sum() <= 2
    both = seen & seen_ref
    np.testing.assert_allclose(got[both], ref[both], rtol=0, atol=1e-9)
    assert not seen[-10:].any()  # NaN points and points behind the camera are never seen


def test_reflected_scene_colour_is_the_median_over_the_seeing_views():
    """Three views of the same plane: each point's prior is the median of the colours of the
    views that see it (the point is its own reflection through a plane far behind the cameras:
    mirror(mirror(X)) = X)."""
    rng = np.random.default_rng(5)
    cams = [_camera((0.3, -0.2, 0.0)), _camera((0.0, 0.0, 0.0)), _camera((-0.2, 0.1, 0.0))]
    views = []
    for cam in cams:
        depth, exclude, image = _view(rng, cam)
        views.append((cam, image, depth, exclude))
    X = _points_on_depth(rng, cams[1], views[1][2], 500)
    plane = [0.0, 0.0, 1.0, 50.0]  # z = -50: mirror(X) = X - 2 (z + 50) e_z
    M = np.diag([1.0, 1.0, -1.0])
    X1 = X @ M.T - np.array([0.0, 0.0, 100.0])  # mirror-world points whose reflection is X
    got = reflected_scene_colour(X1, plane, views, tol=0.03)
    cols = np.stack([seen_colours_np(c, X, d, e, i, 0.03)[0] for c, i, d, e in views])
    n = np.isfinite(cols[..., 0]).sum(0)
    assert (n >= 2).sum() > 50  # points seen by several views
    with np.errstate(all="ignore"):
        import warnings
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            ref = np.nanmedian(cols, axis=0)
    ok = np.isfinite(ref[:, 0]) & np.isfinite(got[:, 0])
    assert (np.isfinite(ref[:, 0]) != np.isfinite(got[:, 0])).sum() <= 2
    np.testing.assert_allclose(got[ok], ref[ok], atol=1e-6)


def test_rejects_mismatched_shapes():
    cam = _camera()
    depth, exclude, image = _view(np.random.default_rng(0), cam)
    with pytest.raises(ValueError, match="points must be"):
        seen_colours(cam, np.zeros((4, 2)), depth, exclude, image, 0.03)
    with pytest.raises(ValueError, match="must be 29x37"):
        seen_colours(cam, np.zeros((4, 3)), depth[:-1], exclude, image, 0.03)


def test_views_in_frustum_matches_projecting_into_each_camera():
    """The all-cameras-at-once test against projecting into one camera at a time."""
    from ibr_pipeline.geometry.decompose_terms import project
    from ibr_pipeline.geometry.reflection_prior import views_in_frustum
    rng = np.random.default_rng(3)
    cams = [_camera((x, y, 0.0)) for x, y in rng.uniform(-1, 1, (12, 2))]
    cams.append(Camera.look_at(np.array([0.0, 0.0, 9.0]), np.array([0.0, 0.0, 20.0]),
                               np.array([0.0, -1.0, 0.0]), cams[0].K, W, H))  # looks away
    cams.append(cams[0].resized(2 * W, 2 * H))  # another image size
    X = rng.normal([0.0, 0.0, 3.0], [0.6, 0.6, 0.2], (40, 3))
    ref = []
    for i, cam in enumerate(cams):
        pos, z = project(cam, X)
        if ((z > 0) & (pos[:, 0] > -0.5) & (pos[:, 1] > -0.5) & (pos[:, 0] < cam.width - 0.5)
                & (pos[:, 1] < cam.height - 0.5)).any():
            ref.append(i)
    got = views_in_frustum(X, cams)
    assert got == ref and 12 not in got and (0 in got) == (13 in got)
    assert 3 <= len(got) < len(cams)  # the case has cameras that see the points and some that do not
    assert views_in_frustum(np.zeros((0, 3)), cams) == []
