"""geometry/patchmatch.py against an analytic scene: a slanted plane and a box in front of it,
textured with a solid (3-D) noise and rendered by exact ray casting in numpy, so the true depth
and normal of every pixel are known without the code under test."""
import math

import numpy as np
import pytest

from ibr_pipeline.geometry.mvs import plane_sweep
from ibr_pipeline.geometry.patchmatch import (PatchMatchOptions, PatchMatchResult, face_camera,
                                              patchmatch, patchmatch_views, plane_warp)
from ibr_pipeline.scene import Camera

# --- the scene --------------------------------------------------------------------------------
PLANE_N = np.array([0.3, -1.5, -1.0]) / np.linalg.norm([0.3, -1.5, -1.0])  # n.X = 0, a floor-like
BOX_LO, BOX_HI = np.array([-0.6, -0.1, -1.3]), np.array([-0.1, 0.4, -0.85])  # slant of 58 degrees
# camera centres (x, y) at z = -3.5, all looking at (0, 0, -0.3): baselines of 8-16 degrees; the
# reference (first) view sees the plane between 2.1 and 10.2 depth units
EYES = [(0, 0), (-1.0, 0), (1.0, 0), (0, -0.7), (0, 0.5), (0.7, -0.6)]
DEPTH_RANGE = (1.5, 20.0)
_rng = np.random.default_rng(7)
_DIRS = _rng.normal(size=(48, 3))
_FREQ = (_DIRS / np.linalg.norm(_DIRS, axis=1, keepdims=True)) * _rng.uniform(15, 70, (48, 1))
_PHASE = _rng.uniform(0, 2 * math.pi, 48)


def texture(points):
    """Solid noise in [0.1, 0.9]: a sum of 48 random 3-D sinusoids (wavelengths 3-14 px here)."""
    v = np.sin(points @ _FREQ.T + _PHASE).sum(-1) / math.sqrt(24)
    return 0.5 + 0.4 * np.tanh(v)


def cast(cam: Camera, uv):
    """Nearest hit of the rays through pixels uv (N, 2): (world point, z-depth, world normal, label
    0 = plane / 1 = box)."""
    C = cam.center
    d = np.linalg.solve(cam.K, np.c_[uv, np.ones(len(uv))].T).T @ cam.R  # world dirs, cam z = 1
    t_plane = -(C @ PLANE_N) / (d @ PLANE_N)
    with np.errstate(divide="ignore", invalid="ignore"):
        t0, t1 = (BOX_LO - C) / d, (BOX_HI - C) / d
    tn = np.minimum(t0, t1).max(1)
    tf = np.maximum(t0, t1).min(1)
    box = (tn <= tf) & (tn > 0) & (tn < t_plane)
    t = np.where(box, tn, t_plane)
    X = C + t[:, None] * d
    axis = np.argmax(np.minimum(t0, t1), 1)  # the slab that was entered last is the face hit
    nb = np.zeros_like(X)
    nb[np.arange(len(X)), axis] = -np.sign(d[np.arange(len(X)), axis])
    normal = np.where(box[:, None], nb, PLANE_N)
    return X, t, normal, box.astype(int)  # t is the z-depth: d has cam z = 1


def make_scene(width=112, height=84, eyes=EYES, scale=1.0, contrast=1.0, noise=0.01, seed=1):
    """Images (H, W, 3) (2 x 2 supersampled, texture contrast scaled by `contrast`, Gaussian
    noise of std `noise` added), cameras (translations x `scale`), true z-depth (x `scale`),
    camera-frame normal and label (0 plane, 1 box) maps."""
    rng = np.random.default_rng(seed)
    K = Camera.intrinsics_from_fov(width, height, 50.0)
    cams, imgs, gt = [], [], []
    for ex, ey in eyes:
        cam = Camera.look_at([ex, ey, -3.5], [0, 0, -0.3], [0, -1, 0], K, width, height)
        u, v = np.meshgrid(np.arange(width, dtype=float), np.arange(height, dtype=float))
        uv = np.c_[u.ravel(), v.ravel()]
        grey = np.zeros(len(uv))
        for du in (-0.25, 0.25):
            for dv in (-0.25, 0.25):
                X, _, _, lab = cast(cam, uv + [du, dv])
                grey += (0.5 + contrast * (texture(X) - 0.5)) * np.where(lab == 1, 0.9, 1.0) / 4
        X, z, n, lab = cast(cam, uv)
        img = np.stack([grey, 0.95 * grey, 0.9 * grey], -1).reshape(height, width, 3)
        img = np.clip(img + rng.normal(0.0, noise, img.shape), 0.0, 1.0)
        T = cam.cam_from_world.copy()
        T[:3, 3] *= scale
        cams.append(Camera(cam.K, T, width, height))
        imgs.append(img.astype(np.float32))
        gt.append(dict(depth=(z * scale).reshape(height, width), label=lab.reshape(height, width),
                       normal=(n @ cam.R.T).reshape(height, width, 3)))
    return imgs, cams, gt


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    """Timings of a shared 2-core machine: threads beyond the free cores only spin-wait."""
    import torch
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


@pytest.fixture(scope="module")
def scene():
    return make_scene()


@pytest.fixture(scope="module")
def weak_scene():
    """Low contrast (texture amplitude 0.06) under noise 0.02: a weakly textured wall."""
    return make_scene(contrast=0.15, noise=0.02)


def interior(label, which, margin=3):
    """Pixels of `which` label at least `margin` pixels from the other label and the border."""
    import scipy.ndimage as ndi
    m = ndi.binary_erosion(label == which, iterations=margin)
    m[:margin], m[-margin:], m[:, :margin], m[:, -margin:] = False, False, False, False
    return m


def rel_err(depth, true):
    return np.abs(depth - true) / true


def correct(res, true, tol, where=None):
    """Fraction of the pixels (of `where`) that are valid and within `tol` of the true depth."""
    ok = res.valid & (rel_err(np.where(res.valid, res.depth, 1.0), true) < tol)
    return float(np.mean(ok if where is None else ok[where]))


def run_ref(scene, opts=PatchMatchOptions(), **kw):
    imgs, cams, _ = scene
    return patchmatch(imgs[0], cams[0], imgs[1:5], cams[1:5], *DEPTH_RANGE, opts, **kw)


# --- tests --------------------------------------------------------------------------------------
def test_plane_warp_matches_projection_of_plane_points():
    """The homography samples of a window land where the camera projects the 3-D points of the
    plane under those window pixels (independent ray-plane intersection); the affine expansion
    stays within 0.1 px of them on an 11-pixel window at a focal length of ~280 px."""
    import torch
    K_ref, K_src = Camera.intrinsics_from_fov(320, 240, 60), Camera.intrinsics_from_fov(360, 280, 55)
    ref = Camera.look_at([0, 0, -3], [0, 0, 0], [0, -1, 0], K_ref, 320, 240)
    src = Camera.look_at([0.7, -0.2, -2.8], [0.1, 0, 0], [0, -1, 0], K_src, 360, 280)
    rel = src.cam_from_world @ ref.world_from_cam
    A, b = src.K @ rel[:3, :3] @ np.linalg.inv(ref.K), src.K @ rel[:3, 3]
    n_cam = np.array([0.3, -0.4, -0.8]) / np.linalg.norm([0.3, -0.4, -0.8])
    pix, depth = np.array([[20.0, 231.0], [300.0, 12.0]]), np.array([[2.7, 3.4]])  # 1 hypothesis each
    offs = np.array([[-5.0, -5.0], [1.0, -1.0], [3.0, 5.0], [5.0, 5.0]])
    T = lambda a: torch.as_tensor(a, dtype=torch.float64)  # noqa: E731
    args = (T(A), T(b), T(np.linalg.inv(ref.K)), T(pix), T(depth),
            T(np.broadcast_to(n_cam, (1, 2, 3)).copy()), T(offs))
    centre, samp = plane_warp(*args)
    _, affine = plane_warp(*args, exact=False)
    shift = []  # how far the warp is from a plain translation of the window
    for i in range(2):
        X0 = depth[0, i] * np.linalg.solve(ref.K, [*pix[i], 1.0])  # plane through X0 with n_cam
        uv0, _ = src.project((ref.world_from_cam @ np.r_[X0, 1.0])[None, :3])
        np.testing.assert_allclose(centre[0, i, :2].numpy() / centre[0, i, 2].item(), uv0[0], atol=1e-6)
        for j, o in enumerate(offs):
            ray = np.linalg.solve(ref.K, [*(pix[i] + o), 1.0])
            Xc = ray * (n_cam @ X0) / (n_cam @ ray)
            uv, _ = src.project((ref.world_from_cam @ np.r_[Xc, 1.0])[None, :3])
            np.testing.assert_allclose(samp[j, 0, i].numpy(), uv[0], atol=1e-6)
            assert np.linalg.norm(affine[j, 0, i].numpy() - uv[0]) < 0.1
            shift.append(np.linalg.norm(uv[0] - uv0[0] - o))
    assert max(shift) > 1.0


def test_face_camera_turns_and_limits_normals():
    """Normals come out unit, facing the camera and at most 80 degrees from the reversed ray;
    those already inside that cone only change sign."""
    import torch
    g = torch.Generator().manual_seed(0)
    v = torch.randn(4000, 3, generator=g, dtype=torch.float64)
    v /= v.norm(dim=1, keepdim=True)
    n = torch.randn(4000, 3, generator=g, dtype=torch.float64)
    c = math.cos(math.radians(80))
    out = face_camera(n, v, c)
    assert torch.allclose(out.norm(dim=1), torch.ones(4000, dtype=torch.float64))
    assert ((out * v).sum(1) <= -c + 1e-9).all()
    unit = n / n.norm(dim=1, keepdim=True)
    cos = (unit * v).sum(1)
    inside = cos.abs() >= c
    assert inside.float().mean() > 0.7 and (~inside).any()
    assert torch.allclose(out[inside], -torch.sign(cos[inside, None]) * unit[inside])


def test_slanted_plane_is_dense_accurate_with_true_normals(scene):
    """(a) On the 58-degree slanted plane: >= 90 % valid, median relative depth error <= 1 %,
    median normal error <= 10 degrees; the box in front is found too."""
    _, _, gt = scene
    res = run_ref(scene)
    assert isinstance(res, PatchMatchResult) and res.depth.shape == gt[0]["depth"].shape
    assert res.normal.shape == gt[0]["depth"].shape + (3,) and res.depth.dtype == np.float32
    plane = interior(gt[0]["label"], 0)
    valid = res.valid[plane]
    assert valid.mean() >= 0.9, valid.mean()
    err = rel_err(res.depth, gt[0]["depth"])[plane & res.valid]
    assert np.median(err) <= 0.01, np.median(err)
    cos = (res.normal * gt[0]["normal"]).sum(-1)[plane & res.valid]
    ang = np.degrees(np.arccos(np.clip(cos, -1, 1)))
    assert np.median(ang) <= 10.0, np.median(ang)
    assert correct(res, gt[0]["depth"], 0.02, interior(gt[0]["label"], 1)) >= 0.8


def test_denser_than_plane_sweep_at_equal_error(weak_scene):
    """(b) Pixels with a depth within 1 % / 2 % of the truth, as a fraction of the image:
    PatchMatch vs the fronto-parallel plane sweep on the same low-contrast images (its defaults
    but k_best 2 and max_cost 0.6 like ours)."""
    imgs, cams, gt = weak_scene
    pm = run_ref(weak_scene)
    ps = plane_sweep(imgs[0], cams[0], imgs[1:5], cams[1:5], *DEPTH_RANGE, k_best=2, max_cost=0.6)
    for tol, margin in ((0.02, 0.03), (0.01, 0.04)):
        f_pm, f_ps = correct(pm, gt[0]["depth"], tol), correct(ps, gt[0]["depth"], tol)
        assert f_pm >= f_ps + margin, (tol, f_pm, f_ps)
    assert correct(pm, gt[0]["depth"], 0.02) >= 0.8


def test_views_filter_drops_inconsistent_depth(scene):
    """(c) patchmatch_views with a fifth view whose image is unrelated noise, max_cost 2 (no
    photometric rejection) and no geometric sweeps: without the forward-backward filter every
    pixel of it is 'valid'; with it < 10 % is (random depths that happen to lie within the 2 %
    tolerance of a source's surface), and the good views keep >= 90 % of their
    correct pixels (within 2 %) while losing >= 75 % of the wrong ones (off by > 5 %)."""
    imgs, cams, gt = scene
    names = ["a", "b", "c", "d", "bad"]
    rng = np.random.default_rng(3)
    images = dict(zip(names, imgs[:4] + [rng.random(imgs[4].shape).astype(np.float32)]))
    args = (images, dict(zip(names, cams[:5])), {n: [m for m in names if m != n] for n in names},
            {n: DEPTH_RANGE for n in names})
    opts = PatchMatchOptions(max_cost=2.0, iterations=2, geom_iterations=0)
    raw = patchmatch_views(*args, PatchMatchOptions(**{**opts.to_dict(), "filter_min_views": 0}))
    res = patchmatch_views(*args, opts)
    assert set(res) == set(names)
    assert raw["bad"].valid.mean() == 1.0 and res["bad"].valid.mean() < 0.1
    for i, n in enumerate(names[:4]):
        err = rel_err(np.where(res[n].valid, res[n].depth, 1), gt[i]["depth"])
        err_raw = rel_err(raw[n].depth, gt[i]["depth"])
        right, right_raw = np.mean(res[n].valid & (err < 0.02)), np.mean(err_raw < 0.02)
        wrong, wrong_raw = np.mean(res[n].valid & (err > 0.05)), np.mean(err_raw > 0.05)
        assert right >= 0.9 * right_raw and right >= 0.6, (n, right, right_raw)
        assert wrong <= 0.25 * wrong_raw and wrong <= 0.02, (n, wrong, wrong_raw)


def test_geometric_term_uses_source_depths(weak_scene):
    """(c) With weak texture, the geometric term against true source depth maps (from the ground
    truth) makes more pixels correct than the photometric cost alone; against source depths that
    are all 5 % too far it pulls the depth away from the truth (it is really used)."""
    imgs, cams, gt = weak_scene
    photo = run_ref(weak_scene)
    geo = run_ref(weak_scene, src_depths=[g["depth"] for g in gt[1:5]])
    f_geo, f_photo = correct(geo, gt[0]["depth"], 0.01), correct(photo, gt[0]["depth"], 0.01)
    assert f_geo >= f_photo + 0.05, (f_geo, f_photo)
    far = run_ref(weak_scene, PatchMatchOptions(geom_weight=1.0, max_cost=2.0),
                  src_depths=[g["depth"] * 1.05 for g in gt[1:5]])
    plane = interior(gt[0]["label"], 0)
    assert np.median((far.depth / gt[0]["depth"])[plane]) > 1.02


def test_init_depth_is_refined(scene):
    """A slightly wrong init_depth (1 % too far) is used and refined: one sweep from it beats one
    sweep from random hypotheses by far."""
    imgs, cams, gt = scene
    one = PatchMatchOptions(iterations=1, levels=0)
    plane = interior(gt[0]["label"], 0)
    f_init = correct(run_ref(scene, one, init_depth=gt[0]["depth"] * 1.01), gt[0]["depth"], 0.01, plane)
    f_rand = correct(run_ref(scene, one), gt[0]["depth"], 0.01, plane)
    assert f_init >= 0.9 and f_init >= f_rand + 0.2, (f_init, f_rand)


def test_independent_of_scene_scale(scene):
    """(e) Translations and depth range x 1000: depths x 1000 (1e-3 relative), same valid mask up
    to a handful of pixels, same normals."""
    base = run_ref(scene)
    imgs, cams_k, _ = make_scene(scale=1000.0)
    big = patchmatch(imgs[0], cams_k[0], imgs[1:5], cams_k[1:5], DEPTH_RANGE[0] * 1000,
                     DEPTH_RANGE[1] * 1000)
    assert np.sum(base.valid != big.valid) <= 5
    both = base.valid & big.valid
    np.testing.assert_allclose(big.depth[both] / 1000.0, base.depth[both], rtol=1e-3)
    assert np.median((base.normal * big.normal).sum(-1)[both]) > 0.9999


def test_bad_arguments_raise_value_error(scene):
    """(d) Library errors are ValueErrors that name the argument."""
    imgs, cams, _ = scene
    ok = (imgs[0], cams[0], imgs[1:3], cams[1:3], 1.5, 20.0)
    cases = [
        (dict(ref_image=np.zeros((20, 20, 2))), "ref_image"),
        (dict(src_images=imgs[1:3], src_cams=cams[1:2]), "as many cameras"),
        (dict(src_images=[], src_cams=[]), "source image"),
        (dict(depth_min=5.0, depth_max=2.0), "depth_min < depth_max"),
        (dict(depth_min=np.ones((3, 3))), "scalars"),
        (dict(init_depth=np.ones((5, 5))), "init_depth"),
        (dict(src_depths=[np.ones((84, 112))]), "src_depths"),
        (dict(src_depths=[np.ones((84, 112, 1)), None]), r"src_depths\[0\]"),
        (dict(opts=PatchMatchOptions(window=8)), "window"),
        (dict(opts=PatchMatchOptions(iterations=0)), "iterations"),
    ]
    if not _has_cuda():
        cases.append((dict(device="cuda"), "CUDA"))
    names = ["ref_image", "ref_cam", "src_images", "src_cams", "depth_min", "depth_max"]
    for change, msg in cases:
        kw = dict(zip(names, ok))
        kw.update(change)
        with pytest.raises(ValueError, match=msg):
            patchmatch(**kw)
    with pytest.raises(ValueError, match="sources must be other views"):
        patchmatch_views({"a": imgs[0]}, {"a": cams[0]}, {"a": ["b"]}, {"a": (1.5, 20.0)})
    with pytest.raises(ValueError, match="ranges"):
        patchmatch_views({"a": imgs[0], "b": imgs[1]}, {"a": cams[0], "b": cams[1]},
                         {"a": ["b"]}, {})


def _has_cuda():
    import torch
    return torch.cuda.is_available()


@pytest.mark.skipif(not _has_cuda(), reason="no CUDA device")
def test_cuda_gives_the_same_quality(scene):
    _, _, gt = scene
    res = run_ref(scene, device="cuda")
    plane = interior(gt[0]["label"], 0)
    err = rel_err(np.where(res.valid, res.depth, 1), gt[0]["depth"])
    assert res.valid[plane].mean() >= 0.9 and np.median(err[plane & res.valid]) <= 0.01


def test_worker_processes_give_the_serial_maps_bit_for_bit(scene):
    """global_mesh hands each PatchMatch pass's views to `--jobs` worker processes (map_fn): the
    depth, normal and cost maps are identical to the serial run's, geometric passes and filter
    included (every view's seed is fixed by its position, each task runs with one torch thread)."""
    from ibr_pipeline.executors import LocalExecutor
    from ibr_pipeline.stages.global_mesh import _pool_map
    imgs, cams, _ = scene
    names = ["a", "b", "c", "d"]
    args = (dict(zip(names, imgs[:4])), dict(zip(names, cams[:4])),
            {n: [m for m in names if m != n] for n in names}, {n: DEPTH_RANGE for n in names})
    opts = PatchMatchOptions(iterations=2, geom_iterations=1)
    serial = patchmatch_views(*args, opts)
    with LocalExecutor(2) as ex:
        pooled = patchmatch_views(*args, opts, map_fn=_pool_map(ex, 1))
    for n in names:
        assert serial[n].valid.mean() > 0.5, n
        for field in ("depth", "normal", "cost"):
            assert np.array_equal(getattr(serial[n], field), getattr(pooled[n], field)), (n, field)


@pytest.mark.parametrize("warp", ["affine", "homography"])
def test_matcher_cost_matches_a_vectorised_ncc(warp):
    """The matcher accumulates the weighted window sums one sample at a time; here the same cost
    is computed the direct way (every sample warped at once by `plane_warp`, one grid_sample,
    weighted sums over the window axis) for random hypotheses of the analytic scene."""
    import torch
    import torch.nn.functional as F

    from ibr_pipeline.geometry.patchmatch import FLAT_VAR, MAX_COST, _UNSEEN, _Matcher, best_k_mean
    imgs, cams, _ = make_scene(width=64, height=48, eyes=EYES[:4])
    gray = [im.mean(2).astype(np.float32) for im in imgs]
    opts = PatchMatchOptions(warp=warp, sources_k_best=2)
    scale = math.sqrt(DEPTH_RANGE[0] * DEPTH_RANGE[1])
    m = _Matcher(gray[0], cams[0], [(g, c, None) for g, c in zip(gray[1:], cams[1:])], scale, opts,
                 torch.device("cpu"))
    gen = torch.Generator().manual_seed(5)
    idx = torch.randperm(64 * 48, generator=gen)[:300]
    depth = (DEPTH_RANGE[0] + torch.rand(300, 3, generator=gen) * 6.0) / scale
    normal = face_camera(torch.randn(300, 3, 3, generator=gen), m.view[idx][:, None], 0.17)
    got = m.cost(idx, depth, normal, geom=False)                      # (P, h)

    pix, w, wr = m.pix[idx], m.w[:, None, idx], m.wr[:, None, idx]
    d, nrm = depth.T.contiguous(), normal.transpose(0, 1).contiguous()
    per = []
    for s in m.sources:
        centre, grid = plane_warp(s["A"], s["b"], m.kinv, pix, d, nrm, m.offsets,
                                  exact=warp == "homography")
        n, h, P = grid.shape[:3]
        val = F.grid_sample(s["img"], grid.reshape(1, n, h * P, 2), mode="bilinear",
                            padding_mode="zeros", align_corners=True).reshape(n, h, P)
        mean, m2, cov = (val * w).sum(0), (val * val * w).sum(0), (val * wr).sum(0)
        c = (1 - cov / (m2 - mean * mean).clamp_min(FLAT_VAR).sqrt()).clamp(0, MAX_COST)
        z = centre[..., 2]
        ok = (z > 1e-6) & ((centre[..., 0] / z.clamp_min(1e-6)).abs() <= s["lim"][0]) \
            & ((centre[..., 1] / z.clamp_min(1e-6)).abs() <= s["lim"][1])
        per.append(torch.where(ok, c, torch.full_like(c, _UNSEEN)))
    agg = best_k_mean(torch.stack(per), 2)
    want = torch.where(m.flat[idx] & (agg < MAX_COST), torch.ones(()), agg).T
    assert got.shape == want.shape == (300, 3)
    assert float((got - want).abs().max()) < 1e-4
    assert float(want.std()) > 0.05   # hypotheses of varied quality, not all one value
