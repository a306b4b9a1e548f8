"""geometry/mvs.py against the exact ground truth of sample_data/mirror_room."""
import numpy as np
import pytest

from ibr_pipeline.geometry.mvs import geometric_consistency, plane_sweep, select_sources
from ibr_pipeline.io.images import read_image
from ibr_pipeline.io.inputs import read_input

MIRROR = 23  # material index of the mirror in gt/scene.json (mirror_room)


@pytest.fixture(scope="module")
def sample(sample_scene):
    scene = read_input(sample_scene)
    cams = {v.name: v.camera for v in scene.views}
    img = {n: read_image(sample_scene / "images" / n) for n in ("0003.png", "0004.png", "0005.png", "0006.png")}
    gt = {n: np.load(sample_scene / "gt" / "geom" / n.replace(".png", ".npz")) for n in img}
    return cams, img, gt


def test_select_sources_prefers_neighbours(sample):
    cams = sample[0]
    src = select_sources(cams["0005.png"], cams, k=3)
    assert 1 <= len(src) <= 3 and "0005.png" not in src
    assert set(src) <= {"0002.png", "0003.png", "0004.png", "0006.png", "0007.png", "0008.png"}


def test_plane_sweep_matches_ground_truth_depth(sample):
    cams, img, gt = sample
    src = ["0004.png", "0006.png", "0003.png"]
    res = plane_sweep(img["0005.png"], cams["0005.png"], [img[s] for s in src], [cams[s] for s in src],
                      0.4, 8.0, num_depths=48, max_cost=0.3)
    d, mat = gt["0005.png"]["depth"], gt["0005.png"]["material"]
    assert res.depth.shape == d.shape and res.valid.dtype == bool
    assert np.all(res.depth[~res.valid] == 0)
    ok = res.valid & (mat != MIRROR)
    assert ok.mean() > 0.3, f"only {ok.mean():.2f} of the pixels got a depth"
    err = np.abs(res.depth - d)[ok]
    # depth precision: most matched pixels within 5 cm (F-score threshold) and median within 2 cm
    assert np.mean(err < 0.05) > 0.85, np.mean(err < 0.05)
    assert np.median(err) < 0.02


def test_masked_sweep_computes_only_the_mask_and_agrees(sample):
    cams, img, gt = sample
    src = ["0004.png", "0006.png"]
    d = gt["0005.png"]["depth"]
    lo, hi = d * 0.9, d * 1.1  # per-pixel search band around an initial depth (view_depth's use)
    mask = np.zeros(d.shape, bool)
    mask[100:110, 40:280] = True
    args = (img["0005.png"], cams["0005.png"], [img[s] for s in src], [cams[s] for s in src], lo, hi)
    full = plane_sweep(*args, num_depths=16, max_cost=2.0)
    part = plane_sweep(*args, num_depths=16, max_cost=2.0, mask=mask)
    assert not part.valid[~mask].any() and np.all(part.depth[~mask] == 0)
    both = part.valid & full.valid
    assert both.sum() > 0.8 * mask.sum()
    np.testing.assert_allclose(part.depth[both], full.depth[both], rtol=1e-3)
    err = np.abs(part.depth - d)[both & (gt["0005.png"]["material"] != MIRROR)]
    assert np.median(err) < 0.02


def test_geometric_consistency_counts_agreeing_views(sample):
    cams, _, gt = sample
    names = ["0004.png", "0006.png"]
    d = gt["0005.png"]["depth"]
    srcd = [gt[n]["depth"] for n in names]
    cnt = geometric_consistency(cams["0005.png"], d, [cams[n] for n in names], srcd)
    assert cnt.shape == d.shape and cnt.max() <= 2
    assert np.mean(cnt >= 1) > 0.3  # true depths agree wherever the views overlap
    wrong = geometric_consistency(cams["0005.png"], d * 1.1, [cams[n] for n in names], srcd)
    assert np.mean(wrong >= 1) < 0.2 * np.mean(cnt >= 1)


def test_bad_shapes_raise_value_error(sample):
    cams, img, _ = sample
    with pytest.raises(ValueError, match="mask"):
        plane_sweep(img["0005.png"], cams["0005.png"], [img["0004.png"]], [cams["0004.png"]], 0.5, 5,
                    mask=np.ones((3, 3), bool))
    with pytest.raises(ValueError, match="depth_min"):
        plane_sweep(img["0005.png"], cams["0005.png"], [img["0004.png"]], [cams["0004.png"]],
                    np.ones((2, 2)), 5)
    with pytest.raises(ValueError, match="ref_image"):
        plane_sweep(np.zeros((4, 4, 2)), cams["0005.png"], [img["0004.png"]], [cams["0004.png"]], 0.5, 5)


def test_fusion_skips_frames_left_empty_by_masking(tiny_scene):
    """A frame with no valid depth (e.g. all masked as mirror) is skipped, not fatal (open3d
    aborts on it); only when no frame has depth is it an error."""
    import pytest

    from ibr_pipeline.geometry.fusion import FusionOptions, tsdf_fuse
    from ibr_pipeline.io.images import read_depth_png
    from ibr_pipeline.scene import cameras_from_json

    root = tiny_scene[0]
    cams = cameras_from_json(root / "cameras.json")
    name = sorted(cams)[0]
    d = read_depth_png(root / "depth" / f"{name[:-4]}.png")
    mesh, stats = tsdf_fuse([(np.zeros_like(d), cams[name], None), (d, cams[name], None)],
                             FusionOptions(voxel_size=0.02))
    assert stats["frames"] == 1 and stats["skipped_empty_frames"] == 1 and len(mesh.faces) > 100
    with pytest.raises(ValueError, match="no frame has valid depth"):
        tsdf_fuse([(np.zeros_like(d), cams[name], None)], FusionOptions(voxel_size=0.02))


def test_box_sum_equals_direct_window_sums():
    """The integral-image box filter (running sums) equals direct k x k window sums."""
    import torch

    from ibr_pipeline.geometry.mvs import _box_sum
    rng = np.random.default_rng(0)
    x = rng.random((2, 3, 40, 57)) - 0.5
    for k in (3, 7, 9):
        got = _box_sum(torch.as_tensor(x, dtype=torch.float32), k).numpy()
        want = np.zeros(x.shape[:2] + (40 - k + 1, 57 - k + 1))
        for dy in range(k):
            for dx in range(k):
                want += x[..., dy:dy + 40 - k + 1, dx:dx + 57 - k + 1]
        np.testing.assert_allclose(got, want, atol=2e-5)


def test_best_k_aggregation_drops_the_worst_source(sample):
    """With K = sources - 1 the aggregated cost is the mean of the K best single-source costs
    (Kang et al. 2001), computed without sorting."""
    import torch

    from ibr_pipeline.geometry.mvs import _Sweeper, _extract, _gray
    cams, img, _ = sample
    ref, src = "0005.png", ["0004.png", "0006.png", "0003.png"]
    g = _gray(img[ref], "r")[100:140, 100:160]
    # a crop of the reference: shift the principal point accordingly
    K = cams[ref].K.copy()
    K[0, 2] -= 100
    K[1, 2] -= 100
    from ibr_pipeline.scene import Camera
    rc = Camera(K, cams[ref].cam_from_world, 60, 40)
    sgray = [_gray(img[s], s) for s in src]

    def sweeper(idx, k):
        return _Sweeper(g, rc, [sgray[i] for i in idx], [cams[src[i]] for i in idx], [(0, 0)], (40, 60),
                        3, 7, k, torch.device("cpu"))
    inv = torch.as_tensor(_extract(np.full((40, 60), 1 / 2.5), [(0, 0)], (40, 60), 3, 40, 60),
                          dtype=torch.float32)
    inv = torch.stack([inv * f for f in (0.8, 1.0, 1.25)])
    with torch.no_grad():
        agg = sweeper([0, 1, 2], 2).costs(inv).numpy()
        single = np.stack([sweeper([i], 1).costs(inv).numpy() for i in range(3)])
    seen = single < 2.0  # a source in which the pixel does not project costs MAX_COST = 2
    everywhere, two = seen.all(0), seen.sum(0) == 2
    assert everywhere.mean() > 0.2 and two.any()
    want = np.sort(single, 0)[:2].mean(0)  # unseen ones sort last: the mean of the 2 best or seen
    np.testing.assert_allclose(agg[everywhere | two], want[everywhere | two], atol=1e-4)


def test_pyramid_sweep_is_accurate_and_masked_pyramid_agrees(sample):
    """Coarse-to-fine: full sweep one octave down, 16-hypothesis band at full size; as accurate as
    the single-resolution test above, and a masked pyramid sweep gives the unmasked depths."""
    cams, img, gt = sample
    src = ["0004.png", "0006.png", "0003.png"]
    args = (img["0005.png"], cams["0005.png"], [img[s] for s in src], [cams[s] for s in src], 0.4, 8.0)
    res = plane_sweep(*args, num_depths=96, window=9, coarse_levels=1, refine_levels=0, max_cost=0.3)
    d, mat = gt["0005.png"]["depth"], gt["0005.png"]["material"]
    ok = res.valid & (mat != MIRROR)
    assert ok.mean() > 0.3, f"only {ok.mean():.2f} of the pixels got a depth"
    err = np.abs(res.depth - d)[ok]
    assert np.mean(err < 0.05) > 0.85, np.mean(err < 0.05)
    assert np.median(err) < 0.02
    mask = np.zeros(d.shape, bool)
    mask[60:75, 30:200] = True
    part = plane_sweep(*args, num_depths=96, window=9, coarse_levels=1, refine_levels=0, max_cost=2.0,
                       mask=mask)
    full = plane_sweep(*args, num_depths=96, window=9, coarse_levels=1, refine_levels=0, max_cost=2.0)
    assert not part.valid[~mask].any()
    both = part.valid & full.valid
    assert both.sum() > 0.9 * mask.sum()
    # window sums are running sums from the tile's corner: float32 rounding differs between the
    # tiled and the whole-image sweep and may flip a near-tie (a few pixels of thousands)
    same = np.abs(part.depth[both] / full.depth[both] - 1) < 1e-3
    assert same.mean() > 0.99, same.mean()


def test_loop_pairs_close_the_sequence():
    """Sequential matching with overlap k pairs i with i+1..i+k; loop closure adds exactly the
    pairs whose circular distance is <= k but linear distance > k."""
    from ibr_pipeline.geometry.sfm import loop_pairs
    names = [f"{i:03d}" for i in range(30)]
    got = {tuple(sorted(p)) for p in loop_pairs(names, 4)}
    want = {tuple(sorted((names[i], names[j]))) for i in range(30) for j in range(i + 1, 30)
            if j - i > 4 and 30 - (j - i) <= 4}
    assert got == want and len(got) == 10
    assert loop_pairs(names[:5], 4) == []  # short sequences: sequential matching covers all
