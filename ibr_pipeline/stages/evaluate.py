"""Stage `evaluate`: held-out metrics, side-by-sides, a chart and the fly-through video.

Reads `renders/test` (+ `test_single`, `fly`, `fly_single`, `tour`) of `render_views` and the input's
ground truth. Methods compared on the same cameras:
  ours     two-layer rendering of the reconstructed representation (renders/test)
  single   the same renderer with the decomposition off (renders/test_single; ~InsideOut)
  oracle   the same renderer on the representation built from GT depth and GT layers
           (`render/oracle.py`; synthetic inputs only) — the ceiling of the reconstruction stages
  nearest  the captured image nearest to the camera (Eq. 14), unwarped
  naive    the naïve diffuse warp (`render/naive.py`): the nearest captured image that sees each
           pixel, warped with the global mesh's depth only (no per-view meshes, blending or
           layers) — the floor; its ms/frame is measured here (numpy + open3d ray casting, CPU)
PSNR/SSIM/FLIP (`metrics`) over the whole image and inside reflectors (held-out views: GT material
that reflects (kr > 0, or glass) from gt/test/geom; leave-one-out views: GT beta > 0, or the
reflection stage's beta when there is no GT; held-out photographs of a real capture: the reflectors of reflection/planes.json
projected into them, less what the global mesh puts in front). Temporal stability on the
fly-through: mean absolute frame-to-frame change of ours vs the GT video, and the error of that
change (flicker).
Outputs: eval/metrics.json (`summary` = the headline numbers), eval/metrics.png (bar chart),
eval/side_by_side/NNNN.png (ours | GT | single-layer | error ×4; display sRGB), eval/fly.mp4 (the
tour set when rendered, else the fly-through).
"""
from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path

from .. import layout as L
from ..config import StageConfig, param
from ..errors import InputError
from ..runner import Stage, StageContext
from .common import scene_is_input_frame

log = logging.getLogger("ibr_pipeline.evaluate")


@dataclass(frozen=True)
class EvaluateConfig(StageConfig):
    flip: bool = param(True, "compute FLIP (slowest metric)")
    oracle: bool = param(True, "render the GT-built oracle representation (synthetic inputs)")
    fps: float = param(24.0, "fly-through video frame rate", min=1.0, max=240.0)
    naive: bool = param(True, "score the naïve diffuse-warp baseline (nearest captured view "
                        "warped with the global mesh's depth)")


def _set_cameras(ctx: StageContext, s: str) -> dict:
    from ..scene import cameras_from_json
    p = ctx.ws.path(L.render_file(s, "cameras.json"))
    return cameras_from_json(p) if p.is_file() else {}


def _gt_image_key(ctx: StageContext, s: str, name: str, source: str) -> str | None:
    if source == "heldout":
        return f"input/gt/test/images/{name}"
    if source == "flythrough":
        return f"input/gt/flythrough/images/{name}"
    if source in ("leave_one_out", "heldout_captures"):
        return ctx.scene.view(name).image
    return None


def _source(ctx: StageContext, s: str) -> str:
    p = ctx.ws.path(L.render_file(s, "timings.json"))
    try:
        return json.loads(p.read_text()).get("source", "") if p.is_file() else ""
    except (OSError, json.JSONDecodeError):
        raise InputError(f"{p}: malformed JSON") from None


def inputs(ctx: StageContext) -> list[str]:
    keys = [L.render_file("test", "cameras.json"), L.render_file("test", "timings.json")]
    if ctx.config.naive and ctx.ws.path(L.GLOBAL_MESH).is_file():
        from ..render.naive import cast_depth_files
        keys += [L.GLOBAL_MESH, L.REGISTERED_CAMERAS]
        keys += [ctx.ws.key(p) for p in cast_depth_files(ctx.ws, L.registered_cameras(ctx.ws)).values()]
    for s in ("test", "test_single", "fly", "fly_single", "tour"):
        cams = _set_cameras(ctx, s)
        if not cams:
            continue
        keys += [L.render_file(s, "cameras.json")] if s != "test" else []
        keys += [L.render_file(s, f"{i:04d}.png") for i in range(len(cams))]
        src = _source(ctx, s)
        if s == "test" and src == "heldout_captures" and ctx.ws.path(L.PLANES).is_file():
            keys += [L.PLANES, L.GLOBAL_MESH]  # the projected reflector masks
        if s in ("test", "fly"):
            keys += [k for n in cams if (k := _gt_image_key(ctx, s, n, src))
                     and ctx.ws.path(k).is_file()]
    return list(dict.fromkeys(keys))


def outputs(ctx: StageContext) -> list[str]:
    n = len(_set_cameras(ctx, "test"))
    out = [L.EVAL_METRICS, L.EVAL_METRICS_PNG]
    out += [f"{L.SIDE_BY_SIDE}/{i:04d}.png" for i in range(n)]
    if _set_cameras(ctx, "fly") or _set_cameras(ctx, "tour"):
        out.append(L.EVAL_FLY_MP4)
    if _energy_histories(ctx.ws):
        out.append(L.EVAL_ENERGY_PNG)
    return out


def _energy_histories(ws) -> dict:
    """{(view, reflector, pass): [energy per optimisation step]} from views/*/layers.json (the
    reflection stage's record of Eq. 7 per step); views without a decomposition give none."""
    out = {}
    for p in sorted(ws.path("views").glob("*/layers.json")):
        try:
            layers = json.loads(p.read_text())
        except (OSError, json.JSONDecodeError):
            raise InputError(f"{p}: malformed JSON") from None
        for r in layers.get("reflectors", []):
            for h in r.get("history", []):
                if "energy" in h and math.isfinite(h["energy"]):
                    out.setdefault((p.parent.name, r.get("name", "?"), h.get("pass", 1)), []).append(h["energy"])
    return {k: v for k, v in out.items() if len(v) > 1 and v[0] > 0}


def _energy_chart(path: Path, histories: dict) -> None:
    """The paper's Fig. 11: the decomposition energy per optimisation step (start, image and
    geometry steps alternating, end), relative to its start, one line per view and reflector."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..workspace import atomic_path
    names = sorted({k[1] for k in histories})
    colours = {n: f"C{i % 10}" for i, n in enumerate(names)}
    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    for (view, name, pss), e in histories.items():
        ax.plot(range(len(e)), [x / e[0] for x in e], color=colours[name], lw=0.8, alpha=0.6,
                ls="-" if pss == 1 else "--")
    for n in names:
        ax.plot([], [], color=colours[n], label=n)
    ax.plot([], [], color="k", ls="--", label="pass 2 (multi-view, Eqs. 11-13)")
    ax.set_xlabel("optimisation step (start, image / geometry steps, end)")
    ax.set_ylabel("Eq. 7 energy / energy at start")
    ax.set_title(f"reflection decomposition convergence ({len(histories)} runs)", fontsize=9)
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)


def _projected_reflector_masks(ctx: StageContext, cameras: dict) -> dict:
    """{held-out photograph: reflector mask} for the reflectors the reflection stage used
    (reflection/planes.json), projected into each camera less what G puts in front of them;
    {} when there are none. A photograph has no depth and no decomposition of its own, so this
    is how "inside the reflector" is measured on a real capture."""
    import numpy as np

    from ..geometry import planes as P
    from ..geometry import raycast
    from ..io.mesh import read_ply
    from .reflection import read_planes
    if not ctx.ws.path(L.PLANES).is_file() or not ctx.ws.path(L.GLOBAL_MESH).is_file():
        return {}
    refl = read_planes(ctx.ws)["reflectors"]
    if not refl:
        return {}
    mesh = read_ply(ctx.ws.path(L.GLOBAL_MESH))
    scene = raycast.build_scene(mesh.vertices, mesh.faces)
    out = {}
    for name, cam in cameras.items():
        occ = raycast.render_depth(scene, cam)
        mask = np.zeros((cam.height, cam.width), bool)
        for r in refl:
            poly = None if r.get("polygon") is None else np.asarray(r["polygon"], np.float64)
            mask |= P.reflector_support(cam, r["plane"], poly, occ)
        out[name] = mask
    return out


def _reflector_mask(ctx: StageContext, name: str, source: str, shape, projected: dict):
    """Reflector mask of a test camera (None when unknown): GT where the input has it, else for
    held-out photographs the projection of the reconstructed reflectors (`projected`)."""
    import numpy as np

    from ..io.images import read_image
    ws = ctx.ws
    if source == "heldout":
        geom = ws.path(f"input/gt/test/geom/{Path(name).stem}.npz")
        scene = ws.path("input/gt/scene.json")
        if geom.is_file() and scene.is_file():
            from ..synthetic.materials import reflecting_indices
            kinds = reflecting_indices(json.loads(scene.read_text()).get("materials", []))
            with np.load(geom) as z:
                return np.isin(z["material"], kinds)
        return None
    if source in ("leave_one_out", "heldout_captures"):
        p = ws.path(f"input/gt/beta/{Path(name).stem}.png")
        if p.is_file():
            return read_image(p)[..., 0] > 0
        p = ws.path(f"{ws.view_dir(name)}/beta.npy")
        if p.is_file():
            b = np.load(p)
            return b > 0 if b.shape == shape else None
        m = projected.get(name)
        return m if m is not None and m.shape == shape and m.any() else None
    return None


def _holes(ctx: StageContext, s: str) -> dict:
    """{frame name: fraction of its pixels no view covered} from renders/<s>/timings.json."""
    p = ctx.ws.path(L.render_file(s, "timings.json"))
    try:
        frames = json.loads(p.read_text()).get("frames", []) if p.is_file() else []
    except (OSError, json.JSONDecodeError):
        raise InputError(f"{p}: malformed JSON") from None
    return {f["name"]: f["holes"] for f in frames if "holes" in f and "name" in f}


def _scores(ref, img, mask, with_flip: bool) -> dict:
    from .. import metrics
    m = metrics.all_metrics(ref, img, mask, with_flip=with_flip)
    return {k: float(v) for k, v in m.items()}


def _score_view(ref, imgs: dict, mask, enc: str, with_flip: bool) -> dict:
    """{method: scores} of one test camera: `_scores` on the stored encoding `enc` (published
    figures are on the stored, usually sRGB, images), and PSNR in the other space, named."""
    from ..io.images import encode
    other = "linear" if enc == "srgb" else "srgb"
    ref_enc = encode(ref, enc)
    out = {}
    for k, img in imgs.items():
        sc = _scores(ref_enc, encode(img, enc), mask, with_flip)
        sc[f"psnr_{other}"] = _psnr_in(other, ref, img)
        out[k] = sc
    return out


def _psnr_in(space: str, ref, img) -> float:
    """PSNR of two linear images after encoding both in `space`."""
    from .. import metrics
    from ..io.images import encode
    return float(metrics.psnr(encode(ref, space), encode(img, space)))


def mean_metrics(rows: list[dict]) -> dict:
    """Per-key mean over rows, ignoring NaN/missing values (None when a key has none)."""
    import numpy as np
    keys = sorted({k for r in rows for k in r})
    out = {}
    for k in keys:
        vals = np.array([r.get(k, np.nan) for r in rows], dtype=np.float64)
        vals = vals[np.isfinite(vals)]
        out[k] = float(vals.mean()) if len(vals) else None
    return out


def temporal(frames: list, gt: list | None) -> dict:
    """Fly-through stability: mean |R_t − R_{t−1}| of ours (and of the GT video), and the mean
    |(R_t − R_{t−1}) − (G_t − G_{t−1})| flicker error against the GT video."""
    import numpy as np
    if len(frames) < 2:
        return {}
    d = [np.abs(b - a).mean() for a, b in zip(frames, frames[1:])]
    out = {"frame_change": float(np.mean(d))}
    if gt is not None and len(gt) == len(frames):
        dg = [np.abs(b - a).mean() for a, b in zip(gt, gt[1:])]
        out["gt_frame_change"] = float(np.mean(dg))
        out["flicker_error"] = float(np.mean([np.abs((b - a) - (gb - ga)).mean() for a, b, ga, gb
                                              in zip(frames, frames[1:], gt, gt[1:])]))
    return out


def run(ctx: StageContext) -> None:
    """The stage, with one pool of ctx.jobs workers (in this process when 1) shared by the
    oracle's view construction and the scoring, so workers start once."""
    from ..executors import LocalExecutor
    with LocalExecutor(max(1, ctx.jobs)) as ex:
        _run(ctx, ex)


def _run(ctx: StageContext, ex) -> None:
    import numpy as np

    from ..io.images import read_image, write_image
    from ..render.video import to_display

    ws, cfg = ctx.ws, ctx.config
    enc = ctx.scene.image_encoding
    test = _set_cameras(ctx, "test")
    if not test:
        raise InputError(f"{ws.path(L.render_file('test', 'cameras.json'))}: no test renders (run render_views)")
    source = _source(ctx, "test")
    single = _set_cameras(ctx, "test_single")
    excludes = {n: (n,) if source == "leave_one_out" else () for n in test}
    # the oracle's views are built by the workers while this process renders the naive baseline
    # and scores the fly-through, which do not need it (without an oracle the baselines are
    # rendered camera by camera below: a real capture's held-out set need not be in memory)
    finish_oracle = (_oracle_model(ctx, ex, [(c, excludes[n]) for n, c in test.items()])
                     if cfg.oracle and source in ("heldout", "leave_one_out") else None)
    naive = _naive_model(ctx) if cfg.naive else None
    baselines = ({n: _naive_baseline(naive, c, excludes[n]) for n, c in test.items()}
                 if naive is not None and finish_oracle is not None else {})
    temporal_result = _fly(ctx)
    oracle = finish_oracle() if finish_oracle is not None else None
    naive_ms = []
    rows = {"ours": [], "single": [], "oracle": [], "naive": [], "nearest": []}
    holes = _holes(ctx, "test")
    projected = _projected_reflector_masks(ctx, test) if source == "heldout_captures" else {}
    per_view, scoring = [], []
    for i, (name, cam) in enumerate(test.items()):
        key = _gt_image_key(ctx, "test", name, source)
        ref = read_image(ws.path(key), enc)
        ours = read_image(ws.path(L.render_file("test", f"{i:04d}.png")), enc)
        if ref.shape != ours.shape:
            raise InputError(f"{ws.path(key)}: ground truth is {ref.shape[1]}x{ref.shape[0]}, "
                             f"the render {ours.shape[1]}x{ours.shape[0]}")
        mask = _reflector_mask(ctx, name, source, ref.shape[:2], projected)
        entry = {"name": name, "reflector_pixels": int(mask.sum()) if mask is not None else 0,
                 "holes": holes.get(name)}
        imgs = {"ours": ours}
        if single:
            imgs["single"] = read_image(ws.path(L.render_file("test_single", f"{i:04d}.png")), enc)
        if oracle is not None:
            f = oracle.render(cam, exclude=excludes[name])
            imgs["oracle"] = np.clip(f.color, 0, 1)
        if naive is not None:
            base = baselines.pop(name) if name in baselines else _naive_baseline(naive, cam, excludes[name])
            entry["nearest_view"], imgs["naive"], imgs["nearest"], ms = base
            naive_ms.append(ms)
        # scored by the workers while this process renders the next camera
        scoring.append(ex.submit(_score_view, ref, imgs, mask, enc, cfg.flip))
        per_view.append(entry)
        err = np.repeat(np.clip(np.abs(ours - ref).mean(2, keepdims=True) * 4, 0, 1), 3, 2)
        panel = [ours, ref, imgs.get("single", np.zeros_like(ours)), err]
        write_image(ws.path(f"{L.SIDE_BY_SIDE}/{i:04d}.png"),
                    np.concatenate([to_display(p) for p in panel], 1))  # display sRGB
    if oracle is not None:
        oracle.release()
    for entry, fut in zip(per_view, scoring):
        for k, sc in fut.result().items():
            rows[k].append(sc)
            entry[k] = sc
    methods = {k: mean_metrics(v) for k, v in rows.items() if v}
    summary = {k: v for k, v in methods["ours"].items()}
    for k in ("single", "oracle", "naive", "nearest"):
        for m, v in methods.get(k, {}).items():
            summary[f"{k}_{m}"] = v
    if naive_ms:
        summary["naive_ms"] = float(np.median(naive_ms))
    if holes:  # pixels no view covers, filled by push-pull (render_views timings)
        summary["holes"] = float(np.mean(list(holes.values())))
    if "single" in methods and methods["ours"].get("psnr_mask") is not None:
        summary["reflector_gain_db"] = methods["ours"]["psnr_mask"] - methods["single"]["psnr_mask"]
    if "oracle" in methods:
        summary["oracle_gap_db"] = methods["oracle"]["psnr"] - methods["ours"]["psnr"]
    result = {"set": "test", "source": source, "summary": summary, "methods": methods,
              "per_view": per_view, "notes": "psnr_mask/ssim_mask/flip_mask: inside reflectors"}
    if temporal_result:
        result["temporal"] = temporal_result
        for k, v in temporal_result["ours"].items():
            summary[f"fly_{k}"] = v
    _chart(ws.path(L.EVAL_METRICS_PNG), methods)
    if hist := _energy_histories(ws):
        _energy_chart(ws.path(L.EVAL_ENERGY_PNG), hist)
    ws.write_json(L.EVAL_METRICS, result)
    log.info("evaluate: PSNR ours %.2f dB (reflectors %s), single-layer %s, oracle %s, naive "
             "warp %s, nearest image %s; holes %s", summary["psnr"], _fmt(summary.get("psnr_mask")),
             _fmt(summary.get("single_psnr")), _fmt(summary.get("oracle_psnr")),
             _fmt(summary.get("naive_psnr")), _fmt(summary.get("nearest_psnr")),
             "n/a" if "holes" not in summary else f"{100 * summary['holes']:.1f} %")


def _naive_baseline(naive, cam, exclude) -> tuple:
    """(nearest view's name, naive-warp image, nearest image, naive frame ms) of one camera."""
    img, _, ms = naive.render(cam, exclude=exclude)
    nearest_name, nearest_img = naive.nearest(cam, exclude=exclude)
    return nearest_name, img, nearest_img, ms


def _fly(ctx: StageContext) -> dict:
    """The fly-through's temporal stability ({} without one: {"ours": ..., "single": ...}) and
    the video: the tour set when rendered (streamed: 96 full-size frames need not be in memory
    at once), else the fly-through."""
    from ..io.images import read_image
    from ..render.video import write_mp4
    ws, enc = ctx.ws, ctx.scene.image_encoding
    fly, out, frames = _set_cameras(ctx, "fly"), {}, []
    if fly:
        fsrc = _source(ctx, "fly")
        frames = [read_image(ws.path(L.render_file("fly", f"{i:04d}.png")), enc) for i in range(len(fly))]
        gkeys = [_gt_image_key(ctx, "fly", n, fsrc) for n in fly]
        gt = ([read_image(ws.path(k), enc) for k in gkeys]
              if all(k and ws.path(k).is_file() for k in gkeys) else None)
        out["ours"] = temporal(frames, gt)
        fs = _set_cameras(ctx, "fly_single")
        if fs:
            sframes = [read_image(ws.path(L.render_file("fly_single", f"{i:04d}.png")), enc)
                       for i in range(len(fs))]
            out["single"] = temporal(sframes, gt)
    tour = _set_cameras(ctx, "tour")
    if tour:
        write_mp4(ws.path(L.EVAL_FLY_MP4), (read_image(ws.path(L.render_file("tour", f"{i:04d}.png")),
                                                       enc) for i in range(len(tour))), fps=ctx.config.fps)
    elif fly:
        write_mp4(ws.path(L.EVAL_FLY_MP4), frames, fps=ctx.config.fps)
    return out


def _fmt(v) -> str:
    return "n/a" if v is None else f"{v:.2f} dB"


def _render_config(ctx: StageContext):
    """The workspace's `[render_views]` settings (ibr.toml), for the baselines rendered here."""
    from ..config import build_config
    from .render_views import RenderViewsConfig
    return build_config(RenderViewsConfig, "render_views", ctx.ws.config().get("render_views", {}))


def _renderer_settings(ctx: StageContext):
    """`_render_config`'s renderer with what it leaves to the workspace resolved (Eq. 14's D)."""
    from ..render.ibr import resolve_settings
    return resolve_settings(ctx.ws, _render_config(ctx).renderer)


def _naive_model(ctx: StageContext):
    from ..render.naive import from_workspace
    s = _renderer_settings(ctx)
    return from_workspace(ctx.ws, lam=s.lam, scene_depth=s.scene_depth)


def _oracle_model(ctx: StageContext, ex, frames: list):
    """finish() -> the GT-built model of the views the renderer selects for `frames` [(camera,
    exclude)] (renders as the model of every view would, `views_needed`), its views started on
    `ex` now (`GroundTruth.submit_model`); None without the ground truth."""
    from ..render.ibr import views_needed
    from ..render.oracle import GroundTruth
    root = ctx.ws.input_root
    if not (root / "gt" / "geom").is_dir() or not (root / "gt" / "mesh.ply").is_file():
        return None
    # the oracle lives in the true frame: only where the scene frame is that frame (given poses,
    # not normalised: without depth frames the poses stage rescales even given poses)
    if not (root / "cameras.json").is_file() or not scene_is_input_frame(ctx):
        return None
    gt, settings = GroundTruth(root), _renderer_settings(ctx)
    return gt.submit_model(ex.submit if ex.jobs > 1 else None, layers=True, settings=settings,
                           names=views_needed(gt.cameras, settings, frames))


def _chart(path: Path, methods: dict) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from ..workspace import atomic_path
    groups = [("psnr", "PSNR (dB)"), ("psnr_mask", "PSNR in reflectors (dB)"), ("ssim", "SSIM"),
              ("flip", "FLIP (lower is better)")]
    fig, axes = plt.subplots(1, len(groups), figsize=(3.2 * len(groups), 3.2))
    names = list(methods)
    for ax, (key, title) in zip(axes, groups):
        vals = [methods[m].get(key) for m in names]
        ax.bar(names, [np.nan if v is None else v for v in vals],
               color=["tab:blue", "tab:orange", "tab:green", "tab:gray", "tab:brown"][:len(names)])
        ax.set_title(title, fontsize=9)
        for j, v in enumerate(vals):
            if v is not None:
                ax.text(j, v, f"{v:.3g}", ha="center", va="bottom", fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)


STAGE = Stage(name="evaluate", help="held-out metrics, charts and videos (PSNR/SSIM/FLIP)",
              config=EvaluateConfig, version="9", run=run, inputs=inputs, outputs=outputs)
