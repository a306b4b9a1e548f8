"""Held-out re-rendering of the reflection benchmark (target: re-rendering both layers at a
held-out neighbour view beats warping the unsplit image by >= 5 dB): predictions of a view t
from a neighbour k's layers (`predict`, `rerender`, through k's own M0/M1: `rerender_own`), the
renderer-like blend of the neighbours' predictions, the perfect-reflection-layer ceiling, and the
`heldout` driver used by `ibr bench reflection --heldout` (docs/REFLECTION.md, "Held-out
re-rendering")."""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from ibr_pipeline.geometry.reflection_layers import visible_from
from ibr_pipeline.metrics import psnr

from .reflection import forget_passes, make_loader


def predict(tg, kg, R_k, tol: float = 0.05, layers=None, own_r=None) -> dict | None:
    """Predictions of the held-out view t's reflector pixels (`sel` = t's mask with M1) from
    neighbour k, on every `sel` pixel (`ok` marks where both warps are valid; other pixels are 0).
    Layered: I0_k at a = w(u, M0) (surface points of t projected into k) + R_k = beta I1_k at
    b = w(u, M1) (t's mirror-world points projected into k), as in Eq. 8; unsplit: I_k(a).
    `layers` = (I0_k, R_k) of another source (GT): `gt_layers`. `own_r` = t's own reflection
    layer R_t (GT) on `sel`: `perfect_r` = I0_k(a) from `layers` + R_t, the prediction by a
    perfect reflection layer, whose error is the surface layer's resampling alone (the part both
    predictions share). None when fewer than 50 pixels are valid."""
    from ibr_pipeline.geometry.decompose_terms import sample_bilinear
    sel, a, b, ok = visible_from(tg, kg, tol)
    if ok.sum() < 50:
        return None
    out = {"sel": sel, "ok": ok, "target": tg.image[sel]}

    def put(x):
        full = np.zeros((len(ok), 3))
        full[ok] = x
        return full
    a, b = a[ok], b[ok]
    out["layers"] = put(sample_bilinear(kg.image - R_k, a) + sample_bilinear(R_k, b))
    out["unsplit"] = put(sample_bilinear(kg.image, a))
    if layers is not None:
        s0 = sample_bilinear(layers[0], a)
        out["gt_layers"] = put(s0 + sample_bilinear(layers[1], b))
        if own_r is not None:
            out["perfect_r"] = put(s0 + own_r[ok])
    return out


def rerender(tg, kg, R_k, tol: float = 0.05, layers=None):
    """`predict` on the valid pixels only: (target, layered, unsplit, extra, coverage) with extra
    the prediction from `layers` (or None), or None."""
    p = predict(tg, kg, R_k, tol, layers)
    if p is None:
        return None
    ok = p["ok"]
    extra = p["gt_layers"][ok] if layers is not None else None
    return p["target"][ok], p["layers"][ok], p["unsplit"][ok], extra, float(ok.mean())


def blend_predictions(preds: list[dict], weights) -> dict | None:
    """The renderer's per-pixel blend (render/ibr.py, Eq. 15): each prediction of `predict`
    weighted by its view weight where its warps are valid, normalised over the views valid at
    the pixel; the same weights for every kind (layered, unsplit, GT layers), so the comparison
    stays fair. Returns {kind: blended (N, 3) on the covered pixels, "target": ..., "n": N}."""
    if not preds:
        return None
    Wt = np.zeros(len(preds[0]["ok"]))
    for p, w in zip(preds, weights):
        Wt += w * p["ok"]
    cov = Wt > 0
    if cov.sum() < 50:
        return None
    out = {"target": preds[0]["target"][cov], "n": int(cov.sum())}
    for kind in ("layers", "unsplit", "gt_layers", "perfect_r"):
        if all(kind in p for p in preds):
            acc = sum(w * p["ok"][:, None] * p[kind] for p, w in zip(preds, weights))
            out[kind] = acc[cov] / Wt[cov, None]
    return out


def view_weight_distance(t_cam, k_cam) -> float:
    """Eq. 14's d_k of capture view k for the novel view t (render/selection.py): what the
    renderer's Eq. 15 weights exp(-d_k / delta) are computed from."""
    from ibr_pipeline.render.selection import view_distance
    return float(view_distance(k_cam.viewing_direction[None], k_cam.center[None],
                               t_cam.viewing_direction, t_cam.center)[0])


def _through_own(kg, X, centre, D, pos, offset):
    """Where k's own mesh of depth D (optionally offset, geometry_step.py) is seen along the rays
    centre -> X: pos + J (eps + delta(pos)), the first-order ray-surface intersection."""
    from ibr_pipeline.geometry.decompose_terms import sample_bilinear
    from ibr_pipeline.geometry.geometry_step import shift_jacobian
    J, eps = shift_jacobian(kg.camera, X, X - centre, np.where(kg.mask, D, 0.0))
    dlt = 0.0 if offset is None else sample_bilinear(np.asarray(offset)[..., None], pos)[:, 0]
    return pos + J * (eps + dlt)[:, None]


def rerender_own(tg, kg, R_k, m1_offset=None, tol: float = 0.05, m0_offset=None,
                 own_m0: bool = False):
    """As `rerender`'s layered prediction, but the reflection layer is sampled where k's OWN M1
    (optionally with its optimised relative depth offsets) is seen through t's pixels (what
    rendering M1.ply of k at t gives) and, with `own_m0`, the surface layer where k's own M0
    (optionally offset: M0.ply) is seen, instead of t's surface points. Returns (target,
    layered) or None."""
    from ibr_pipeline.geometry.decompose_terms import sample_bilinear
    sel, a, b, ok = visible_from(tg, kg, tol)
    if ok.sum() < 50:
        return None
    c = tg.camera.center
    b = _through_own(kg, tg.X1[sel][ok], c, kg.D1, b[ok], m1_offset)
    a = a[ok]
    if own_m0:
        a = _through_own(kg, tg.X0[sel][ok], c, kg.depth, a, m0_offset)
    lay = sample_bilinear(kg.image - R_k, a) + sample_bilinear(R_k, b)
    return tg.image[sel][ok], lay


def heldout(ws, scene: Path, base: dict, neighbours: int = 2, m1_noise: float = 0.0) -> dict:
    """Leave-one-out re-rendering: every capture view t that sees a reflector is held out (the
    decompositions of its nearest views k are recomputed without t: t is neither a neighbour nor
    a prior source), t's reflector pixels are predicted from k's layers and from k's unsplit
    image warped with the surface depth, and compared with t's own image (PSNR inside the mask,
    pixels where both warps are valid). Also: the same prediction from k's GT layers, and the
    one of a perfect reflection layer (k's GT surface layer + t's own GT reflection layer): its
    gain over the unsplit warp (`perfect_r`) bounds what any split can gain with these warps,
    because both predictions share the surface layer's resampling error.

    Per pair (t, k) and, as render/ibr.py re-renders, per held-out view with the neighbours'
    predictions blended per pixel by the renderer's Eq. 15 weights (`blended_*`; the unsplit
    image blended with the same weights)."""
    from ibr_pipeline.geometry.decompose_terms import pose_distance
    from ibr_pipeline.geometry.reflection_views import decompose_reflector
    from ibr_pipeline.render.blend import view_weights
    from ibr_pipeline.render.oracle import GroundTruth
    gt = GroundTruth(scene)
    cfg, loader = make_loader(ws, base, m1_noise)
    opts = cfg.decompose
    names = list(loader.names)
    per: dict = {}
    kinds = ("layers", "unsplit", "gt_layers", "perfect_r")
    t0 = time.perf_counter()
    for refl in loader.reflectors:
        seen = [n for n in names if loader.mask(n, refl).sum() >= cfg.min_mask_pixels]
        for t in seen:
            tg = loader.geom(t, refl)
            t0_gt, t1_gt, tb_gt = gt.layers(t)
            r_t = (tb_gt[..., None] * t1_gt)[tg.mask & (tg.D1 > 0)]
            loader.names = [n for n in names if n != t]
            forget_passes(loader)
            used, preds, dists = 0, [], []
            for k in sorted((k for k in seen if k != t),
                            key=lambda k: pose_distance(tg.camera, loader.geom(k, refl).camera)):
                if used >= neighbours:
                    break
                info = decompose_reflector(loader, k, refl, opts)
                if "discarded" in info:
                    continue
                kg = info["geom"]
                g0, g1, gb = gt.layers(k)
                got = predict(tg, kg, info["R"], opts.visibility_tol,
                              layers=(g0, gb[..., None] * g1), own_r=r_t)
                if got is None:
                    continue
                used += 1
                preds.append(got)
                dists.append(view_weight_distance(tg.camera, kg.camera))
                ok = got["ok"]
                tgt = got["target"][ok]
                lay, uns, gtl, pr = (got[x][ok] for x in kinds)
                d = per.setdefault(refl["name"], {"pairs": [], "views": [], "se": np.zeros(4),
                                                  "n": 0, "bse": np.zeros(4), "bn": 0})
                d["pairs"].append({"heldout": t, "from": k, "pixels": len(tgt),
                                   "coverage": float(ok.mean()), "d_k": dists[-1],
                                   "pose_distance": pose_distance(tg.camera, kg.camera),
                                   **{x: psnr(y, tgt) for x, y in zip(kinds, (lay, uns, gtl, pr))}})
                m0o, m1o = info.get("m0_offset"), info.get("m1_offset")
                own = []  # k's own M1 (and M0), before / after their offsets
                if m1o is not None:
                    own += [("layers_own_m1", None, None, False),
                            ("layers_own_m1_opt", m1o, None, False)]
                if m0o is not None:
                    own += [("layers_own", None, None, True), ("layers_own_opt", m1o, m0o, True)]
                for key, o1, o0, m0 in own:
                    got = rerender_own(tg, kg, info["R"], o1, opts.visibility_tol, o0, m0)
                    if got is not None:
                        d["pairs"][-1][key] = psnr(got[1], got[0])
                d["se"] += [((x - tgt) ** 2).mean(1).sum() for x in (lay, uns, gtl, pr)]
                d["n"] += len(tgt)
            w = view_weights(np.asarray(dists)) if dists else []
            bl = blend_predictions(preds, w)
            if bl is not None:
                d = per[refl["name"]]
                tgt = bl["target"]
                d["views"].append({"heldout": t, "from": [p["from"] for p in d["pairs"][-used:]],
                                   "weights": [float(x) for x in w / np.sum(w)],
                                   "pixels": bl["n"],
                                   **{x: psnr(bl[x], tgt) for x in kinds}})
                d["bse"] += [((bl[x] - tgt) ** 2).mean(1).sum() for x in kinds]
                d["bn"] += bl["n"]
    loader.names = names
    out = {"seconds": time.perf_counter() - t0, "neighbours_per_view": neighbours}
    for name, d in per.items():
        ps, vs = d["pairs"], d["views"]
        med = lambda rows, f: float(np.median([f(r) for r in rows])) if rows else None  # noqa: E731
        pooled = [float(10 * np.log10(d["n"] / max(se, 1e-30))) for se in d["se"]]
        bpooled = [float(10 * np.log10(d["bn"] / max(se, 1e-30))) if d["bn"] else None
                   for se in d["bse"]]
        o = out[name] = {"pairs": len(ps),
                         "median_layers_psnr": med(ps, lambda p: p["layers"]),
                         "median_unsplit_psnr": med(ps, lambda p: p["unsplit"]),
                         "median_gain_db": med(ps, lambda p: p["layers"] - p["unsplit"]),
                         "median_gt_layers_psnr": med(ps, lambda p: p["gt_layers"]),
                         "median_gt_layers_gain_db": med(ps, lambda p: p["gt_layers"] - p["unsplit"]),
                         "median_perfect_r_psnr": med(ps, lambda p: p["perfect_r"]),
                         "median_perfect_r_gain_db": med(ps, lambda p: p["perfect_r"] - p["unsplit"]),
                         "pooled_layers_psnr": pooled[0], "pooled_unsplit_psnr": pooled[1],
                         "pooled_gt_layers_psnr": pooled[2], "pooled_perfect_r_psnr": pooled[3],
                         "blended_views": len(vs)}
        for x in kinds:
            o[f"blended_median_{x}_psnr"] = med(vs, lambda v: v[x])
        for x in ("layers", "gt_layers", "perfect_r"):
            o[f"blended_median_{x}_gain_db"] = med(vs, lambda v: v[x] - v["unsplit"])
        for x, v in zip(kinds, bpooled):
            o[f"blended_pooled_{x}_psnr"] = v
        o["per_pair"], o["per_view"] = ps, vs
        for key in ("layers_own_m1", "layers_own_m1_opt", "layers_own", "layers_own_opt"):
            v = [p[key] for p in ps if key in p]
            if v:
                o["median_" + key + "_psnr"] = float(np.median(v))
    return out
