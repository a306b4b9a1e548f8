"""Reflector candidates no single view sees whole: holes in a plane, pooled over the views.

`behind_detect.behind_outlines` needs one view that sees the whole region behind a plane and a
ring of the plane around it. A mirror that fills a close view, or that every view cuts with its
frame, has no such view, so its mirror world stays in G. Here every view adds its evidence to
one grid on the plane instead: where its rays meet the plane and find depth on it (or up to
`behind` in front of it: a frame, a bezel), the cell is surface; where they find depth well
behind it, the cell is seen through it. A region seen through the plane and enclosed, on the
pooled grid, by surface is a hole through it, whichever views saw which part (issue #26's "the
planar boundary itself", in the pane's plane). A doorway or a gap between ceiling panels is a
hole as well; like `behind_detect`'s candidates, these are verified with the multi-view mirror
cue afterwards (`behind_detect.verify_candidate`).
"""
from __future__ import annotations

import numpy as np

from ..scene import Camera
from .planes import plane_basis, same_plane


def view_samples(cams: dict[str, Camera], depths: dict, samples: int = 20000) -> dict:
    """Each view's depth on a regular lattice of about `samples` pixels, as rays: name ->
    (camera centre (3,), world directions (N, 3) scaled to camera z = 1, z-depth (N,)); pixels
    without depth are left out. depths: name -> (h, w) z-depth (0 = none), cams at any size."""
    from .raycast import pixel_directions
    out = {}
    for n, d in depths.items():
        d = np.asarray(d)
        if d.ndim != 2:
            raise ValueError(f"depth of {n} must be (h, w), got {d.shape}")
        h, w = d.shape
        step = max(1, int(round(np.sqrt(h * w / samples))))
        vs, us = np.mgrid[0:h:step, 0:w:step].reshape(2, -1)
        z = d[vs, us].astype(np.float64)
        has = (z > 0) & np.isfinite(z)
        cam = cams[n].resized(w, h)
        out[n] = (cam.center, pixel_directions(cam, np.c_[us[has], vs[has]].astype(np.float64)),
                  z[has])
    return out


def pooled_grid(plane, samples: dict, cell: float, *, behind: float, on_plane: float = 0.02,
                max_cells: int = 4_000_000
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple, dict]:
    """Counts of surface and seen-through samples per `cell`-sized square of `plane` (4,),
    over every view's `samples` (`view_samples`). A ray meets the plane at X with z-depth zp;
    its measured depth d is surface when -`behind` < d / zp - 1 < `on_plane`, seen through when
    d / zp - 1 > `behind`. A plane whose extent would take more than `max_cells` cells (a floor
    seen to the horizon) gets larger cells. Returns (surface (H, W), through (H, W) counts, the
    sum of d / zp - 1 of the through samples (H, W), (origin, u, v, u0, v0, cell) to map cells
    back to the plane, {view: cells (K,) flat indices it saw through the plane})."""
    p = np.asarray(plane, np.float64)
    if p.shape != (4,):
        raise ValueError(f"plane must be (4,), got {p.shape}")
    origin, u, v = plane_basis(p)
    per_view = {}
    for n, (c, dirs, d) in samples.items():
        with np.errstate(divide="ignore", invalid="ignore"):
            zp = -(c @ p[:3] + p[3]) / (dirs @ p[:3])      # the ray parameter is a z-depth
        ok = np.isfinite(zp) & (zp > 0)
        if not ok.any():
            continue
        rel = d[ok] / zp[ok] - 1.0
        surf, thru = (rel > -behind) & (rel < on_plane), rel > behind
        P = c - origin + zp[ok, None] * dirs[ok]
        ab = np.c_[P @ u, P @ v]
        per_view[n] = (ab[surf], ab[thru], rel[thru])
    empty = np.zeros((0, 0), np.float64)
    surf_ab = [s for s, _, _ in per_view.values() if len(s)]
    if not surf_ab:
        return empty, empty, empty, (origin, u, v, 0, 0, cell), {}
    surf_ab = np.concatenate(surf_ab)
    # a hole lies inside the plane's own extent; its outermost 0.1 % are strays (a ray grazing
    # another surface where it crosses the plane's line), which would stretch the grid
    lo_ab, hi_ab = np.percentile(surf_ab, [0.05, 99.95], axis=0)
    cell = max(cell, float(np.sqrt(np.prod(hi_ab - lo_ab + 1e-12) / max_cells)))
    lo = np.floor(lo_ab / cell).astype(np.int64)
    hi = np.floor(hi_ab / cell).astype(np.int64)
    cells = lambda ab: np.floor(ab / cell).astype(np.int64)  # noqa: E731
    surf_q = cells(surf_ab)
    surf_q = surf_q[np.all((surf_q >= lo) & (surf_q <= hi), axis=1)]
    H, W = int(hi[1] - lo[1] + 1), int(hi[0] - lo[0] + 1)
    flat = lambda q: (q[:, 1] - lo[1]) * W + (q[:, 0] - lo[0])  # noqa: E731
    surface = np.bincount(flat(surf_q), minlength=H * W).astype(np.float64)
    through, rel_sum = np.zeros(H * W), np.zeros(H * W)
    seen = {}
    for n, (_, t, r) in per_view.items():
        t = cells(t)
        inside = np.all((t >= lo) & (t <= hi), axis=1)
        idx = flat(t[inside])
        through += np.bincount(idx, minlength=H * W)
        rel_sum += np.bincount(idx, r[inside], minlength=H * W)
        seen[n] = np.unique(idx)
    return (surface.reshape(H, W), through.reshape(H, W), rel_sum.reshape(H, W),
            (origin, u, v, int(lo[0]), int(lo[1]), cell), seen)


def grid_holes(surface: np.ndarray, through: np.ndarray, *, enclosed: float, min_cells: int = 30,
               ring: int = 2, min_ring_seen: float = 0.3
               ) -> list[dict]:
    """Regions of a pooled grid seen through the plane (more through- than surface samples),
    closed by one cell, of at least `min_cells` cells, not touching the grid's edge (the
    plane's extent: beyond it nothing encloses them), whose ring (`ring` cells wide) is
    observed on at least `min_ring_seen` of its cells and is surface on at least `enclosed` of
    the observed ones. Returns per hole: mask (H, W) bool, cells, enclosed."""
    import cv2
    surface, through = np.asarray(surface), np.asarray(through)
    if surface.shape != through.shape or surface.ndim != 2:
        raise ValueError(f"surface {surface.shape} and through {through.shape} must be one (H, W)")
    if surface.size == 0:
        return []
    # each view samples the plane unevenly (a lattice of its pixels, foreshortened): counts over
    # 3x3 cells, so that a cell no ray happened to land in takes its neighbours' evidence
    surface = cv2.boxFilter(surface.astype(np.float32), -1, (3, 3), normalize=False)
    through = cv2.boxFilter(through.astype(np.float32), -1, (3, 3), normalize=False)
    observed = (surface + through) > 0
    is_through = (through > surface).astype(np.uint8)
    k3 = cv2.getStructuringElement(cv2.MORPH_RECT, (3, 3))
    is_through = cv2.morphologyEx(is_through, cv2.MORPH_CLOSE, k3)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(is_through, connectivity=8)
    kr = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * ring + 1,) * 2)
    H, W = labels.shape
    out = []
    for i in range(1, n):
        x, y, w, h, area = stats[i]
        if area < min_cells or x == 0 or y == 0 or x + w == W or y + h == H:
            continue                                # too small, or on the plane's extent edge
        # the component and its ring lie in its box widened by the ring: work there, not on
        # the whole grid (a plane's grid can hold millions of cells and hundreds of specks)
        box = (slice(max(0, y - ring), y + h + ring), slice(max(0, x - ring), x + w + ring))
        m = labels[box] == i
        around = (cv2.dilate(m.astype(np.uint8), kr) > 0) & ~m
        seen = around & observed[box]
        if seen.sum() < min_ring_seen * max(around.sum(), 1):
            continue
        enc = float(((surface[box] >= through[box]) & seen).sum() / max(seen.sum(), 1))
        if enc >= enclosed:
            mask = np.zeros((H, W), bool)
            mask[box] = m
            out.append({"mask": mask, "cells": int(area), "enclosed": enc})
    return out


def find_plane_holes(cams: dict[str, Camera], depths: dict, view_planes_of: dict, *,
                     behind: float, enclosed: float, cell: float = 0.01,
                     min_cells: int = 30) -> list[dict]:
    """Holes through the planes of a capture's depth maps, pooled over all views. Each view's
    largest planes (`view_planes_of`: name -> planes (4,), `behind_detect.view_planes`) are
    merged across views (`planes.same_plane`, within 2 % of the median depth); each plane found in 2
    views gets a pooled grid of `cell` x the median depth (`pooled_grid`, `behind`) and its
    holes (`grid_holes`, `enclosed`). Returns per hole, largest first: plane (4,), polygon
    (K, 3) (convex hull of its cells on the plane), views (those that saw through at least 5 %
    of it), view (the one that saw most of it), cells, enclosed, behind (median over its cells
    of the mean relative depth behind the plane)."""
    import cv2
    depths = {n: np.asarray(d) for n, d in depths.items()}
    coarse = [d[::4, ::4] for d in depths.values()]  # the scale, not a measurement: a subsample
    med = float(np.median([np.median(d[d > 0]) for d in coarse if (d > 0).any()] or [1.0]))
    planes: list[tuple[np.ndarray, set]] = []
    for n in depths:
        for pl in view_planes_of.get(n, ()):
            for p, views in planes:
                if same_plane(p, pl, offset=0.02 * med):
                    views.add(n)
                    break
            else:
                planes.append((np.asarray(pl, np.float64), {n}))
    out, lattice = [], view_samples(cams, depths)
    for pl, views in planes:
        if len(views) < 2:
            continue
        surface, through, rel_sum, (origin, u, v, u0, v0, size), seen = pooled_grid(
            pl, lattice, cell * med, behind=behind)
        for h in grid_holes(surface, through, min_cells=min_cells, enclosed=enclosed):
            flat = np.flatnonzero(h["mask"].ravel())
            share = {n: np.isin(idx, flat, assume_unique=True).sum() / len(flat)
                     for n, idx in seen.items()}
            saw = sorted(n for n, f in share.items() if f >= 0.05)
            if len(saw) < 2:
                continue
            ys, xs = np.nonzero(h["mask"])
            pts = np.c_[np.r_[xs, xs + 1, xs, xs + 1], np.r_[ys, ys, ys + 1, ys + 1]]
            hull = cv2.convexHull(pts.astype(np.float32)).reshape(-1, 2).astype(np.float64)
            a, b = (hull[:, 0] + u0) * size, (hull[:, 1] + v0) * size
            m = h["mask"] & (through > 0)
            out.append({"plane": pl, "polygon": origin + a[:, None] * u + b[:, None] * v,
                        "views": saw, "view": max(saw, key=share.get), "cells": h["cells"],
                        "enclosed": h["enclosed"],
                        "behind": float(np.median(rel_sum[m] / through[m]))})
    return sorted(out, key=lambda h: -h["cells"])
