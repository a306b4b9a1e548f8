"""The sections of `ibr report`, each a function of the Report that reads recorded files and adds
blocks (report.py says what a block is). Nothing here is measured: numbers become Facts pointing at
their file and key, pictures are drawn by report_figures from those files.
"""
from __future__ import annotations

import json
from pathlib import Path
from statistics import median

from . import layout as L
from . import report_figures as F

SBS_LABELS = ["ours", "ground truth", "single layer", "|error| x4"]
METHODS = [("ours", "", "two-layer IBR (ours)"), ("single", "single_", "single layer"),
           ("oracle", "oracle_", "oracle (GT-built)"), ("naive", "naive_", "naive warp"),
           ("nearest", "nearest_", "nearest captured image")]


def read_json(path: Path):
    try:
        return json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError):
        return None


def flatten(d, prefix: str = "") -> dict:
    out = {}
    if isinstance(d, dict):
        for k, v in d.items():
            out.update(flatten(v, f"{prefix}.{k}" if prefix else str(k)))
    elif isinstance(d, (int, float, str, bool)) or d is None:
        out[prefix] = d
    return out


def _cameras(path: Path) -> dict:
    from .scene import cameras_from_json
    from .errors import InputError
    try:
        return cameras_from_json(path) if path.is_file() else {}
    except (InputError, OSError, ValueError):  # a picture is left out, the report still written
        return {}


def _display(path: Path, encoding: str):
    from .io.images import read_image
    from .render.video import to_display
    return to_display(read_image(path, encoding))


def latest_results(results: Path) -> list[dict]:
    """The rows of an `ibr bench` results.jsonl, the latest per (scene, setting)."""
    latest: dict[tuple, dict] = {}
    for line in Path(results).read_text().splitlines():
        if line.strip():
            r = json.loads(line)
            latest[(r.get("scene"), r.get("setting"))] = r
    return list(latest.values())


# --- summary -------------------------------------------------------------------------------------
def summary(rep) -> None:
    m = read_json(rep.root / L.EVAL_METRICS)
    if not isinstance(m, dict) or "summary" not in m:
        return
    src, s = rep.root / L.EVAL_METRICS, m["summary"]
    ms = {"ours": rep.root / L.render_file("test", "timings.json"),
          "single": rep.root / L.render_file("test_single", "timings.json")}
    rows = []
    for method, pre, label in METHODS:
        if f"{pre}psnr" not in s:
            continue
        cells = [label] + [rep.fact(s[k], src, f"summary.{k}") if k in s else "-"
                           for k in (f"{pre}psnr", f"{pre}ssim", f"{pre}flip", f"{pre}psnr_mask")]
        t = read_json(ms[method]) if method in ms else None
        if t and t.get("median_ms") is not None:
            cells.append(rep.fact(t["median_ms"], ms[method], "median_ms"))
        elif method == "naive" and "naive_ms" in s:
            cells.append(rep.fact(s["naive_ms"], src, "summary.naive_ms"))
        else:
            cells.append("-")
        rows.append(cells)
    scene = read_json(rep.root / L.SCENE)
    enc = scene.get("image_encoding", "linear") if isinstance(scene, dict) else "linear"
    other = "linear" if enc == "srgb" else "srgb"
    blocks = [("p", f"Held-out cameras ({m.get('source', '?')}), {len(m.get('per_view', []))} "
                    f"views; PSNR in dB on the images in the capture's encoding ({enc}; "
                    f"`summary.psnr_{other}` in eval/metrics.json: {other}), SSIM, FLIP (lower "
                    "is better), and PSNR inside reflectors; ms/frame: medians as the stages "
                    "rendered them, beside their other worker processes (`ibr bench speed` "
                    "times frames alone)."),
              ("table", ["method", "PSNR", "SSIM", "FLIP", "PSNR in reflectors", "ms/frame"], rows)]
    extra = [(k, label) for k, label in (("reflector_gain_db", "two layers over single layer "
                                                               "inside reflectors (dB)"),
                                         ("holes", "fraction of held-out pixels no view covers "
                                                   "(push-pull filled)"),
                                         ("oracle_gap_db", "oracle minus ours (dB)"))
             if k in s]
    if extra:
        blocks.append(("table", ["quantity", "value"],
                       [[label, rep.fact(s[k], src, f"summary.{k}")] for k, label in extra]))
    if (rep.root / L.EVAL_METRICS_PNG).is_file():
        blocks.append(("img", rep.root / L.EVAL_METRICS_PNG, "held-out metrics per method"))
    rep.add("Held-out accuracy", blocks)


def side_by_sides(rep, limit: int = 8) -> None:
    m = read_json(rep.root / L.EVAL_METRICS) or {}
    src = rep.root / L.EVAL_METRICS
    per_view = m.get("per_view", []) if isinstance(m, dict) else []
    single = (rep.root / L.render_file("test_single", "cameras.json")).is_file()
    labels = SBS_LABELS if single else SBS_LABELS[:2] + ["(single layer not rendered)"] + SBS_LABELS[3:]
    blocks = []
    for i, img in enumerate(sorted((rep.root / L.SIDE_BY_SIDE).glob("*.png"))[:limit]):
        cap = img.stem
        if i < len(per_view):
            v = per_view[i]
            parts = [v.get("name", img.stem)]
            for k, label in (("ours", "ours"), ("single", "single layer")):
                if isinstance(v.get(k), dict) and "psnr" in v[k]:
                    parts.append(f"{label} {rep.fact(v[k]['psnr'], src, f'per_view.{i}.{k}.psnr').text()} dB")
            if v.get("holes") is not None:
                parts.append(f"hole fraction {rep.fact(v['holes'], src, f'per_view.{i}.holes').text()}")
            cap = ": ".join([parts[0], ", ".join(parts[1:])]) if len(parts) > 1 else parts[0]
        blocks.append(("sbs", img, labels, cap))
    if blocks:
        blocks.insert(0, ("p", "Each row: our render, the photograph held out, the single-layer "
                               "render, and our absolute error (x4), in display sRGB."))
    rep.add("Held-out views, side by side", blocks)


# --- reflections ---------------------------------------------------------------------------------
def reflections(rep, per_reflector: int = 2) -> None:
    import numpy as np
    root = rep.root
    scene = read_json(root / "scene.json") or {}
    enc = scene.get("image_encoding", "linear")
    from .workspace import Workspace
    ws = Workspace(root)
    images = {v.get("name"): v.get("image") for v in scene.get("views", [])}
    planes_src = root / "reflection" / "planes.json"
    planes = read_json(planes_src) or {}
    stats: dict[str, dict] = {}
    for p in sorted((root / "views").glob(f"*/{L.LAYERS}")):
        d = read_json(p) or {}
        view = p.parent.name
        # a layers.json without per-reflector entries (ground-truth layers) names one reflector
        for r in d.get("reflectors") or ([{"name": d["reflector"]}] if d.get("reflector") else []):
            s = stats.setdefault(r["name"], {"kept": [], "dropped": [], "beta": [], "mirror": None})
            s["kept"].append((r.get("mask_pixels", 0), view))
            s["beta"].append(r.get("beta"))
            s["mirror"] = r.get("mirror")
        for r in d.get("discarded", []):
            s = stats.setdefault(r["name"], {"kept": [], "dropped": [], "beta": [], "mirror": None})
            s["dropped"].append((view, str(r.get("discarded"))))
    if not stats and not planes.get("reflectors") and not planes.get("candidates"):
        return
    source = {r["name"]: r.get("source", "?") for r in planes.get("reflectors", [])}
    material = {r["name"]: r.get("material") for r in planes.get("reflectors", [])}
    vsrc = root / "views"
    rows = []
    for name, s in stats.items():
        betas = [b for b in s["beta"] if isinstance(b, (int, float))]
        kind = {True: "mirror (colour-less I0)", False: "glossy / partial"}.get(s["mirror"], "-")
        if material.get(name) == "glass":
            kind = "glass (I0: the scene behind the pane)"
        rows.append([name, kind, source.get(name, "?"),
                     rep.fact(len(s["kept"]), vsrc, f"*/{L.LAYERS}:{name}:kept"),
                     rep.fact(len(s["dropped"]), vsrc, f"*/{L.LAYERS}:{name}:discarded"),
                     rep.fact(median(betas), vsrc, f"*/{L.LAYERS}:{name}:beta:median") if betas else "-"])
    blocks = [("p", "Per reflector: in how many views its two-layer decomposition (Xu et al. Eq. 3, "
                    "I = I0 + beta I1) was kept, in how many it was discarded and why; beta is its "
                    "reflectance."),
              ("table", ["reflector", "kind", "from", "views kept", "views discarded", "beta"], rows)]
    reasons = sorted({why for s in stats.values() for _, why in s["dropped"]})
    if reasons:
        blocks.append(("p", "Reasons for discarding: " + "; ".join(reasons) + "."))
    cands = planes.get("candidates") or []
    if cands:
        def num(i, c, key):
            v = (c.get("score") or {}).get(key)
            return (rep.fact(v, planes_src, f"candidates.{i}.score.{key}")
                    if isinstance(v, (int, float)) else "-")
        blocks.append(("p", f"Reflector detection: {len(cands)} candidates — regions seen behind "
                            "a plane of the depth maps (behind_* in one view, hole_* pooled over "
                            "the views; stage global_mesh) and planes of "
                            "the global mesh (stage reflectors) — each with its evidence and the "
                            "reason it was kept or dropped (docs/REFLECTION.md, Detection)."))
        blocks.append(("table", ["candidate", "verdict", "views", "surface-warp error",
                                 "mirror / surface", "Eq. 3 beta", "Eq. 3 corr", "reason"],
                       [[c.get("name", "?"), "kept" if c.get("kept") else "dropped",
                         rep.fact(c["views"], planes_src, f"candidates.{i}.views")
                         if isinstance(c.get("views"), int) else "-",
                         num(i, c, "surface_error"), num(i, c, "mirror_ratio"),
                         num(i, c, "fit_beta"), num(i, c, "fit_corr"), c.get("reason", "-")]
                        for i, c in sorted(enumerate(cands), key=lambda ic: not ic[1].get("kept"))]))
    m = read_json(root / L.EVAL_METRICS) or {}
    gain = (m.get("summary") or {}).get("reflector_gain_db") if isinstance(m, dict) else None
    if gain is not None:
        blocks.append(("p", f"On held-out views, two layers are {rep.fact(gain, root / L.EVAL_METRICS, 'summary.reflector_gain_db').text()} dB "
                            "above the single layer inside the reflectors."))
    for name, s in stats.items():
        for _, view in sorted(s["kept"], reverse=True)[:per_reflector]:
            vdir = root / "views" / view
            row = []
            try:
                if images.get(view) and ws.path(images[view]).is_file():
                    row.append((F.thumbnail(rep.fig_dir / f"layers_{view}_image.png",
                                            _display(ws.path(images[view]), enc)), "captured image"))
                for f, label in ((L.I0, "I0 surface layer"), (L.I1, "I1 reflection layer")):
                    if (vdir / f).is_file():
                        row.append((F.thumbnail(rep.fig_dir / f"layers_{view}_{Path(f).stem}.png",
                                                _display(vdir / f, enc)), label))
                if (vdir / L.BETA).is_file():
                    row.append((F.thumbnail(rep.fig_dir / f"layers_{view}_beta.png",
                                            F.colour_map(np.load(vdir / L.BETA))), "beta (0 to 1)"))
            except (OSError, ValueError):
                continue
            if row:
                blocks.append(("row", row, f"{name} in view {view} (layers of every reflector "
                                           "of the view)"))
    if (root / L.EVAL_ENERGY_PNG).is_file():
        blocks.append(("img", root / L.EVAL_ENERGY_PNG, "decomposition energy per iteration"))
    rep.add("Reflections", blocks)


# --- cameras, geometry, video --------------------------------------------------------------------
def plan(rep) -> None:
    root = rep.root
    roles = {"training": _cameras(root / L.REGISTERED_CAMERAS),
             "held out": _cameras(root / L.render_file("test", "cameras.json"))
             or _cameras(root / L.HELDOUT_CAMERAS),
             "tour": _cameras(root / L.render_file("tour", "cameras.json"))}
    roles = {k: list(v.values()) for k, v in roles.items() if v}
    if not roles.get("training"):
        return
    pts = None
    if (root / L.GLOBAL_MESH).is_file():
        try:
            import numpy as np

            from .io.mesh import read_ply
            v = read_ply(root / L.GLOBAL_MESH).vertices
            pts = v[np.random.default_rng(0).choice(len(v), min(len(v), 200_000), replace=False)]
        except (OSError, ValueError):
            pts = None
    path = F.top_down(rep.fig_dir / "plan.png", pts, roles,
                      "cameras over the global mesh, seen from above")
    rep.add("Cameras and geometry", [("img", path, "top-down plan: training cameras (blue), "
                                                   "held-out cameras (orange), tour path (green), "
                                                   "global mesh density (grey)")])


def video(rep) -> None:
    vids = [p for p in (rep.root / L.EVAL_FLY_MP4,) if p.is_file()] \
        or sorted(rep.root.glob("renders/**/*.mp4"))
    if not vids:
        return
    t = read_json(rep.root / L.render_file("tour", "timings.json"))
    what = (f"the tour: {rep.fact(len(t['frames']), rep.root / L.render_file('tour', 'timings.json'), 'frames:count').text()} "
            "frames on a smooth path through the fly-through cameras") if t else "the fly-through"
    rep.add("Fly-through", [("video", vids[0], f"{what} ({vids[0].relative_to(rep.root)})")])


# --- DSRNet, speed -------------------------------------------------------------------------------
def dsrnet(rep) -> None:
    src = rep.root / L.TRAIN_JSON
    t = read_json(src)
    if not isinstance(t, dict):
        return
    val = t.get("validation") or {}
    rows = [[label, rep.fact(val[k], src, f"validation.{k}")] for k, label in
            (("psnr", "validation PSNR, DSRNet (dB)"), ("psnr_bilinear", "validation PSNR, "
             "bilinear upsampling (dB)"), ("ssim", "validation SSIM, DSRNet"),
             ("ssim_bilinear", "validation SSIM, bilinear")) if isinstance(val.get(k), (int, float))]
    rows += [[label, rep.fact(t[k], src, k)] for k, label in
             (("steps", "training steps"), ("parameters", "parameters")) if isinstance(t.get(k), int)]
    if isinstance((t.get("seconds") or {}).get("train"), (int, float)):
        rows.append(["training seconds", rep.fact(t["seconds"]["train"], src, "seconds.train")])
    blocks = [("p", "DSRNet (Xu et al. §5.2) supersamples half-resolution renders; trained on "
                    "leave-one-out renders of the captures, validated on views it never saw.")]
    if (rep.root / L.LOSS_PNG).is_file():
        blocks.append(("img", rep.root / L.LOSS_PNG, "training loss per step and validation PSNR "
                                                     "against bilinear upsampling"))
    blocks.append(("table", ["quantity", "value"], rows))
    rep.add("DSRNet supersampling", blocks)


def stage_timings(rep) -> None:
    state = rep.root / ".ibr" / "state"
    if not state.is_dir():
        return
    from .stages import STAGES
    rows, names, secs_all = [], [], []
    for s in STAGES:
        whole = state / f"{s.name}.json"
        per_view = sorted((state / s.name).glob("*.json")) if (state / s.name).is_dir() else []
        recs = [(p, read_json(p)) for p in ([whole] if whole.is_file() else []) + per_view]
        recs = [(p, r) for p, r in recs if r]
        if not recs:
            continue
        ok = sum(r.get("status") == "ok" for _, r in recs)
        secs = [r.get("seconds", 0.0) for _, r in recs]
        src = whole if whole.is_file() else state / s.name
        rows.append([s.name, f"{ok}/{len(recs)} ok", rep.fact(round(sum(secs), 3), src, "sum(seconds)"),
                     rep.fact(round(median(secs), 3), src, "median(seconds)") if per_view else "-"])
        names.append(s.name)
        secs_all.append(round(sum(secs), 3))
    blocks = []
    if rows:
        blocks += [("img", F.stage_times(rep.fig_dir / "stage_times.png", names, secs_all),
                    "seconds per stage"),
                   ("table", ["stage", "records", "seconds (sum)", "s/view (median)"], rows)]
    runs = rep.root / ".ibr" / "runs.jsonl"
    if runs.is_file():
        lines = [json.loads(x) for x in runs.read_text().splitlines() if x.strip()]
        if lines:
            last = lines[-1]
            blocks += [("p", f"Last `ibr run` finished {last['finished']}:"),
                       ("table", ["stage", "result", "wall seconds"],
                        [[e["stage"], e["result"], rep.fact(e["seconds"], runs, f"[-1].{e['stage']}.seconds")]
                         for e in last["stages"]])]
    rep.add("Time per stage", blocks)


def speed(rep) -> None:
    """This run's methods as speed against accuracy, the browser viewer's frame time, and the
    charts and tables of `ibr bench` results found in the bench folders."""
    root = rep.root
    m = read_json(root / L.EVAL_METRICS) or {}
    s = m.get("summary", {}) if isinstance(m, dict) else {}
    pts = []
    for set_, key, label in (("test", "psnr", "two-layer (ours)"), ("test_single", "single_psnr",
                                                                    "single layer")):
        t = read_json(root / L.render_file(set_, "timings.json"))
        if t and t.get("median_ms") and key in s:
            pts.append((label, float(t["median_ms"]), float(s[key])))
    if s.get("naive_ms") and "naive_psnr" in s:
        pts.append(("naive warp", float(s["naive_ms"]), float(s["naive_psnr"])))
    blocks = []
    if len(pts) >= 2:
        blocks.append(("img", F.speed_accuracy(rep.fig_dir / "speed_accuracy.png", pts,
                                               "this run: frame time against held-out PSNR"),
                       "speed against accuracy of the renderers of this run"))
    vsrc = root / "bench" / "viewer.json"
    v = read_json(vsrc)
    if isinstance(v, dict):
        blocks.append(("table", ["browser viewer (ibr bench viewer)", "value"],
                       [[label, rep.fact(v[k], vsrc, k)] for k, label in
                        (("browser_median_ms", "frame ms in the browser (median)"),
                         ("offline_median_ms", "frame ms offline, same run"),
                         ("first_frame_s", "seconds to the first frame"),
                         ("bundle_mb", "bundle MB"),
                         ("agreement_psnr_min", "browser vs offline PSNR, worst held-out (dB)"))
                        if isinstance(v.get(k), (int, float))]))
    for bench in rep.bench_dirs:
        blocks += bench_blocks(rep, bench)
    rep.add("Speed", blocks)


def bench_blocks(rep, bench: Path) -> list:
    results = bench / "results.jsonl"
    if not results.is_file():
        return []
    blocks: list = [("img", p, f"ibr bench: {p.stem.replace('_', ' ')}") for p in sorted(bench.glob("*.png"))]
    rows, stab = [], []
    for r in latest_results(results):
        mm = r.get("metrics") or {}
        key = f"{r.get('scene')}/{r.get('setting')}"
        f = lambda v, k: "-" if v is None else rep.fact(v, results, f"{key}.{k}")  # noqa: E731
        if r.get("group") == "stability":
            did = r.get("crashed") or "; ".join(r.get("fallbacks") or []) or "completed"
            stab.append([r["setting"], did, f(mm.get("psnr"), "metrics.psnr")])
        else:
            rows.append([r["setting"], r.get("group", ""), f(r.get("preprocess_s"), "preprocess_s"),
                         f(r.get("render_ms"), "render_ms"), f(mm.get("psnr"), "metrics.psnr"),
                         f(mm.get("ssim"), "metrics.ssim"), f(mm.get("flip"), "metrics.flip"),
                         f(mm.get("psnr_mask"), "metrics.psnr_mask"),
                         f(r.get("mb_per_view"), "mb_per_view")])
    if rows:
        blocks.append(("table", ["setting", "group", "preprocess s", "render ms", "PSNR", "SSIM",
                                 "FLIP", "PSNR in reflectors", "MB/view"], rows))
    if stab:
        blocks.append(("table", ["degradation", "what the pipeline did", "PSNR"], stab))
    return blocks


# --- appendix ------------------------------------------------------------------------------------
def json_table(rep, path: Path, title: str, skip=("config",)) -> list:
    d = read_json(path)
    if not isinstance(d, dict):
        return []
    flat = {k: v for k, v in flatten(d).items() if not any(k.startswith(s) for s in skip)}
    rows = [[k, rep.fact(v, path, k)] for k, v in flat.items()
            if isinstance(v, (int, float)) and not isinstance(v, bool)]
    rows += [[k, str(v)] for k, v in flat.items() if isinstance(v, str) and len(v) < 80]
    if not rows:
        return []
    return [("h", f"{title}: {path.relative_to(rep.root)}"), ("table", ["key", "value"], rows[:80])]


def per_view_table(rep, name: str, title: str) -> list:
    files = sorted((rep.root / "views").glob(f"*/{name}"))
    vals: dict[str, list[float]] = {}
    for f in files:
        for k, v in flatten(read_json(f) or {}).items():
            if isinstance(v, (int, float)) and not isinstance(v, bool):
                vals.setdefault(k, []).append(float(v))
    if not vals:
        return []
    src = rep.root / "views"
    rows = [[k, rep.fact(len(v), src, f"*/{name}:{k}:count"),
             rep.fact(round(median(v), 6), src, f"*/{name}:{k}:median"),
             rep.fact(round(min(v), 6), src, f"*/{name}:{k}:min"),
             rep.fact(round(max(v), 6), src, f"*/{name}:{k}:max")] for k, v in vals.items()]
    return [("h", f"{title}: views/*/{name}, {len(files)} views"),
            ("table", ["key", "views", "median", "min", "max"], rows)]


def appendix(rep) -> None:
    root = rep.root
    blocks = (json_table(rep, root / L.POSES_REPORT, "Poses",
                         skip=("config", "transform", "depth_ranges", "gt_to_scene.R"))
              + json_table(rep, root / "global" / "report.json", "Global mesh")
              + per_view_table(rep, L.DEPTH_REPORT, "Per-view depth refinement")
              + per_view_table(rep, L.MESH_REPORT, "Per-view meshes")
              + per_view_table(rep, L.LAYERS, "Reflection layers")
              + json_table(rep, root / L.EVAL_METRICS, "Held-out evaluation")
              + json_table(rep, root / L.TRAIN_JSON, "DSRNet training"))
    if blocks:
        rep.add("Appendix: every recorded value", [("details", "recorded values, by file", blocks)])
