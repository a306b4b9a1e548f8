"""Detecting planar reflectors from a multi-view consistency cue (Xu et al. §4.3, "we detect
reflective planes for each input image using a multi-view consistency cue").

Candidates are the planar pieces of the global mesh G (`planes.ransac_planes`). For a candidate
seen by view k, the pixels on it are warped from the nearest views twice: with the surface depth
(w(u, M0)) and with the mirrored geometry (w(u, M1)). A diffuse plane is explained by the surface
warp (small photometric error); a reflector is not, because its reflection moves with the mirrored
scene. The score of a candidate is the median over views of the median absolute surface-warp error
on its pixels; `mirror_ratio` (mirror-warp error / surface-warp error) tells a mirror (reflection
only, ratio << 1) from a glossy surface (texture + reflection, ratio >= 1).

A weak reflector (the polished table top, beta 0.15) is not found by that error alone: its
surface-warp error is at the level of diffuse planes (texture resampling). `reflectance_cue` uses
the image formation model (Eq. 3) instead: for a surface point x seen by views k and k', the
surface layer cancels in the difference, I_k(u) - I_k'(w(u, M0)) = beta (C_k(u) - C_k'(w(u, M0))),
where C is the colour of the reflected scene point (mirror(X1), seen directly by other captures:
reflection_prior.py). The least-squares beta and the correlation of the two differences tell a
reflector (beta > 0, correlated) from a diffuse plane (beta ~ 0, uncorrelated), and estimate its
reflectance.

Glass shows the scene behind it: its surface warp fails and its mirror warp need not do better.
The same warp error with the geometry behind the plane on each pixel's ray (the caller passes
ViewGeoms whose X1 / D1 are those points) tells it apart from a plane whose geometry is simply
wrong. `decision` weighs the cues and says why.
"""
from __future__ import annotations

import numpy as np

from .decompose_terms import (ViewGeom, _nearest, all_last, any_last, depth_consistent,
                             nearest_by_pose, project, remap_points)


def warp_errors(ref: ViewGeom, nb: ViewGeom, tol: float = 0.05) -> tuple[float, float, int]:
    """(median |I_k - I_k'(w(u, M0))|, median |I_k - I_k'(w(u, M1))|, pixel count) over the
    reference's mask pixels visible in nb under both warps. Only those pixels are projected: the
    rest of ref.X0 / ref.X1 is not read."""
    sel = ref.mask & (ref.D1 > 0)
    if not sel.any():
        return np.nan, np.nan, 0
    p0, z0 = project(nb.camera, ref.X0[sel])
    p1, z1 = project(nb.camera, ref.X1[sel])
    v0 = depth_consistent(nb.depth, p0, z0, tol)
    v1 = depth_consistent(np.where(nb.mask, nb.D1, 0.0), p1, z1, tol)
    both = v0 & v1
    n = int(both.sum())
    if n < 20:
        return np.nan, np.nan, n
    img = ref.image[sel]
    e0 = np.abs(remap_points(nb.image, p0) - img).mean(1)[both]
    e1 = np.abs(remap_points(nb.image, p1) - img).mean(1)[both]
    return float(np.median(e0)), float(np.median(e1)), n


def score_candidate(views: list[ViewGeom], neighbours: int = 2, tol: float = 0.05) -> dict:
    """Multi-view consistency score of one candidate plane over the views that see it."""
    s0, s1, counts = [], [], 0
    big = [v for v in views if v.mask.sum() >= 50]   # each mask counted once, not once per pair
    near = nearest_by_pose([v.camera for v in big], neighbours)
    for v, nb in zip(big, near):
        for o in (big[j] for j in nb):
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


def decision(score: dict, threshold: float, min_pairs: int, min_beta: float | None,
             min_corr: float, mirror_ratio: float | None = None,
             min_fit_pixels: int = 0) -> tuple[bool, str]:
    """(is a reflector, why) from `score_candidate` (+ `reflectance_cue` as fit_beta, fit_corr).

    A plane scored on fewer than `min_pairs` view pairs is not one (one or two pairs are too weak:
    a wall at the edge of two views with depth errors scored like a reflector). Otherwise it is a
    reflector when (a) the Eq. 3 fit gives beta >= min_beta with correlation >= min_corr
    (`min_beta` None: cue off), or (b) its surface warp leaves a median error above `threshold`
    and, with `mirror_ratio` given, a reflector explains that error: the mirror warp does better
    (mirror/surface error < mirror_ratio), or the warp of the geometry behind the plane does
    (key transmission_ratio: glass). An error that none of these explains is view-inconsistency
    of another kind -- on real captures, wrong geometry at a depth edge or a light fixture -- and
    is reported as such. `mirror_ratio` None: the error alone decides (b). The Eq. 3 fit counts
    only over at least `min_fit_pixels` pixels (key fit_pixels) on a candidate that covers at
    least as many pixels of one view (key mask_pixels, its largest mask): a correlation over a
    few dozen pixels, or summed over many pairs of slivers, is noise."""
    pairs = score.get("pairs", 0) or 0
    if pairs < min_pairs:
        return False, f"scored on {pairs} view pair(s), {min_pairs} needed"
    e, r = score.get("surface_error"), score.get("mirror_ratio")
    b, c = score.get("fit_beta"), score.get("fit_corr")
    npx = score.get("fit_pixels") or 0
    mpx = score.get("mask_pixels")
    has_fit = min_beta is not None and b is not None and c is not None
    few = has_fit and (npx < min_fit_pixels or (mpx is not None and mpx < min_fit_pixels))
    fitted = has_fit and not few and b >= min_beta and c >= min_corr
    err = "no surface-warp error" if e is None else f"surface-warp error {e:.4f}"
    if fitted:
        return True, (f"Eq. 3 fit beta {b:.3f} >= {min_beta:g} with correlation {c:.2f} >= "
                      f"{min_corr:g} ({pairs} view pairs; {err})")
    fit = ("" if min_beta is None else "; no Eq. 3 fit" if b is None or c is None
           else (f"; Eq. 3 fit over {npx} pixels"
                 + ("" if mpx is None else f" of a candidate of at most {mpx} per view")
                 + f", {min_fit_pixels} needed") if few
           else f"; Eq. 3 fit beta {b:.3f} / correlation {c:.2f} below {min_beta:g} / {min_corr:g}")
    if e is None or e <= threshold:
        return False, (f"{err} <= {threshold:g}" if e is not None else err) + fit
    if mirror_ratio is None:
        return True, f"{err} > {threshold:g} on {pairs} view pairs"
    if r is not None and r < mirror_ratio:
        return True, (f"{err} > {threshold:g} on {pairs} view pairs, explained by the mirror warp "
                      f"(mirror/surface error {r:.2f} < {mirror_ratio:g})")
    t = score.get("transmission_ratio")
    if t is not None and t < mirror_ratio:
        return True, (f"{err} > {threshold:g} on {pairs} view pairs, explained by the scene seen "
                      f"through the plane (transmission/surface error {t:.2f} < {mirror_ratio:g}): "
                      "glass")
    ratio = "no mirror warp" if r is None else f"mirror/surface error {r:.2f} >= {mirror_ratio:g}"
    if t is not None:
        ratio += f", transmission/surface error {t:.2f} >= {mirror_ratio:g}"
    return False, f"{err} > {threshold:g} but no reflection explains it ({ratio}{fit})"


def reflectance_cue(views: list[ViewGeom], colours: dict, neighbours: int = 2, tol: float = 0.05,
                    saturation: float = 0.98) -> dict:
    """Fit Eq. 3's beta from view differences (module docstring). colours: view name -> (H, W, 3)
    reflected-scene colour C (NaN where unknown). Returns {beta, corr, pixels}: least-squares
    beta = <dI, dC> / <dC, dC> and the correlation of dI and dC over all pairs and channels."""
    dI, dC = [], []
    big = [v for v in views if colours.get(v.name) is not None and v.mask.sum() >= 50]  # once
    for v, nb in zip(big, nearest_by_pose([v.camera for v in big], neighbours)):
        Cv = colours[v.name]
        sel = v.mask & (v.D1 > 0)
        sel[sel] = all_last(np.isfinite(Cv[sel])) & ~any_last(v.image[sel] >= saturation)
        others = [big[j] for j in nb]
        X0, Iv, Cs = v.X0[sel], v.image[sel], Cv[sel]  # the selected pixels only, in raster order
        for o in others:
            p0, z0 = project(o.camera, X0)
            ok = depth_consistent(o.depth, p0, z0, tol) & _nearest(o.mask, p0, False)[0]
            Co = _nearest(colours[o.name], p0, np.nan)[0]
            Io = remap_points(o.image, p0)
            ok &= all_last(np.isfinite(Co)) & ~any_last(Io >= saturation)
            if ok.sum() < 20:
                continue
            dI.append((Iv - Io)[ok].reshape(-1))
            dC.append((Cs - Co)[ok].reshape(-1))
    if not dI:
        return {"beta": None, "corr": None, "pixels": 0}
    dI, dC = np.concatenate(dI), np.concatenate(dC)

    def dot(a, b):  # numpy's pairwise sum, not BLAS: the same bits whatever the thread count
        return float(np.sum(a * b))
    cc = dot(dC, dC)
    if cc < 1e-9:
        return {"beta": None, "corr": None, "pixels": len(dI) // 3}
    ic = dot(dI, dC)
    corr = ic / float(np.sqrt(max(dot(dI, dI), 1e-30) * cc))
    return {"beta": ic / cc, "corr": corr, "pixels": len(dI) // 3}
