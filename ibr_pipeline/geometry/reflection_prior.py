"""Reflected-scene colour prior for the reflection layer (an addition to Xu et al. §4.3.1).

M1 is the scene mirrored through the reflector plane, so every reflection pixel u with a
mirror-world point X1(u) looks at the real point Xr = mirror(X1(u)) of G. Where other captures see
Xr directly (depth-consistent, not through a reflector) their colours give the radiance that
the reflector reflects: I1(u) ~ median_j I_j(project_j(Xr)) (view-independent shading assumed).
The stage uses beta * that colour as the initial R = beta I1 and as a weak data prior of the image
step (weight `lambda_scene`); pixels whose reflected point is not observed keep the Eq. 6 init.
"""
from __future__ import annotations

import numpy as np

from .decompose_terms import sample_bilinear, depth_consistent, project
from .planes import mirror_matrix


def reflected_scene_colour(X1: np.ndarray, plane, views, tol: float = 0.03,
                           min_views: int = 1) -> np.ndarray:
    """X1: (..., 3) mirror-world points (NaN = none); views: iterable of (camera, image (H, W, 3),
    depth (H, W), exclude (H, W) bool = pixels on reflectors). Returns (..., 3) median colour of
    the reflected points over the views that see them directly, NaN where fewer than min_views."""
    X1 = np.asarray(X1, np.float64)
    shp = X1.shape[:-1]
    flat = X1.reshape(-1, 3)
    ok_pts = np.all(np.isfinite(flat), axis=1)
    out = np.full((len(flat), 3), np.nan)
    if not ok_pts.any():
        return out.reshape(shp + (3,))
    M = mirror_matrix(plane)
    Xr = flat[ok_pts] @ M[:3, :3].T + M[:3, 3]
    cols = []
    for cam, img, depth, exclude in views:
        pos, z = project(cam, Xr)
        vis = depth_consistent(np.where(exclude, 0.0, depth), pos, z, tol)
        if not vis.any():
            continue
        s = sample_bilinear(np.asarray(img, np.float64), np.nan_to_num(pos, nan=-1.0))
        cols.append(np.where(vis[:, None], s, np.nan))
    if cols:
        st = np.stack(cols)
        n = np.isfinite(st[..., 0]).sum(0)
        with np.errstate(all="ignore"):
            import warnings
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                med = np.nanmedian(st, axis=0)
        med[n < min_views] = np.nan
        out[ok_pts] = med
    return out.reshape(shp + (3,))
