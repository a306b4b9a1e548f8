"""Seeded procedural textures evaluated on 2D surface coordinates (metres), fully vectorised.

Every texture is a pure function of (coordinates, parameters, seed): the same surface point has
the same albedo from every view, which is what makes the diffuse layer view-independent. Patterns
are built from hashed-lattice value noise, so they have blobs and corners for SIFT at every
scale, unlike flat colours. Low-texture materials ("plaster") use a low-contrast, low-frequency
variant, as painted walls in real rooms are.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

def _hash2(ix: np.ndarray, iy: np.ndarray, seed: int) -> np.ndarray:
    """Deterministic hash of integer lattice points to floats in [0, 1) (uint32 arithmetic,
    which wraps modulo 2^32 by definition)."""
    h = (np.asarray(ix).astype(np.int64).astype(np.uint32) * np.uint32(0x8DA6B343)
         ^ np.asarray(iy).astype(np.int64).astype(np.uint32) * np.uint32(0xD8163841)
         ^ np.uint32((seed * 0x9E3779B1) & 0xFFFFFFFF))
    for _ in range(2):
        h = (h ^ (h >> np.uint32(16))) * np.uint32(0x45D9F3B)
    h = h ^ (h >> np.uint32(16))
    return h.astype(np.float64) * (1.0 / 4294967296.0)


def value_noise(p: np.ndarray, freq: float, seed: int) -> np.ndarray:
    """Smooth value noise in [0, 1] at (N, 2) points, lattice spacing 1/freq (`noise_nb`: the
    same bits as `value_noise_np`, in one pass)."""
    from .noise_nb import value_noise_nb
    p = np.ascontiguousarray(p, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2:
        raise ValueError(f"points must be (N, 2), got {p.shape}")
    return value_noise_nb(p, float(freq), np.uint64((int(seed) * 0x9E3779B1) & 0xFFFFFFFF))


def value_noise_np(p: np.ndarray, freq: float, seed: int) -> np.ndarray:
    """The reference of `value_noise`, in numpy."""
    q = p * freq
    i = np.floor(q)
    f = q - i
    f = f * f * (3 - 2 * f)
    ix, iy = i[:, 0].astype(np.int64), i[:, 1].astype(np.int64)
    a = _hash2(ix, iy, seed)
    b = _hash2(ix + 1, iy, seed)
    c = _hash2(ix, iy + 1, seed)
    d = _hash2(ix + 1, iy + 1, seed)
    u, v = f[:, 0], f[:, 1]
    return (a * (1 - u) + b * u) * (1 - v) + (c * (1 - u) + d * u) * v


def fbm(p: np.ndarray, freq: float, seed: int, octaves: int = 4, gain: float = 0.5) -> np.ndarray:
    """Fractal sum of value noise, normalised to about [0, 1]."""
    total = np.zeros(len(p))
    amp, norm = 1.0, 0.0
    for o in range(octaves):
        total += amp * value_noise(p, freq * 2.0 ** o, seed + 7919 * o)
        norm += amp
        amp *= gain
    return total / norm


def _dots(uv: np.ndarray, col: np.ndarray, freq: float, seed: int, strength: float) -> np.ndarray:
    """Overlay round spots (one per lattice cell with probability 0.7, random radius, offset and
    brightness): blob features at a controlled scale, what SIFT's detector responds to best."""
    q = uv * freq
    cell = np.floor(q).astype(np.int64)
    cx, cy = cell[:, 0], cell[:, 1]
    present = _hash2(cx, cy, seed) < 0.7
    ox = 0.3 + 0.4 * _hash2(cx, cy, seed + 1)
    oy = 0.3 + 0.4 * _hash2(cx, cy, seed + 2)
    rad = 0.12 + 0.16 * _hash2(cx, cy, seed + 3)
    f = q - cell
    inside = present & ((f[:, 0] - ox) ** 2 + (f[:, 1] - oy) ** 2 < rad ** 2)
    tone = _hash2(cx, cy, seed + 4)
    target = np.where(tone[:, None] < 0.5, col * (1 - strength), col + strength * (1 - col))
    return np.where(inside[:, None], target, col)


@dataclass(frozen=True)
class Texture:
    """A procedural albedo. kind: 'noise' | 'plaster' | 'planks' | 'tiles' | 'flat'."""

    kind: str
    color_a: tuple[float, float, float]
    color_b: tuple[float, float, float]
    freq: float = 4.0  # features per metre
    seed: int = 0
    contrast: float = 1.0

    def albedo(self, uv: np.ndarray) -> np.ndarray:
        """(N, 3) linear albedo in [0, 1] at (N, 2) surface coordinates in metres."""
        uv = np.asarray(uv, dtype=np.float64)
        if uv.ndim != 2 or uv.shape[1] != 2:
            raise ValueError(f"uv must be (N, 2), got {uv.shape}")
        a, b = np.asarray(self.color_a), np.asarray(self.color_b)
        if self.kind == "flat":
            return np.broadcast_to(a, (len(uv), 3)).copy()
        if self.kind == "noise":
            t = fbm(uv, self.freq, self.seed, octaves=6, gain=0.62)
            t = np.clip(0.5 + (t - 0.5) * 2.6 * self.contrast, 0, 1)
            hue = fbm(uv + 13.7, self.freq * 0.5, self.seed + 1, octaves=2)
            col = a[None] * (1 - t[:, None]) + b[None] * t[:, None]
            col = col * (0.75 + 0.5 * hue[:, None])
            return np.clip(_dots(uv, col, self.freq * 2.5, self.seed + 17, 0.55 * self.contrast), 0, 1)
        if self.kind == "plaster":
            t = fbm(uv, self.freq, self.seed, octaves=3)
            return np.clip(a[None] * (1 + 0.12 * self.contrast * (t[:, None] - 0.5)), 0, 1)
        if self.kind == "planks":
            width = 1.0 / self.freq
            row = np.floor(uv[:, 1] / width)
            shift = _hash2(row.astype(np.int64), np.zeros_like(row, dtype=np.int64), self.seed) * 3
            along = uv[:, 0] + shift
            col_id = np.floor(along / 1.2)
            plank = _hash2(row.astype(np.int64), col_id.astype(np.int64), self.seed + 3)
            grain = fbm(np.c_[along * 1.5, uv[:, 1] * 30], 2.0, self.seed + 5, octaves=4)
            t = np.clip(0.35 * plank + 0.65 * grain, 0, 1)
            col = a[None] * (1 - t[:, None]) + b[None] * t[:, None]
            fy = (uv[:, 1] / width) % 1.0
            fx = (along / 1.2) % 1.0
            seam = (np.minimum(fy, 1 - fy) < 0.04) | (np.minimum(fx, 1 - fx) < 0.008)
            col = _dots(uv, col, self.freq * 4, self.seed + 17, 0.3 * self.contrast)  # knots
            return np.clip(np.where(seam[:, None], col * 0.45, col), 0, 1)
        if self.kind == "tiles":
            size = 1.0 / self.freq
            cell = np.floor(uv / size).astype(np.int64)
            tone = _hash2(cell[:, 0], cell[:, 1], self.seed)
            speck = fbm(uv, self.freq * 6, self.seed + 11, octaves=4, gain=0.65)
            t = np.clip(0.45 * tone + 0.55 * (0.5 + 1.8 * (speck - 0.5)), 0, 1)
            col = a[None] * (1 - t[:, None]) + b[None] * t[:, None]
            col = _dots(uv, col, self.freq * 7, self.seed + 17, 0.45 * self.contrast)
            f = (uv / size) % 1.0
            grout = (np.minimum(f, 1 - f) < 0.04).any(axis=1)
            return np.clip(np.where(grout[:, None], 0.85 * np.ones(3)[None] * 0.6, col), 0, 1)
        raise ValueError(f"unknown texture kind {self.kind!r}")
