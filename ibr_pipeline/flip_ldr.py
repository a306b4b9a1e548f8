"""LDR-FLIP (Andersson et al. 2020, "FLIP: A Difference Evaluator for Alternating Images", HPG),
written with OpenCV's separable filters.

Why not NVIDIA's `flip_evaluator` (the official binding, which the tests compare this with): it
convolves with the 2-D kernels (21 × 21 and 19 × 19 taps at the default viewing distance), and
`evaluate` scores five methods on every test view, so FLIP was the largest share of that stage's
CPU time (docs/BENCHMARKS.md). Every FLIP kernel is separable — a Gaussian, a sum of two
Gaussians (the blue-yellow CSF), or a Gaussian times a polynomial in one coordinate (the edge and
point detectors) — so the same filters run here as row and column passes.

The pipeline, in the paper's order (its §4, defaults: 0.7 m wide 4K monitor at 0.7 m, 67 px per
degree): linear RGB → YCxCz; each channel filtered by its contrast sensitivity function; back to
linear RGB, clamped to [0, 1]; CIELAB with the Hunt adjustment; HyAB distance, raised to q_c and
redistributed to [0, 1] (ΔE_c); on the achromatic channel, edge and point detectors (first and
second Gaussian derivatives, σ = 0.5 · 0.082 · ppd), ΔE_f = max of the differences of their
magnitudes, (ΔE_f/√2)^q_f; FLIP = ΔE_c^(1 − ΔE_f). Borders replicate the edge pixels.
"""
from __future__ import annotations

import math

import numpy as np

PPD = 0.7 * 3840 / 0.7 * math.pi / 180   # pixels per degree of the default observer
QC, QF, PC, PT = 0.7, 0.5, 0.4, 0.95

# contrast sensitivity functions as sums of Gaussians (a1, b1, a2, b2) per opponent channel
_CSF = {"A": (1.0, 0.0047, 0.0, 1e-5), "RG": (1.0, 0.0053, 0.0, 1e-5),
        "BY": (34.1, 0.04, 13.5, 0.025)}
_WHITE = np.array([0.950428545, 1.0, 1.088900371])   # D65
_RGB2XYZ = np.array([[10135552 / 24577794, 8788810 / 24577794, 4435075 / 24577794],
                     [2613072 / 12288897, 8788810 / 12288897, 887015 / 12288897],
                     [1425312 / 73733382, 8788810 / 73733382, 70074185 / 73733382]])
_XYZ2RGB = np.linalg.inv(_RGB2XYZ)


def _apply3(m: np.ndarray, img: np.ndarray) -> np.ndarray:
    """(H, W, 3) image times the (3, 3) matrix m per pixel."""
    m = m.astype(np.float32)
    return img @ m.T


def linear_to_ycxcz(rgb: np.ndarray) -> np.ndarray:
    xyz = _apply3(_RGB2XYZ / _WHITE[:, None], rgb)
    y = 116 * xyz[..., 1] - 16
    return np.stack([y, 500 * (xyz[..., 0] - xyz[..., 1]), 200 * (xyz[..., 1] - xyz[..., 2])], -1)


def ycxcz_to_linear(ycc: np.ndarray) -> np.ndarray:
    y = (ycc[..., 0] + 16) / 116
    xyz = np.stack([y + ycc[..., 1] / 500, y, y - ycc[..., 2] / 200], -1)
    return _apply3(_XYZ2RGB * _WHITE[None, :], xyz)


def linear_to_hunt_lab(rgb: np.ndarray) -> np.ndarray:
    """CIELAB (D65) with the Hunt adjustment: a and b scaled by L/100."""
    import cv2
    xyz = np.ascontiguousarray(_apply3(_RGB2XYZ / _WHITE[:, None], rgb), dtype=np.float32)
    d = 6 / 29
    cube_root = cv2.pow(np.maximum(xyz, d ** 3).reshape(-1, 1), 1 / 3).reshape(xyz.shape)  # SIMD
    f = np.where(xyz > d ** 3, cube_root, xyz / (3 * d * d) + 4 / 29)
    L = 116 * f[..., 1] - 16
    h = 0.01 * L
    return np.stack([L, h * 500 * (f[..., 0] - f[..., 1]), h * 200 * (f[..., 1] - f[..., 2])], -1)


def hyab(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """|ΔL| + ‖(Δa, Δb)‖ of two (..., 3) Lab images."""
    d = a - b
    return np.abs(d[..., 0]) + np.sqrt(d[..., 1] ** 2 + d[..., 2] ** 2)


def _csf_terms(channel: str, ppd: float) -> list[tuple[np.ndarray, float]]:
    """The channel's CSF kernel (normalised over its square support, as the paper's 2-D kernel)
    as separable terms [(1-D taps, weight)]: filter = Σ weight · taps ⊗ taps."""
    r = int(math.ceil(3 * math.sqrt(max(max(v[1], v[3]) for v in _CSF.values()) / (2 * math.pi ** 2))
                      * ppd))
    x = np.arange(-r, r + 1, dtype=np.float64) / ppd
    a1, b1, a2, b2 = _CSF[channel]
    terms = [(np.exp(-math.pi ** 2 * x * x / b), a * math.sqrt(math.pi / b))
             for a, b in ((a1, b1), (a2, b2)) if a != 0]
    total = sum(c * k.sum() ** 2 for k, c in terms)
    return [(k, c / total) for k, c in terms]


def _detector(kind: str, ppd: float) -> tuple[np.ndarray, np.ndarray]:
    """1-D taps (along the derivative, across it) of the edge or point detector, normalised as the
    paper's 2-D kernel: its positive weights sum to 1 and its negative weights to −1."""
    sd = 0.5 * 0.082 * ppd
    r = int(math.ceil(3 * sd))
    x = np.arange(-r, r + 1, dtype=np.float64)
    g = np.exp(-x * x / (2 * sd * sd))
    along = -x * g if kind == "edge" else (x * x / (sd * sd) - 1) * g
    along = np.where(along > 0, along / along[along > 0].sum(), along / -along[along < 0].sum())
    return along, g / g.sum()


def _sep(img: np.ndarray, kx: np.ndarray, ky: np.ndarray) -> np.ndarray:
    import cv2
    return cv2.sepFilter2D(img, cv2.CV_32F, kx.astype(np.float32), ky.astype(np.float32),
                           borderType=cv2.BORDER_REPLICATE)


def _filtered_lab(ycc: np.ndarray, ppd: float) -> np.ndarray:
    out = np.empty_like(ycc)
    for c, name in enumerate(("A", "RG", "BY")):
        ch = np.ascontiguousarray(ycc[..., c])
        out[..., c] = sum(w * _sep(ch, k, k) for k, w in _csf_terms(name, ppd))
    return linear_to_hunt_lab(np.clip(ycxcz_to_linear(out), 0.0, 1.0))


def _features(y: np.ndarray, ppd: float) -> tuple[np.ndarray, np.ndarray]:
    """Magnitudes of the (x, y) edge and point responses of the normalised achromatic channel."""
    out = []
    for kind in ("edge", "point"):
        along, across = _detector(kind, ppd)
        fx, fy = _sep(y, along, across), _sep(y, across, along)
        out.append(np.sqrt(fx * fx + fy * fy))
    return out[0], out[1]


def flip_map(reference: np.ndarray, test: np.ndarray, ppd: float = PPD) -> np.ndarray:
    """(H, W) LDR-FLIP error in [0, 1] of two (H, W, 3) linear-RGB images in [0, 1]."""
    ref = np.asarray(reference, dtype=np.float32)
    tst = np.asarray(test, dtype=np.float32)
    if ref.shape != tst.shape or ref.ndim != 3 or ref.shape[2] != 3:
        raise ValueError(f"flip_map: expected two (H, W, 3) images, got {ref.shape} and {tst.shape}")
    ref, tst = np.clip(ref, 0, 1), np.clip(tst, 0, 1)
    y_ref, y_tst = linear_to_ycxcz(ref), linear_to_ycxcz(tst)
    power = hyab(_filtered_lab(y_ref, ppd), _filtered_lab(y_tst, ppd)) ** QC
    lab = linear_to_hunt_lab(np.eye(3, dtype=np.float32)[None])[0]   # pure red, green, blue
    cmax = float(hyab(lab[1], lab[2]) ** QC)
    pccmax = PC * cmax
    dc = np.where(power < pccmax, (PT / pccmax) * power,
                  PT + (power - pccmax) / (cmax - pccmax) * (1.0 - PT))
    e_ref, p_ref = _features(np.ascontiguousarray((y_ref[..., 0] + 16) / 116), ppd)
    e_tst, p_tst = _features(np.ascontiguousarray((y_tst[..., 0] + 16) / 116), ppd)
    df = np.maximum(np.abs(e_ref - e_tst), np.abs(p_ref - p_tst))
    df = (df / math.sqrt(2)) ** QF
    return (dc ** (1.0 - df)).astype(np.float32)
