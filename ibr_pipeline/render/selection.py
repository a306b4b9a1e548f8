"""View distance and view selection (Xu et al. 2021, §5.1.1–5.1.2, Eq. 14, Fig. 7).

Pure numpy on camera centres and optical axes; no GL. Conventions of `scene.py`: a camera's
optical axis R^z is the third row of its `cam_from_world` rotation, its centre `-R^T t`. The
paper's t_k is the optical *centre* of view k (§5.1.1), so that is what `centers` holds here.
"""
from __future__ import annotations

import numpy as np

LAMBDA = 1.0          # Eq. 14's translation term as a parallax angle (view_distance; paper: 0.1)
MAX_ANGLE_DEG = 30.0  # §5.1.2 / Fig. 7: maximum angle between optical axes
MAX_DIST_M = 1.8      # §5.1.2 / Fig. 7: maximum distance between optical centres
ANGLE_BINS = 3        # §5.1.2: three angle intervals per quadrant
DIST_BINS = 3         # §5.1.2: three distance intervals per quadrant
FALLBACK_VIEWS = 4    # ours: views taken by smallest d_k when none satisfies the limits


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.maximum(n, 1e-12)


def axis_angle_deg(axes: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Angle in degrees between each (N, 3) axis and one (3,) axis."""
    axes = np.asarray(axes, dtype=np.float64)
    if axes.ndim != 2 or axes.shape[1] != 3 or np.shape(axis) != (3,):
        raise ValueError(f"axes must be (N, 3) and axis (3,), got {axes.shape} and {np.shape(axis)}")
    c = np.clip(_unit(axes) @ _unit(np.asarray(axis, dtype=np.float64)), -1.0, 1.0)
    return np.degrees(np.arccos(c))


def view_distance(axes: np.ndarray, centers: np.ndarray, axis_n: np.ndarray, center_n: np.ndarray,
                  lam: float = LAMBDA, scene_depth: float = 1.0) -> np.ndarray:
    """Eq. 14 for every captured view k: d_k = ∠(R_k^z, R_n^z)·π/180 + λ‖t_k − t_n‖/D.

    The angle is in degrees in the paper, so ∠·π/180 is the angle in radians. The paper divides
    the translation by ‖t_n‖, the novel camera's distance from the world origin, with λ = 0.1.
    That depends on where the origin is: an SfM capture's normalised frame puts it among the
    cameras (‖t_n‖ → 0), a scan's frame in a corner of the room. Here D is the scene's median
    depth (`RenderSettings.scene_depth`), so the term is the angle the baseline subtends at the
    scene, in radians like the first, and the same capture gives the same d_k wherever its
    origin is; λ = 1 weighs rotation and parallax alike (docs/RENDERING.md "View distance").
    """
    axes = np.asarray(axes, dtype=np.float64)
    centers = np.asarray(centers, dtype=np.float64)
    if centers.shape != axes.shape or centers.ndim != 2 or centers.shape[1] != 3:
        raise ValueError(f"axes and centers must both be (N, 3), got {axes.shape}, {centers.shape}")
    if np.shape(center_n) != (3,):
        raise ValueError(f"center_n must be (3,), got {np.shape(center_n)}")
    if not scene_depth > 0:
        raise ValueError(f"scene_depth must be > 0, got {scene_depth}")
    ang = np.radians(axis_angle_deg(axes, axis_n))  # ∠(R_k^z, R_n^z)·π/180
    return ang + lam * np.linalg.norm(centers - np.asarray(center_n, dtype=np.float64),
                                      axis=1) / scene_depth


def sub_regions(R_n: np.ndarray, center_n: np.ndarray, axes: np.ndarray, centers: np.ndarray,
                max_angle: float = MAX_ANGLE_DEG, max_dist: float = MAX_DIST_M,
                angle_bins: int = ANGLE_BINS, dist_bins: int = DIST_BINS) -> np.ndarray:
    """§5.1.2 / Fig. 7: the sub-region index of every view, -1 outside the angle/distance limits.

    8 quadrants (octants) by the sign of the view centre in the novel camera's local x, y, z axes
    × `angle_bins` equal angle intervals of [0, max_angle] × `dist_bins` equal distance intervals
    of [0, max_dist] = 72 sub-regions with the defaults. Fig. 7 is not given numerically; equal
    intervals are our reading of it.
    """
    R_n = np.asarray(R_n, dtype=np.float64)
    if R_n.shape != (3, 3):
        raise ValueError(f"R_n must be (3, 3), got {R_n.shape}")
    local = (np.asarray(centers, dtype=np.float64) - center_n) @ R_n.T  # centres in novel axes
    octant = (local[:, 0] >= 0) * 1 + (local[:, 1] >= 0) * 2 + (local[:, 2] >= 0) * 4
    ang = axis_angle_deg(axes, R_n[2])
    dist = np.linalg.norm(local, axis=1)
    a_bin = np.minimum((ang / max_angle * angle_bins).astype(np.int64), angle_bins - 1)
    d_bin = np.minimum((dist / max_dist * dist_bins).astype(np.int64), dist_bins - 1)
    region = octant * angle_bins * dist_bins + a_bin * dist_bins + d_bin
    inside = (ang <= max_angle) & (dist <= max_dist)
    return np.where(inside, region, -1)


def select_views(R_n: np.ndarray, center_n: np.ndarray, axes: np.ndarray, centers: np.ndarray,
                 dist_k: np.ndarray, available: np.ndarray | None = None,
                 previous: tuple[np.ndarray, np.ndarray, list[int]] | None = None,
                 max_angle: float = MAX_ANGLE_DEG, max_dist: float = MAX_DIST_M,
                 angle_bins: int = ANGLE_BINS, dist_bins: int = DIST_BINS,
                 fallback: int = FALLBACK_VIEWS) -> list[int]:
    """Indices of the selected views, sorted by d_k (smallest first).

    One view of smallest d_k per non-empty sub-region (§5.1.2). Temporal hysteresis: `previous`
    is (R_{n-1}, centre_{n-1}, indices selected then); those views stay selected when they satisfy
    the angle and distance limits widened by ∠(R_n^z, R_{n-1}^z) and ‖t_n − t_{n-1}‖. If no view
    lies within the limits (a camera far from the capture), the `fallback` views of smallest d_k
    are used so that the frame is not empty (ours; the paper does not say).
    """
    n = len(centers)
    dist_k = np.asarray(dist_k, dtype=np.float64)
    if dist_k.shape != (n,):
        raise ValueError(f"dist_k must be ({n},), got {dist_k.shape}")
    avail = np.ones(n, bool) if available is None else np.asarray(available, bool)
    region = sub_regions(R_n, center_n, axes, centers, max_angle, max_dist, angle_bins, dist_bins)
    region = np.where(avail, region, -1)
    chosen: set[int] = set()
    order = np.argsort(dist_k, kind="stable")
    seen: set[int] = set()
    for k in order:  # smallest d_k first: the first view met in a region is its minimum
        r = int(region[k])
        if r >= 0 and r not in seen:
            seen.add(r)
            chosen.add(int(k))
    if previous is not None:
        R_p, c_p, prev_sel = previous
        d_ang = float(axis_angle_deg(np.asarray(R_p)[2][None], np.asarray(R_n)[2])[0])
        d_pos = float(np.linalg.norm(np.asarray(center_n) - np.asarray(c_p)))
        prev = np.array([k for k in prev_sel if 0 <= k < n and avail[k]], dtype=np.int64)
        if len(prev):
            ang = axis_angle_deg(np.asarray(axes)[prev], np.asarray(R_n)[2])
            dist = np.linalg.norm(np.asarray(centers)[prev] - center_n, axis=1)
            keep = (ang <= max_angle + d_ang) & (dist <= max_dist + d_pos)
            chosen.update(int(k) for k in prev[keep])
    if not chosen:
        chosen = {int(k) for k in order if avail[k]}
        chosen = set(sorted(chosen, key=lambda k: dist_k[k])[:fallback])
    return sorted(chosen, key=lambda k: (dist_k[k], k))
