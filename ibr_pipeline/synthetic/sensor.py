"""A simple RGB-D (time-of-flight) depth sensor model, applied to exact sensor-resolution depth.

* noise: Gaussian on depth with sigma(z) = 1.2 mm + 1.9 mm * (z - 0.4 m)^2 (the axial noise
  model of Nguyen et al. 2012 for Kinect-class sensors), then quantised to whole millimetres;
* holes: at grazing incidence (|cos| < 0.25, probability rising to 1 at |cos| = 0.1), one pixel
  around depth discontinuities (relative jump > 4 %), beyond the 0.3-6 m range, and 0.5 % random
  dropouts;
* mirrors return the depth of what they reflect (the path length of the light), glass the depth
  of what lies behind it, refractive solids nothing: `Tracer.sensor_range` computes that input.
"""
from __future__ import annotations

import numpy as np

MIN_RANGE, MAX_RANGE = 0.3, 6.0


def noise_sigma(z: np.ndarray) -> np.ndarray:
    """Axial depth noise (m) at z-depth z (m)."""
    return 0.0012 + 0.0019 * (np.asarray(z) - 0.4) ** 2


def simulate_depth(depth: np.ndarray, cos: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Noisy sensor depth (H, W) in metres, 0 = no measurement, from exact z-depth and the
    incidence cosine of the surface that returned the light (0 where there was no return)."""
    depth = np.asarray(depth, dtype=np.float64)
    cos = np.abs(np.asarray(cos, dtype=np.float64))
    if depth.ndim != 2 or cos.shape != depth.shape:
        raise ValueError(f"depth and cos must be the same (H, W), got {depth.shape}, {cos.shape}")
    valid = (depth > MIN_RANGE) & (depth < MAX_RANGE)
    # grazing angles: drop with probability rising from 0 at cos = 0.25 to 1 at cos = 0.1
    p_drop = np.clip((0.25 - cos) / 0.15, 0, 1)
    valid &= rng.random(depth.shape) >= p_drop
    # edges: relative depth jump to any 4-neighbour
    pad = np.pad(depth, 1, mode="edge")
    jump = np.zeros(depth.shape, dtype=bool)
    for dy, dx in ((0, 1), (2, 1), (1, 0), (1, 2)):
        nb = pad[dy:dy + depth.shape[0], dx:dx + depth.shape[1]]
        jump |= np.abs(nb - depth) > 0.04 * np.minimum(nb, depth).clip(min=1e-6)
    valid &= ~jump
    valid &= rng.random(depth.shape) >= 0.005
    noisy = depth + rng.standard_normal(depth.shape) * noise_sigma(depth)
    return np.where(valid, np.round(noisy * 1000.0) / 1000.0, 0.0)
