"""flip_ldr against NVIDIA's flip_evaluator (the official binding, the reference), and its
separable kernels against the paper's 2-D kernels built as the reference implementation does."""
import math

import numpy as np
import pytest

from ibr_pipeline import flip_ldr


def _reference(a, b):
    import flip_evaluator
    err, _, _ = flip_evaluator.evaluate(np.ascontiguousarray(a, np.float32),
                                        np.ascontiguousarray(b, np.float32), "LDR",
                                        inputsRGB=False, applyMagma=False, computeMeanError=False)
    err = np.asarray(err, np.float64)
    return err[..., 0] if err.ndim == 3 else err


def _textured(shape, seed):
    """Smooth colour blobs with hard edges and fine noise: what renders and photos have."""
    import cv2
    rng = np.random.default_rng(seed)
    h, w = shape
    base = cv2.resize(rng.random((h // 8 + 1, w // 8 + 1, 3)).astype(np.float32), (w, h),
                      interpolation=cv2.INTER_CUBIC)
    yy, xx = np.mgrid[:h, :w]
    base[(xx - w / 2) ** 2 + (yy - h / 3) ** 2 < (h / 4) ** 2] = (0.9, 0.2, 0.1)
    base[:, w // 3: w // 3 + 2] = 0.02
    return np.clip(base + rng.normal(0, 0.02, base.shape), 0, 1).astype(np.float32)


@pytest.mark.parametrize("shape,seed", [((96, 128), 0), ((61, 47), 1), ((12, 9), 2)])
def test_flip_map_agrees_with_flip_evaluator(shape, seed):
    a = _textured(shape, seed)
    rng = np.random.default_rng(seed + 10)
    shifted = np.roll(a, 1, axis=1)                     # misregistration: edges disagree
    tinted = np.clip(a * (1.0, 0.9, 1.1), 0, 1)         # colour error only
    noisy = np.clip(a + rng.normal(0, 0.08, a.shape), 0, 1)
    for b in (shifted, tinted, noisy, a):
        ref, ours = _reference(a, b), flip_ldr.flip_map(a, b)
        assert ours.shape == shape
        assert np.abs(ours - ref).max() < 5e-5
        assert abs(float(ours.mean()) - float(ref.mean())) < 1e-6
    assert flip_ldr.flip_map(a, a).max() == 0.0


def _paper_csf_2d(channel, ppd):
    a1, b1, a2, b2 = flip_ldr._CSF[channel]
    r = int(math.ceil(3 * math.sqrt(0.04 / (2 * math.pi ** 2)) * ppd))
    x, y = np.meshgrid(np.arange(-r, r + 1), np.arange(-r, r + 1))
    z = (x / ppd) ** 2 + (y / ppd) ** 2
    g = (a1 * math.sqrt(math.pi / b1) * np.exp(-math.pi ** 2 * z / b1)
         + a2 * math.sqrt(math.pi / b2) * np.exp(-math.pi ** 2 * z / b2))
    return g / g.sum()


def _paper_detector_2d(kind, ppd):
    sd = 0.5 * 0.082 * ppd
    r = int(math.ceil(3 * sd))
    x, y = np.meshgrid(np.arange(-r, r + 1), np.arange(-r, r + 1))
    g = np.exp(-(x ** 2 + y ** 2) / (2 * sd * sd))
    gx = -x * g if kind == "edge" else (x ** 2 / (sd * sd) - 1) * g
    return np.where(gx < 0, gx / -gx[gx < 0].sum(), gx / gx[gx > 0].sum())


@pytest.mark.parametrize("ppd", [flip_ldr.PPD, 20.0])
def test_separable_kernels_are_the_papers_2d_kernels(ppd):
    for ch in ("A", "RG", "BY"):
        sep = sum(w * np.outer(k, k) for k, w in flip_ldr._csf_terms(ch, ppd))
        assert np.abs(sep - _paper_csf_2d(ch, ppd)).max() < 1e-12
    for kind in ("edge", "point"):
        along, across = flip_ldr._detector(kind, ppd)
        assert np.abs(np.outer(across, along) - _paper_detector_2d(kind, ppd)).max() < 1e-12


def test_flip_map_rejects_mismatched_shapes():
    with pytest.raises(ValueError, match="flip_map"):
        flip_ldr.flip_map(np.zeros((4, 4, 3)), np.zeros((4, 5, 3)))
