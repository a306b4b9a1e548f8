"""The fused post-processing kernels against the numpy references of blend.py (§5.1.4, Eq. 3)."""
import cv2
import numpy as np
import pytest

from ibr_pipeline.render import blend, post_nb


def _frame(rng, h, w, c, hole_fraction):
    color = rng.random((h, w, c), dtype=np.float32)
    covered = np.ones((h, w), bool)
    # rectangular holes plus scattered single-pixel ones: both the pyramid and the seam matter
    covered[h // 4:h // 2, w // 3:w // 3 + max(w // 5, 1)] = False
    covered &= rng.random((h, w)) > hole_fraction
    return color, covered


@pytest.mark.parametrize("h, w, c", [(37, 53, 3), (48, 64, 4), (5, 129, 4), (96, 31, 3)])
def test_fill_holes_matches_numpy_reference(h, w, c):
    rng = np.random.default_rng(h * w + c)
    color, covered = _frame(rng, h, w, c, 0.1)
    ref = blend.fill_holes(color, covered, 3.0)
    got = post_nb.fill_holes(color, covered, 3.0)
    assert got.shape == ref.shape and got.dtype == np.float32
    np.testing.assert_allclose(got, ref, atol=2e-5)
    far = cv2.distanceTransform(covered.astype(np.uint8), cv2.DIST_L2, 3) >= 3.0
    np.testing.assert_array_equal(got[far], color[far])  # the seam's weight is 1 there


def test_fill_holes_keeps_pixels_away_from_holes_and_fills_holes_smoothly():
    rng = np.random.default_rng(0)
    color = np.full((40, 60, 3), 0.25, np.float32)
    color[:, 30:] = 0.75
    color += rng.normal(0, 1e-3, color.shape).astype(np.float32)
    covered = np.ones((40, 60), bool)
    covered[15:25, 25:35] = False
    got = post_nb.fill_holes(color, covered, 2.0)
    # 4+ pixels from the hole the warped colour is kept exactly
    np.testing.assert_array_equal(got[:10], color[:10])
    # the hole takes colours between the two sides, rising from left to right
    hole = got[15:25, 25:35, 0]
    assert hole.min() > 0.2 and hole.max() < 0.8
    assert np.all(np.diff(hole.mean(0)) >= -1e-4)


@pytest.mark.parametrize("covered_value", [True, False])
def test_fill_holes_all_or_nothing_covered_is_identity(covered_value):
    color = np.random.default_rng(1).random((9, 11, 4), dtype=np.float32)
    got = post_nb.fill_holes(color, np.full((9, 11), covered_value), 3.0)
    np.testing.assert_array_equal(got, color)


def test_fill_holes_rejects_mismatched_shapes():
    with pytest.raises(ValueError, match="does not match"):
        post_nb.fill_holes(np.zeros((4, 5, 3), np.float32), np.ones((5, 4), bool), 3.0)


def test_normalise_matches_numpy_and_boxes_the_reflective_pixels():
    rng = np.random.default_rng(2)
    h, w = 23, 41
    acc = rng.random((h, w, 4), dtype=np.float32) * 3
    acc[rng.random((h, w)) < 0.2, 3] = 0.0  # uncovered pixels
    bacc = np.zeros((h, w), np.float32)
    bacc[5:9, 12:30] = rng.random((4, 18), dtype=np.float32) + 0.01
    front = rng.random((h, w), dtype=np.float32) * 5
    front[0, :] = 1e30  # "nothing in front" sentinel
    color4, covered, depth, box = post_nb.normalise(acc, bacc, front)
    cov = acc[..., 3] > 0
    inv = 1.0 / np.where(cov, acc[..., 3], 1.0)
    ref = np.concatenate([acc[..., :3], bacc[..., None]], -1) * inv[..., None]
    np.testing.assert_array_equal(covered, cov)
    np.testing.assert_allclose(color4, ref, rtol=1e-6, atol=1e-7)
    np.testing.assert_array_equal(depth, np.where(cov & (front < 1e29), front, 0.0))
    refl = ref[..., 3] > 1e-4
    rows, cols = np.flatnonzero(refl.any(1)), np.flatnonzero(refl.any(0))
    assert box == (cols[0], rows[0], cols[-1] - cols[0] + 1, rows[-1] - rows[0] + 1)
    # nothing reflective: no box
    assert post_nb.normalise(acc, np.zeros((h, w), np.float32), front)[3] is None


def test_normalise_rejects_bad_shapes():
    with pytest.raises(ValueError, match="need acc"):
        post_nb.normalise(np.zeros((4, 5, 3)), np.zeros((4, 5)), np.zeros((4, 5)))
    with pytest.raises(ValueError, match="need acc"):
        post_nb.normalise(np.zeros((4, 5, 4)), np.zeros((5, 4)), np.zeros((4, 5)))


def test_finish_is_eq3_inside_the_box_and_clipped():
    rng = np.random.default_rng(3)
    h, w = 17, 29
    color4 = rng.normal(0.5, 0.5, (h, w, 4)).astype(np.float32)  # negatives and beta outside [0,1]
    box = (4, 3, 10, 6)
    x, y, bw, bh = box
    i1 = rng.random((bh, bw, 3), dtype=np.float32)
    color, beta = post_nb.finish(color4, i1, box)
    ref_beta = np.clip(color4[..., 3], 0, 1)
    full_i1 = np.zeros((h, w, 3), np.float32)
    full_i1[y:y + bh, x:x + bw] = i1
    ref = np.clip(blend.compose(color4[..., :3], ref_beta, full_i1), 0, None)
    np.testing.assert_array_equal(beta, ref_beta)
    np.testing.assert_allclose(color, ref, atol=1e-6)
    # without a reflection layer: the surface layer clipped at 0
    color, _ = post_nb.finish(color4)
    np.testing.assert_array_equal(color, np.clip(color4[..., :3], 0, None))


def test_finish_decodes_srgb_layers_before_eq3():
    """srgb=True: both layers hold blended sRGB values; Eq. 3 adds their linear decodings."""
    from ibr_pipeline.io.images import srgb_to_linear
    rng = np.random.default_rng(5)
    h, w = 19, 23
    color4 = rng.normal(0.5, 0.4, (h, w, 4)).astype(np.float32)  # outside [0, 1] too
    box = (2, 5, 11, 7)
    x, y, bw, bh = box
    i1 = rng.random((bh, bw, 3), dtype=np.float32)
    color, beta = post_nb.finish(color4, i1, box, srgb=True)
    full_i1 = np.zeros((h, w, 3), np.float32)
    full_i1[y:y + bh, x:x + bw] = srgb_to_linear(i1)
    ref = blend.compose(srgb_to_linear(color4[..., :3]), np.clip(color4[..., 3], 0, 1), full_i1)
    np.testing.assert_array_equal(beta, np.clip(color4[..., 3], 0, 1))
    np.testing.assert_allclose(color, ref, atol=2e-6)
    grid = np.linspace(0, 1, 1001, dtype=np.float32)
    dec, _ = post_nb.finish(np.stack([grid] * 4, -1)[None])
    np.testing.assert_array_equal(dec[0, :, 0], grid)  # srgb=False: the values as they are
    dec, _ = post_nb.finish(np.stack([grid] * 4, -1)[None], srgb=True)
    np.testing.assert_allclose(dec[0, :, 0], srgb_to_linear(grid), atol=1e-6)


def test_finish_rejects_a_box_outside_the_frame():
    with pytest.raises(ValueError, match="does not fit"):
        post_nb.finish(np.zeros((8, 8, 4), np.float32), np.zeros((4, 4, 3), np.float32), (6, 0, 4, 4))
    with pytest.raises(ValueError, match="does not fit"):
        post_nb.finish(np.zeros((8, 8, 4), np.float32), np.zeros((4, 3, 3), np.float32), (0, 0, 4, 4))
