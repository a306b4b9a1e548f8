"""Scene scale and camera-path checks for the `poses` stage (docs/DESIGN.md "Scene frame").

A capture without depth frames has no metric scale: SfM units are arbitrary and given poses may be
in millimetres. Every length default of the pipeline (depth ranges, voxels, tolerances) is written
for a room seen from a couple of metres, so such a scene is brought to a *normalised* frame whose
median scene depth is a fixed `target` (scale-equivariant by construction: rescaling the input by
any factor gives the same normalised scene). The median is over the z-depths of triangulated points
in the views that observe them: the SfM model's tracks, or, for given poses without a model, SIFT
matches triangulated with those poses (`triangulate_given`).

* `normalising_scale`: target / median depth.
* `triangulate_given`: per-view z-depths of points triangulated from matches between view pairs.
* `neighbour_pairs`: pairs of views worth matching when the poses are known.
* `path_jumps`: steps of an ordered camera path that are far longer than its median step.
* `numbered_sequence`, `holdout_names`: capture order and the LLFF/NeRF held-out split.
"""
from __future__ import annotations

import re
from typing import Sequence

import numpy as np

from ..scene import Camera


def normalising_scale(depths: np.ndarray, target: float) -> float:
    """Factor that maps the median of positive, finite `depths` to `target`."""
    d = np.asarray(depths, np.float64).reshape(-1)
    d = d[np.isfinite(d) & (d > 0)]
    if len(d) < 10:
        raise ValueError(f"only {len(d)} positive depths: too few to measure the scene scale")
    if not target > 0:
        raise ValueError(f"target depth must be positive, got {target}")
    return float(target / np.median(d))


def depth_range(depths: np.ndarray, lo_pct: float = 2.0, hi_pct: float = 98.0,
                widen: tuple[float, float] = (0.7, 1.4)) -> tuple[float, float] | None:
    """A per-view depth search range: the `lo_pct`..`hi_pct` percentiles of its point depths,
    widened by the factors `widen` (None with fewer than 10 points)."""
    d = np.asarray(depths, np.float64).reshape(-1)
    d = d[np.isfinite(d) & (d > 0)]
    if len(d) < 10:
        return None
    return float(np.percentile(d, lo_pct) * widen[0]), float(np.percentile(d, hi_pct) * widen[1])


def neighbour_pairs(cams: dict[str, Camera], k: int = 2, max_angle_deg: float = 45.0
                    ) -> list[tuple[str, str]]:
    """For every view, its `k` nearest views (camera centres) among those looking within
    `max_angle_deg` of its own direction; each unordered pair once."""
    names = list(cams)
    if len(names) < 2:
        return []
    C = np.array([cams[n].center for n in names])
    Z = np.array([cams[n].R[2] for n in names])  # optical axes in world coordinates
    dist = np.linalg.norm(C[:, None] - C[None], axis=-1)
    cos = Z @ Z.T
    dist[cos < np.cos(np.radians(max_angle_deg))] = np.inf
    np.fill_diagonal(dist, np.inf)
    pairs = set()
    for i in range(len(names)):
        for j in np.argsort(dist[i])[:k]:
            if np.isfinite(dist[i, j]):
                pairs.add((min(i, j), max(i, j)))
    return [(names[i], names[j]) for i, j in sorted(pairs)]


def _gray8(image: np.ndarray) -> np.ndarray:
    a = np.asarray(image)
    if a.ndim == 3:
        a = a[..., :3].mean(-1)
    if a.ndim != 2:
        raise ValueError(f"image must be (H, W) or (H, W, C), got {np.asarray(image).shape}")
    return np.clip(a * 255.0 if a.dtype.kind == "f" else a, 0, 255).astype(np.uint8)


def triangulate_given(images: dict[str, np.ndarray], cams: dict[str, Camera],
                      pairs: Sequence[tuple[str, str]], max_features: int = 4000, ratio: float = 0.8,
                      max_reproj_px: float = 2.0, min_angle_deg: float = 1.0
                      ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """{view: ((N, 2) keypoint pixels, (N,) z-depths) of the points triangulated in it} from
    SIFT matches between `pairs` of
    views with known poses (Lowe ratio test, then linear triangulation kept when it reprojects
    within `max_reproj_px` in both views, lies in front of both and the rays meet at more than
    `min_angle_deg`). OpenCV's SIFT, not pycolmap's: only matches are needed, no database."""
    import cv2

    sift = cv2.SIFT_create(nfeatures=max_features)
    feats = {}
    # the views in order of first appearance in `pairs`, not a set's order: a set of strings
    # iterates in an order that changes with PYTHONHASHSEED, and the mean of the camera centres
    # below (hence `unit`, the triangulated depths and the normalised scene frame) changed in the
    # last bits from one process to the next
    for n in dict.fromkeys(x for p in pairs for x in p):
        if n not in images or n not in cams:
            raise ValueError(f"pair names view {n!r}, which has no image or camera")
        kp, desc = sift.detectAndCompute(_gray8(images[n]), None)
        feats[n] = (np.array([k.pt for k in kp], np.float64).reshape(-1, 2), desc)
    # triangulate in a frame where the cameras are about a unit apart: the result is then the same
    # (to rounding) whatever units the poses come in, and so are the points kept by the tests
    C = np.array([cams[n].center for n in feats])
    unit = float(np.median(np.linalg.norm(C - C.mean(0), axis=1))) or 1.0
    from .align import transform_camera
    cams = {n: transform_camera(cams[n], 1.0 / unit, np.eye(3), np.zeros(3)) for n in feats}
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    out: dict[str, list] = {n: [] for n in cams}
    for a, b in pairs:
        (pa, da), (pb, db) = feats[a], feats[b]
        if da is None or db is None or len(da) < 2 or len(db) < 2:
            continue
        good = [m[0] for m in matcher.knnMatch(da, db, k=2)
                if len(m) == 2 and m[0].distance < ratio * m[1].distance]
        if len(good) < 8:
            continue
        ua = pa[[m.queryIdx for m in good]]
        ub = pb[[m.trainIdx for m in good]]
        ca, cb = cams[a], cams[b]
        Pa, Pb = ca.K @ ca.cam_from_world[:3], cb.K @ cb.cam_from_world[:3]
        X = cv2.triangulatePoints(Pa, Pb, ua.T, ub.T)
        X = (X[:3] / np.where(np.abs(X[3]) > 1e-12, X[3], 1e-12)).T
        ok = np.ones(len(X), bool)
        zs = []
        for cam, uv in ((ca, ua), (cb, ub)):
            xc = X @ cam.R.T + cam.t
            z = xc[:, 2]
            proj = xc @ cam.K.T
            err = np.linalg.norm(proj[:, :2] / np.where(z > 0, z, 1.0)[:, None] - uv, axis=1)
            ok &= (z > 0) & (err < max_reproj_px)
            zs.append(z)
        ra = X - ca.center
        rb = X - cb.center
        cosang = np.sum(ra * rb, 1) / np.maximum(np.linalg.norm(ra, axis=1) * np.linalg.norm(rb, axis=1), 1e-12)
        ok &= cosang < np.cos(np.radians(min_angle_deg))
        out[a].append((ua[ok], zs[0][ok] * unit))
        out[b].append((ub[ok], zs[1][ok] * unit))
    return {n: (np.concatenate([u for u, _ in v]).reshape(-1, 2) if v else np.zeros((0, 2)),
                np.concatenate([z for _, z in v]) if v else np.zeros(0)) for n, v in out.items()}


def path_jumps(centres: np.ndarray, factor: float) -> list[tuple[int, float]]:
    """[(i, step / median step)] for the steps i -> i+1 of an ordered camera path longer than
    `factor` times the median step (an SfM that mixed up repetitive structure jumps back and forth)."""
    C = np.asarray(centres, np.float64)
    if C.ndim != 2 or C.shape[1] != 3:
        raise ValueError(f"centres must be (N, 3), got {C.shape}")
    if len(C) < 4:
        return []
    steps = np.linalg.norm(np.diff(C, axis=0), axis=1)
    med = float(np.median(steps))
    if med <= 0:
        return []
    return [(int(i), float(steps[i] / med)) for i in np.flatnonzero(steps > factor * med)]


_NUMBER = re.compile(r"^(.*?)(\d+)(\.[^.]+)$")


def numbered_sequence(names: Sequence[str]) -> bool:
    """Whether image names look like frames of one ordered capture: a common prefix and suffix
    around an increasing frame number (frame_0001.jpg, IMG_4026.JPG, ...), at most a few numbers
    missing between neighbours."""
    if len(names) < 3:
        return False
    parts = [_NUMBER.match(n) for n in names]
    if not all(parts) or len({(m.group(1), m.group(3).lower()) for m in parts}) != 1:
        return False
    nums = [int(m.group(2)) for m in parts]
    steps = np.diff(nums)
    return bool(np.all(steps > 0) and np.median(steps) <= 10)


def holdout_names(names: Sequence[str], every: int) -> list[str]:
    """The LLFF/NeRF test split: images 0, every, 2*every, ... of the capture in name order."""
    if every < 0:
        raise ValueError(f"every must be >= 0, got {every}")
    return [] if every == 0 else list(names)[::every]
