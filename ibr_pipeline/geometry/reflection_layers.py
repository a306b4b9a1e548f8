"""One view's layers from its per-reflector decompositions (Xu et al. §4.3): what the
`reflection` stage writes, as library code (the stage reads, calls and writes).

`decompose_view` runs `decompose_reflector` for every reflector the view sees; `compose_layers`
combines the results into the Eq. 3 layers I0, I1, beta at image size, the mirror-world mesh M1
(Eq. 7's optimised depths, one grid mesh per reflector, simplified like the view mesh) and M0's
optimised vertex offsets.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .reflection_views import Loader, ReflectionConfig, decompose_reflector, simplify_m1

_INTERNAL = ("R", "mask", "geom", "m1_offset", "m0_offset")  # arrays, not for layers.json


@dataclass
class ViewLayers:
    """I = I0 + beta I1 (Eq. 3) at image size, M1 in world space, M0's vertices (None: as
    view_mesh wrote them)."""

    I0: np.ndarray      # (H, W, 3) float
    I1: np.ndarray      # (H, W, 3) float
    beta: np.ndarray    # (H, W) float32 in [0, 1]
    m1_vertices: np.ndarray
    m1_faces: np.ndarray
    m0_vertices: np.ndarray | None


def visible_from(tg, kg, tol: float):
    """Which of view t's reflector pixels view k can predict: sel = t's mask with M1; a, b = t's
    surface and mirror-world points of sel projected into k; ok = both depth-consistent in k
    (the mirror-world point against k's own M1) and a inside k's mask."""
    from .decompose_terms import _nearest, depth_consistent, project
    sel = tg.mask & (tg.D1 > 0)
    a, za = project(kg.camera, tg.X0[sel])
    b, zb = project(kg.camera, tg.X1[sel])
    ok = depth_consistent(kg.depth, a, za, tol) & _nearest(kg.mask, a, False)[0]
    ok &= depth_consistent(np.where(kg.mask, kg.D1, 0.0), b, zb, tol)
    return sel, a, b, ok


def predict_views(loader: Loader, view: str, refl: dict, r: dict, cfg: ReflectionConfig) -> dict:
    """How well `view`'s decomposition `r` of reflector `refl` predicts other captures' pixels
    on the reflector, against the unsplit photo (Xu et al. §7 discard decompositions that fail;
    here that is measured). For up to cfg.accept_views views t that see the reflector, nearest
    first and not among the decomposition's neighbours (their photos fitted the layers), t's
    surface points a and mirror-world points b are projected into `view` (both depth-tested,
    as the renderer's fuzzy test would): two layers predict I0(a) + R(b) (Eq. 3 at t), one layer
    I(a). When every view that sees the reflector was a neighbour, the nearest neighbours are
    used (`source` says which). Returns {views, source, pixels, two_layer, single_layer}: mean
    absolute errors over the predicted pixels (None without 50 of them)."""
    from .decompose import by_pose_distance
    from .decompose_terms import sample_bilinear
    kg, R = r["geom"], np.clip(np.minimum(r["R"], r["geom"].image), 0, None)
    I0 = kg.image - R
    used = {n["view"] for n in r["neighbours"]}
    held, near = [], []  # nearest first; masks only (cheap) until enough held-out views
    for t in by_pose_distance(loader.cams[view], [n for n in loader.names if n != view],
                              loader.cams):
        if loader.mask(t, refl).sum() >= cfg.min_mask_pixels:
            (near if t in used else held).append(t)
            if len(held) == cfg.accept_views:
                break
    views, source = held, "held-out views"
    if not views:
        views, source = near[:cfg.accept_views], "decomposition neighbours"
    e2 = e1 = 0.0
    n, named = 0, []
    for t in views:
        tg = loader.geom(t, refl)
        sel, a, b, ok = visible_from(tg, kg, cfg.decompose.overlap_tol)
        if ok.sum() < 50:
            continue
        target = tg.image[sel][ok]
        two = sample_bilinear(I0, a[ok]) + sample_bilinear(R, b[ok])
        one = sample_bilinear(kg.image, a[ok])
        e2 += float(np.abs(two - target).mean(1).sum())
        e1 += float(np.abs(one - target).mean(1).sum())
        n += int(ok.sum())
        named.append(t)
    if n < 50:
        return {"views": named, "source": source, "pixels": n, "two_layer": None,
                "single_layer": None}
    return {"views": named, "source": source, "pixels": n, "two_layer": round(e2 / n, 6),
            "single_layer": round(e1 / n, 6)}


def decompose_view(loader: Loader, view: str, reflectors: list[dict],
                   cfg: ReflectionConfig) -> tuple[list[dict], dict]:
    """(kept decompositions, layers.json report) of `view` for every reflector whose mask in it
    has at least cfg.min_mask_pixels pixels; discarded ones are named in the report, with the
    reason: too few neighbours, or (cfg.accept_test) two layers that predict other captures of
    the reflector worse than the unsplit photo does (`predict_views`): that reflector is then
    single layer in this view."""
    _, _, wc, _, _ = loader.raw(view)
    results, skipped = [], []
    for refl in reflectors:
        if int(loader.mask(view, refl).sum()) < cfg.min_mask_pixels:
            continue
        r = decompose_reflector(loader, view, refl, cfg.decompose)
        if "discarded" not in r and cfg.accept_test:
            v = r["validation"] = predict_views(loader, view, refl, r, cfg)
            if v["two_layer"] is not None and v["two_layer"] >= v["single_layer"]:
                r["discarded"] = (f"two layers predict {', '.join(v['views'])} worse than the photo "
                                  f"alone ({v['two_layer']:.4f} vs {v['single_layer']:.4f} mean "
                                  f"absolute error, {v['source']})")
        (skipped if "discarded" in r else results).append(r)
    report = {"reflector": None, "reflectors": [], "discarded": [
        {k: v for k, v in r.items()
         if k in ("name", "discarded", "neighbours", "mask_pixels", "validation")}
        for r in skipped], "work_size": [wc.width, wc.height]}
    if results:
        report["reflector"] = max(results, key=lambda r: r["mask_pixels"])["name"]
    return results, report


def compose_layers(results: list[dict], img: np.ndarray, wc, m0_vertices: np.ndarray,
                   cfg: ReflectionConfig) -> ViewLayers:
    """Combine one view's decompositions (`decompose_view`, at least one) into its layers.
    img: (H, W, 3) the photograph; wc: the working camera; m0_vertices: the view mesh's vertices.
    Larger masks are written last (they win where reflectors overlap)."""
    import cv2

    from .geometry_step import optimised_m0, optimised_m1
    from .planes import grid_mesh
    if not results:
        raise ValueError("compose_layers needs at least one decomposition")
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"img must be (H, W, 3), got {img.shape}")
    H, W = img.shape[:2]
    beta_w = np.zeros((wc.height, wc.width))
    R_w = np.zeros((wc.height, wc.width, 3))
    verts, faces, off = [], [], 0
    for r in sorted(results, key=lambda r: r["mask_pixels"]):
        m = r["mask"]
        beta_w[m] = r["beta"]
        R_w[m] = r["R"][m]
        X1, D1 = optimised_m1(r["geom"], m, r.get("m1_offset"), r["pose"])  # Eq. 7
        v, f = grid_mesh(X1, np.where(m, D1, 0.0), step=cfg.mesh_step)
        if cfg.m1_simplify and len(f):
            v, f, m1_steps = simplify_m1(v, f, wc, cfg)
            r["m1_simplify"] = m1_steps
        verts.append(v)
        faces.append(f + off)
        off += len(v)
    if (wc.width, wc.height) != (W, H):
        beta = cv2.resize(beta_w, (W, H), interpolation=cv2.INTER_NEAREST)
        R = cv2.resize(R_w, (W, H), interpolation=cv2.INTER_LINEAR) * (beta > 0)[..., None]
    else:
        beta, R = beta_w, R_w
    if any(r["mirror"] for r in results):  # mirror special case at full resolution: I1 = I
        R = np.where((beta >= 1.0)[..., None], img, R)
    R = np.clip(np.minimum(R, img), 0, None)
    I0 = img - R  # Eq. 3: I = I0 + beta I1
    I1 = np.where(beta[..., None] > 0, R / np.maximum(beta, 1e-6)[..., None], 0.0)
    m0_off = [r["m0_offset"] for r in results if r.get("m0_offset") is not None]
    # masks are disjoint, so the offsets add (Eq. 7's M0 vertex offsets; others are 0)
    m0v = optimised_m0(m0_vertices, wc, np.sum(m0_off, axis=0)) if m0_off else None
    return ViewLayers(np.clip(I0, 0, 1), np.clip(I1, 0, 1), beta.astype(np.float32),
                      np.concatenate(verts), np.concatenate(faces), m0v)


def layer_report(results: list[dict], report: dict) -> dict:
    """layers.json: `report` with the kept decompositions' JSON-ready entries."""
    out = dict(report)
    out["reflectors"] = [{k: v for k, v in r.items() if k not in _INTERNAL} for r in results]
    return out
