"""Camera paths: a hand-held-like capture loop, held-out test views, a smooth fly-through.

All paths circle the free floor area of the room (World.path_center / path_radius) looking
outwards, so together they see every wall. Capture: one loop with smooth seeded wobble in radius,
height, yaw, pitch and roll (a person walking round the room filming the walls). Test: a second,
frames of the same hand-held trajectory half-way between two consecutive capture frames (the
held-out-frame protocol of IBR/NeRF benchmarks: interpolation inside the captured region). The
old inner test loop (smaller radius, lower) is kept as `inner_loop_path`: it extrapolates outside
the captured region (about a quarter of each frame seen by no capture view). Fly-through: a smooth figure-eight-like curve
looking along its direction of travel, for videos.
"""
from __future__ import annotations

import numpy as np

from ..scene import Camera
from .scenes import World

HFOV_DEG = 62.0


def camera_from_angles(eye, yaw: float, pitch: float, roll: float, K, width: int, height: int) -> Camera:
    """Camera at `eye` looking along (yaw, pitch) in the +z-up world, rolled by `roll` radians."""
    # yaw/pitch/roll parametrisation (hand-held wobble), same axes as Camera.look_at
    f = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)])
    x = np.cross(f, (0.0, 0.0, 1.0))
    x /= np.linalg.norm(x)
    y = np.cross(f, x)  # image y points down
    R = np.stack([x, y, f])
    c, s = np.cos(roll), np.sin(roll)
    Rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    T = np.eye(4)
    T[:3, :3] = Rz @ R
    T[:3, 3] = -T[:3, :3] @ np.asarray(eye, dtype=np.float64)
    return Camera(K, T, width, height)


def _wobble(phi: np.ndarray, rng: np.random.Generator, amp: float, harmonics=(2, 3, 5, 7)) -> np.ndarray:
    """A smooth periodic random function of the loop angle (sum of seeded sinusoids)."""
    out = np.zeros_like(phi)
    for h in harmonics:
        out += amp / len(harmonics) ** 0.5 * rng.uniform(0.3, 1.0) * np.sin(h * phi + rng.uniform(0, 2 * np.pi))
    return out


def _loop(world: World, n: int, width: int, height: int, rng, radius: float, height_off: float,
          yaw_off: float, wobble: float, phase: float, steps=None) -> list[Camera]:
    """n cameras at loop angles phase + 2*pi*steps/n (steps = 0..n-1 unless given; fractional
    steps sample the same smooth trajectory in between)."""
    K = Camera.intrinsics_from_fov(width, height, HFOV_DEG)
    steps = np.arange(n, dtype=np.float64) if steps is None else np.asarray(steps, dtype=np.float64)
    phi = phase + 2 * np.pi * steps / n
    r = radius * (1 + _wobble(phi, rng, 0.1) * (wobble > 0))
    cx, cy = world.path_center
    z = world.eye_height + height_off + _wobble(phi, rng, 0.06 * wobble)
    yaw = phi + yaw_off + _wobble(phi, rng, 0.35 * wobble)
    pitch = -0.18 + _wobble(phi, rng, 0.12 * wobble)
    roll = _wobble(phi, rng, 0.04 * wobble, harmonics=(3, 7, 11))
    return [camera_from_angles((cx + r[i] * np.cos(phi[i]), cy + r[i] * np.sin(phi[i]), z[i]),
                               yaw[i], pitch[i], roll[i], K, width, height) for i in range(len(phi))]


def capture_path(world: World, n: int, width: int, height: int, seed: int, steps=None) -> list[Camera]:
    """The n-view capture loop; `steps` (fractional frame indices) samples the same trajectory
    between capture frames."""
    rng = np.random.default_rng([seed, 101])
    phase = rng.uniform(0, 2 * np.pi)
    # radius 1.3 x path_radius: enough sideways baseline between views for triangulation
    return _loop(world, n, width, height, rng, 1.3 * world.path_radius, 0.0, 0.0, 1.0, phase, steps)


def test_path(world: World, n: int, width: int, height: int, seed: int, n_capture: int) -> list[Camera]:
    """n held-out views on the capture trajectory, each half-way between capture frames k and
    k + 1 with k = floor(j * n_capture / n): spread evenly round the loop, never on a capture
    frame, and inside the captured region (a new photograph where the user walked)."""
    if n_capture < 1:
        raise ValueError(f"n_capture must be >= 1, got {n_capture}")
    steps = np.floor(np.arange(n) * n_capture / max(n, 1)) + 0.5
    return capture_path(world, n_capture, width, height, seed, steps)


def inner_loop_path(world: World, n: int, width: int, height: int, seed: int, every: int = 8) -> list[Camera]:
    """n views: every `every`-th frame of a second, smaller and lower loop (radius 0.55x, 20 cm
    lower, yaw offset 0.3 rad). Off the capture path and partly outside the captured region;
    the DSRNet bench's dense stand-in sequences use it (every=1)."""
    rng = np.random.default_rng([seed, 202])
    full = _loop(world, n * every, width, height, rng, 0.55 * world.path_radius, -0.2, 0.3, 0.7,
                 rng.uniform(0, 2 * np.pi))
    return full[::every]


def flythrough_path(world: World, n: int, width: int, height: int) -> list[Camera]:
    """A smooth closed curve, camera looking along the direction of travel (for videos)."""
    K = Camera.intrinsics_from_fov(width, height, HFOV_DEG)
    th = 2 * np.pi * np.arange(n) / max(n, 1)
    cx, cy = world.path_center
    R = world.path_radius
    x, y = cx + 1.2 * R * np.cos(th), cy + 0.8 * R * np.sin(2 * th)
    dx, dy = -1.2 * R * np.sin(th), 1.6 * R * np.cos(2 * th)
    yaw = np.arctan2(dy, dx) + 0.5 * np.sin(th)
    z = world.eye_height + 0.1 * np.sin(3 * th)
    return [camera_from_angles((x[i], y[i], z[i]), yaw[i], -0.12, 0.0, K, width, height)
            for i in range(n)]
