"""Detecting planar reflectors from a multi-view consistency cue (Xu et al. §4.3, "we detect
reflective planes for each input image using a multi-view consistency cue").

Candidates are the planar pieces of the global mesh G (`planes.ransac_planes`). For a candidate
seen by view k, the pixels on it are warped from the nearest views twice: with the surface depth
(w(u, M0)) and with the mirrored geometry (w(u, M1)). A diffuse plane is explained by the surface
warp (small photometric error); a reflector is not, because its reflection moves with the mirrored
scene. The score of a candidate is the median over views of the median absolute surface-warp error
on its pixels; `mirror_ratio` (mirror-warp error / surface-warp error) tells a mirror (reflection
only, ratio << 1) from a glossy surface (texture + reflection, ratio >= 1).
"""
from __future__ import annotations

import numpy as np

from .decompose import ViewGeom, _sample_np, depth_consistent, pose_distance, project


def warp_errors(ref: ViewGeom, nb: ViewGeom, tol: float = 0.05) -> tuple[float, float, int]:
    """(median |I_k - I_k'(w(u, M0))|, median |I_k - I_k'(w(u, M1))|, pixel count) over the
    reference's mask pixels visible in nb under both warps."""
    sel = ref.mask & (ref.D1 > 0)
    if not sel.any():
        return np.nan, np.nan, 0
    p0, z0 = project(nb.camera, ref.X0)
    p1, z1 = project(nb.camera, ref.X1)
    v0 = depth_consistent(nb.depth, p0, z0, tol) & sel
    v1 = depth_consistent(np.where(nb.mask, nb.D1, 0.0), p1, z1, tol) & sel
    both = v0 & v1
    n = int(both.sum())
    if n < 20:
        return np.nan, np.nan, n
    e0 = np.abs(_sample_np(nb.image, p0) - ref.image).mean(2)[both]
    e1 = np.abs(_sample_np(nb.image, p1) - ref.image).mean(2)[both]
    return float(np.median(e0)), float(np.median(e1)), n


def score_candidate(views: list[ViewGeom], neighbours: int = 2, tol: float = 0.05) -> dict:
    """Multi-view consistency score of one candidate plane over the views that see it."""
    s0, s1, counts = [], [], 0
    for v in views:
        if v.mask.sum() < 50:
            continue
        others = sorted((o for o in views if o is not v and o.mask.sum() >= 50),
                        key=lambda o: pose_distance(v.camera, o.camera))[:neighbours]
        for o in others:
            e0, e1, n = warp_errors(v, o, tol)
            if n:
                s0.append(e0)
                s1.append(e1)
                counts += 1
    if not s0 or np.all(np.isnan(s0)):
        return {"surface_error": None, "mirror_error": None, "mirror_ratio": None, "pairs": counts}
    e0, e1 = float(np.nanmedian(s0)), float(np.nanmedian(s1))
    return {"surface_error": e0, "mirror_error": e1, "mirror_ratio": e1 / max(e0, 1e-6),
            "pairs": counts}


def is_reflective(score: dict, threshold: float, min_pairs: int = 1) -> bool:
    """A plane whose surface warp leaves a median error above `threshold` over at least
    `min_pairs` view pairs is a reflector (one or two pairs are too weak: a wall at the edge of two
    views with depth errors scored like a reflector on the real workspace)."""
    return (score.get("surface_error") is not None and score["surface_error"] > threshold
            and score.get("pairs", 0) >= min_pairs)
