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

from .decompose_terms import (_nearest, all_last, depth_consistent, nanmedian0, project,
                              sample_bilinear)
from .planes import mirror_matrix
from .prior_nb import seen_colours


SAMPLE = 2000  # reflected points that rank the views (deterministic stride)


def reflected_points(X1: np.ndarray, plane) -> tuple[np.ndarray, np.ndarray]:
    """The real points Xr = mirror(X1) (N, 3) of the finite mirror-world points of X1 (..., 3),
    and where those are in X1's flattened order (N,) indices."""
    flat = np.asarray(X1, np.float64).reshape(-1, 3)
    idx = np.flatnonzero(all_last(np.isfinite(flat)))
    M = mirror_matrix(plane)
    return flat[idx] @ M[:3, :3].T + M[:3, 3], idx


def sample_points(points: np.ndarray, n: int = SAMPLE) -> np.ndarray:
    """At most n of the (N, 3) points, evenly strided (deterministic)."""
    step = max(1, -(-len(points) // n))
    return points[::step]


def views_in_frustum(points: np.ndarray, cameras) -> list[int]:
    """Indices of the cameras in front of which at least one of the (N, 3) points projects
    inside the image: the only views that can see them (the colour prior's candidates)."""
    P = np.asarray(points, np.float64).reshape(-1, 3)
    if not len(cameras) or not len(P):
        return []
    R = np.array([c.R for c in cameras], np.float64)
    t = np.array([c.t for c in cameras], np.float64)
    K = np.array([c.K for c in cameras], np.float64)
    cam = P @ R.transpose(0, 2, 1) + t[:, None]  # all cameras at once: (V, N, 3)
    z = cam[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (cam @ K.transpose(0, 2, 1))[..., :2] / z[..., None]
    w = np.array([c.width for c in cameras], np.float64)[:, None]
    h = np.array([c.height for c in cameras], np.float64)[:, None]
    inside = (z > 0) & (uv[..., 0] > -0.5) & (uv[..., 1] > -0.5) \
        & (uv[..., 0] < w - 0.5) & (uv[..., 1] < h - 0.5)
    return [int(i) for i in np.flatnonzero(inside.any(1))]


def _sees(depth, exclude, pos, z, tol):
    """depth_consistent at `pos`, false where the nearest pixel is on a reflector (the view does
    not see the point directly there): the same as testing against the depth with the
    reflector pixels zeroed, without building that map."""
    return depth_consistent(depth, pos, z, tol) & ~_nearest(exclude, pos, True)[0]


def seen_colours_np(camera, points, depth, exclude, image, tol):
    """The reference of `prior_nb.seen_colours` (same arguments and returns): (N, C) bilinear
    colours of the (N, 3) points where the view sees them directly, NaN elsewhere, and the count."""
    pos, z = project(camera, points)
    vis = _sees(depth, exclude, pos, z, tol)
    # float32 images are interpolated in float64 all the same (numpy promotes the corners)
    s = sample_bilinear(np.asarray(image), np.nan_to_num(pos, nan=-1.0))
    return np.where(vis[:, None], s, np.nan), int(vis.sum())


def reflected_scene_colour(X1: np.ndarray, plane, views, tol: float = 0.03,
                           min_views: int = 1, max_views: int | None = None) -> np.ndarray:
    """X1: (..., 3) mirror-world points (NaN = none); views: sequence of (camera, image (H, W, 3),
    depth (H, W), exclude (H, W) bool = pixels on reflectors). Returns (..., 3) median colour of
    the reflected points over the views that see them directly, NaN where fewer than min_views.

    `max_views`: the median is taken over at most this many views, those that see the largest
    share of a sample of the points (ties in the given order); with no more views than that
    seeing any of the sample it is the median over all of them. This keeps a view's cost
    independent of the number of captured views."""
    X1 = np.asarray(X1, np.float64)
    shp = X1.shape[:-1]
    out = np.full((int(np.prod(shp)), 3), np.nan)
    Xr, idx = reflected_points(X1, plane)
    if not len(Xr):
        return out.reshape(shp + (3,))
    views = list(views)
    if max_views is not None and len(views) > max_views:
        S = sample_points(Xr)
        seen = [seen_colours(cam, S, depth, exclude, img, tol)[1] / len(S)
                for cam, img, depth, exclude in views]
        best = sorted(range(len(views)), key=lambda i: -seen[i])[:max_views]
        keep = [i for i in best if seen[i] > 0] or best
        views = [views[i] for i in sorted(keep)]
    cols = []
    for cam, img, depth, exclude in views:
        col, n = seen_colours(cam, Xr, depth, exclude, img, tol)
        if n:
            cols.append(col)
    if cols:
        st = np.stack(cols)
        n = np.isfinite(st[..., 0]).sum(0)
        med = nanmedian0(st)
        med[n < min_views] = np.nan
        out[idx] = med
    return out.reshape(shp + (3,))
