"""Image-quality metrics: PSNR, SSIM, FLIP, each optionally restricted to a mask.

Inputs are float images in [0, 1], (H, W, 3) or (H, W), in the *linear* values we store
(scene.py conventions). PSNR and SSIM are computed on those values as stored. FLIP (Andersson et al.
2020, LDR mode; `flip_ldr`, which agrees with NVIDIA's `flip-evaluator` binding to ~1e-4 per pixel)
models a viewer, so it is given the images as linear RGB (flip-evaluator's `inputsRGB=False`).

SSIM is Wang et al. 2004 with the standard constants (Gaussian window sigma 1.5, K1 0.01, K2 0.03,
data range 1), computed per channel and averaged; the masked variant averages the SSIM map over the
mask. Every function returns a plain float; an empty mask gives NaN (no pixels, no score).
"""
from __future__ import annotations

import numpy as np


def _check(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.shape != b.shape or a.ndim not in (2, 3):
        raise ValueError(f"images must have the same (H,W[,C]) shape, got {a.shape} and {b.shape}")
    if mask is not None and np.asarray(mask).shape != a.shape[:2]:
        raise ValueError(f"mask shape {np.asarray(mask).shape} does not match image {a.shape[:2]}")
    return a, b


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Peak signal-to-noise ratio in dB (peak 1.0); over `mask` pixels when given."""
    a, b = _check(a, b, mask)
    err = (a - b) ** 2
    if err.ndim == 3:
        err = err.mean(axis=2)
    if mask is not None:
        m = np.asarray(mask, dtype=bool)
        if not m.any():
            return float("nan")
        err = err[m]
    mse = float(err.mean())
    return float("inf") if mse == 0 else float(10.0 * np.log10(1.0 / mse))


def gaussian_window(z: np.ndarray, sigma: float = 1.5, truncate: float = 3.5) -> np.ndarray:
    """scipy.ndimage.gaussian_filter(z, sigma, truncate=truncate, mode="reflect") of a 2-D float64
    map, as OpenCV's separable filter (the same normalised taps and border, equal to rounding,
    tested; faster: SSIM is most of an evaluation's time after FLIP)."""
    import cv2
    z = np.asarray(z, dtype=np.float64)
    if z.ndim != 2:
        raise ValueError(f"gaussian_window: expected a 2-D map, got {z.shape}")
    r = int(truncate * float(sigma) + 0.5)   # scipy's radius
    x = np.arange(-r, r + 1, dtype=np.float64)
    k = np.exp(-0.5 * (x / sigma) ** 2)
    k /= k.sum()
    return cv2.sepFilter2D(z, cv2.CV_64F, k, k, borderType=cv2.BORDER_REFLECT)  # = scipy "reflect"


def ssim_map(a: np.ndarray, b: np.ndarray, sigma: float = 1.5) -> np.ndarray:
    """Per-pixel SSIM (H, W), averaged over channels."""
    a, b = _check(a, b, None)
    if a.ndim == 2:
        a, b = a[..., None], b[..., None]
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    out = np.zeros(a.shape[:2])
    for c in range(a.shape[2]):
        x, y = np.ascontiguousarray(a[..., c]), np.ascontiguousarray(b[..., c])
        f = lambda z: gaussian_window(z, sigma)  # noqa: E731
        mx, my = f(x), f(y)
        vx, vy, cxy = f(x * x) - mx * mx, f(y * y) - my * my, f(x * y) - mx * my
        out += ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))
    return out / a.shape[2]


def _masked_mean(values: np.ndarray, mask: np.ndarray | None) -> float:
    """Mean of a per-pixel map, over `mask` pixels when given (NaN for an empty mask)."""
    if mask is None:
        return float(values.mean())
    mask = np.asarray(mask, dtype=bool)
    return float(values[mask].mean()) if mask.any() else float("nan")


def ssim(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean SSIM; over `mask` pixels when given."""
    _check(a, b, mask)
    return _masked_mean(ssim_map(a, b), mask)


def flip_map(reference: np.ndarray, test: np.ndarray) -> np.ndarray:
    """Per-pixel LDR-FLIP error (H, W) in [0, 1]; lower is better (`flip_ldr`: the paper's
    filters as separable passes, tested against NVIDIA's flip_evaluator)."""
    from . import flip_ldr
    a, b = _check(reference, test, None)
    if a.ndim == 2:
        a, b = np.repeat(a[..., None], 3, 2), np.repeat(b[..., None], 3, 2)
    return flip_ldr.flip_map(a, b).astype(np.float64)


def flip(reference: np.ndarray, test: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean LDR-FLIP error; over `mask` pixels when given."""
    _check(reference, test, mask)
    return _masked_mean(flip_map(reference, test), mask)


def all_metrics(reference: np.ndarray, test: np.ndarray, mask: np.ndarray | None = None,
                with_flip: bool = True) -> dict[str, float]:
    """{'psnr', 'ssim', 'flip'} over the whole image, and '<name>_mask' over `mask` if given."""
    _check(reference, test, mask)
    sm = ssim_map(reference, test)  # one map for the whole image and the mask, as for FLIP
    out = {"psnr": psnr(reference, test), "ssim": _masked_mean(sm, None)}
    fm = flip_map(reference, test) if with_flip else None
    if fm is not None:
        out["flip"] = float(fm.mean())
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        out["psnr_mask"] = psnr(reference, test, mask)
        out["ssim_mask"] = _masked_mean(sm, mask)
        if fm is not None:
            out["flip_mask"] = _masked_mean(fm, mask)
    return out
