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

from .reflection_views import Loader, ReflectionConfig, decompose_reflector

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


def decompose_view(loader: Loader, view: str, reflectors: list[dict],
                   cfg: ReflectionConfig) -> tuple[list[dict], dict]:
    """(kept decompositions, layers.json report) of `view` for every reflector whose mask in it
    has at least cfg.min_mask_pixels pixels; discarded ones are named in the report."""
    _, _, wc, _, _ = loader.raw(view)
    results, skipped = [], []
    for refl in reflectors:
        if int(loader.mask(view, refl).sum()) < cfg.min_mask_pixels:
            continue
        r = decompose_reflector(loader, view, refl, cfg.decompose)
        (skipped if "discarded" in r else results).append(r)
    report = {"reflector": None, "reflectors": [], "discarded": [
        {k: v for k, v in r.items()
         if k in ("name", "discarded", "neighbours", "mask_pixels")}
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
            from .reflection_views import simplify_m1
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
