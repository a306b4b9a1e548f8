"""Benchmark of stage `reflection` against synthetic ground truth.

    ibr bench reflection [--scene tiny|mirror_room|DIR] [--out DIR] [--repeats 3] [--scale 1.0]
        [--ablation [--rows 0,4]] [--heldout] [--timing] [--depth-noise 0.01] [--m1-noise 0.02]

Builds a workspace whose upstream outputs are the exact synthetic geometry
(ibr_pipeline.gt_workspace: global/cameras.json, global/mesh.ply = gt/mesh.ply, views/<v>/depth.npy
from gt/geom, a grid mesh.ply), runs the stage through the runner and reports: plane accuracy of
the detection (normal angle, offset vs GT), PSNR of I0 and beta*I1 inside each reflector vs gt/I0,
gt/I1, gt/beta, the mirror's I1, the held-out re-rendering gain over warping the unsplit image,
the ablation table, and seconds per reflective view (median of --repeats runs of one view).
Prints and writes OUT/reflection_bench.json.
"""
from __future__ import annotations

import argparse
import json
import shutil
import time
import zlib
from pathlib import Path

import numpy as np

from ibr_pipeline import layout as L
from ibr_pipeline.geometry.reflection_views import Footprint, Loader


def make_gt_workspace(scene: Path, ws_dir: Path, depth_noise: float = 0.0):
    """A workspace over `scene` whose global_mesh / view_depth / view_mesh outputs are exact GT
    (grid meshes). depth_noise > 0: each view's depth is multiplied by 1 + a smooth random field
    (std `depth_noise`) -- MVS-like low-frequency errors, so that the surface flows w(u, M0) are
    misaligned by a few pixels (what the ARAP warp of Eq. 5 corrects)."""
    from ibr_pipeline.gt_workspace import write_gt_workspace
    return write_gt_workspace(scene, ws_dir, "view_mesh", mesh="grid", depth_noise=depth_noise)


def run_stage(ws, overrides: dict | None = None, force: bool = False):
    """Stages `reflectors` and `reflection`; `overrides`: fields of either (stage_configs)."""
    from ibr_pipeline.geometry.reflection_views import split_overrides
    from ibr_pipeline.pipeline import load_configs, run, select_stages
    from ibr_pipeline.stages import STAGES
    return run(STAGES, ws, load_configs(STAGES, ws, split_overrides(overrides or {})),
               select_stages(STAGES, "reflectors", "reflection"), force=force, progress=False)


def layer_accuracy(ws, scene: Path) -> dict:
    """PSNR of I0 and beta*I1 per reflector (pixels of our beta support with that reflectance)."""
    from ibr_pipeline.io.images import read_image
    from ibr_pipeline.metrics import psnr
    from ibr_pipeline.render.oracle import GroundTruth
    gt = GroundTruth(scene)
    out: dict = {}
    for lay in sorted(ws.root.glob(f"views/*/{L.LAYERS}")):
        rep = json.loads(lay.read_text())
        if rep["reflector"] is None:
            continue
        vdir = lay.parent
        name = next(n for n in json.loads((Path(scene) / "cameras.json").read_text())["cameras"]
                    if vdir.name == Path(n).name or vdir.name == n)
        I0, I1, beta = read_image(vdir / L.I0), read_image(vdir / L.I1), np.load(vdir / L.BETA)
        g0, g1, gb = gt.layers(name)
        for r in rep["reflectors"]:
            m = np.isclose(beta, r["beta"]) & (gb > 0)
            if m.sum() < 50:
                continue
            d = out.setdefault(r["name"], {"I0": [], "betaI1": [], "I1": [], "pixels": 0})
            d["I0"].append(psnr(I0, g0, m))
            d["betaI1"].append(psnr(beta[..., None] * I1, gb[..., None] * g1, m))
            d["I1"].append(psnr(I1, g1, m))
            d["pixels"] += int(m.sum())
    return {k: {"I0_psnr": float(np.median(v["I0"])), "betaI1_psnr": float(np.median(v["betaI1"])),
                "I1_psnr": float(np.median(v["I1"])), "views": len(v["I0"]), "pixels": v["pixels"]}
            for k, v in out.items()}


def plane_accuracy(ws, scene: Path) -> list[dict]:
    """For each GT reflector: the closest detected plane's normal angle (deg) and offset (m)."""
    gt = json.loads((Path(scene) / "reflectors.json").read_text())["reflectors"]
    planes = json.loads(ws.path(L.PLANES).read_text())
    det = [p for p in planes["reflectors"] if p.get("source") == "detected"]
    rows = []
    for g in gt:
        n, d = np.asarray(g["plane"][:3]), g["plane"][3]
        best = None
        for p in det:
            pn, pd = np.asarray(p["plane"][:3]), p["plane"][3]
            if pn @ n < 0:
                pn, pd = -pn, -pd
            ang = float(np.degrees(np.arccos(np.clip(pn @ n, -1, 1))))
            row = {"reflector": g["name"], "detected": p["name"], "angle_deg": ang,
                   "offset_m": float(abs(pd - d))}
            if best is None or ang + 100 * row["offset_m"] < best["angle_deg"] + 100 * best["offset_m"]:
                best = row
        rows.append(best or {"reflector": g["name"], "detected": None})
    return rows


# --- ablation and held-out re-rendering ----------------------------------------------------------
# Both call the stage's own per-reflector decomposition (`geometry.reflection_views.decompose_reflector`)
# on a Loader of the workspace, in float (no 8-bit PNG round trip), one config per row.
_NO_V = {"optimise_m1_vertices": False}  # rows 0-6: the paper's terms alone, M1's vertices fixed


def _d(over: dict) -> dict:
    return {"decompose": over}


ABLATION = [  # cumulative rows of the paper's terms, then the additions of this implementation
    ("init only (Eq. 6, no warp)", _d({"use_warp": False, "outer_iterations": 0, "lambda_scene": 0.0,
                                    **_NO_V})),
    ("+ optimisation (Eq. 7)", _d({"use_warp": False, "lambda_scene": 0.0, **_NO_V})),
    ("+ multi-view consistency (Eqs. 11-13)", _d({"use_warp": False, "lambda_scene": 0.0,
                                               "multiview": True, **_NO_V})),
    ("+ ARAP warp (Eqs. 4-5) = paper", _d({"lambda_scene": 0.0, "multiview": True, **_NO_V})),
    ("init only + ARAP warp", _d({"outer_iterations": 0, "lambda_scene": 0.0, **_NO_V})),
    ("paper without multi-view", _d({"lambda_scene": 0.0, **_NO_V})),
    ("+ reflected-scene prior, multi-view", _d({"multiview": True, **_NO_V})),
    ("stage defaults (prior, no multi-view)", _d({})),
    ("stage defaults, M1 vertices off", _d({"optimise_m1_vertices": False})),
    ("+ M1 vertices (cotangent Laplacian)", _d({"optimise_m1_vertices": True})),
    ("paper without multi-view + M1 vertices", _d({"lambda_scene": 0.0, "optimise_m1_vertices": True})),
    ("+ M0 vertices (cotangent Laplacian)", _d({"optimise_m0_vertices": True})),
    ("paper without multi-view + M0 vertices", _d({"lambda_scene": 0.0, "optimise_m0_vertices": True})),
    ("+ M0 and M1 vertices", _d({"optimise_m0_vertices": True, "optimise_m1_vertices": True})),
]


class NoisyM1Loader(Loader):
    """The stage's Loader, with every view's M1 depth (its mirror-world points) multiplied by
    1 + a smooth random field of std `m1_noise` (independent per view and reflector, like the
    depth noise): M1 errors that the vertex optimisation can fix (G and the planes stay exact).
    `m1_true[(view, reflector)]` keeps the unperturbed M1 depth of every footprint built."""

    def __init__(self, ws, scene, cfg, m1_noise: float = 0.0):
        super().__init__(ws, scene, cfg)
        self.m1_noise = m1_noise
        self.m1_true: dict = {}
        self.noisy: dict = {}  # (view, reflector) -> the perturbed footprint

    def footprint(self, name, refl) -> Footprint:
        key = (name, refl["name"])
        if key not in self.noisy:
            from ibr_pipeline.gt_workspace import smooth_noise
            fp = super().footprint(name, refl)
            self.m1_true[key] = fp.D1.copy()
            if self.m1_noise > 0:
                f = smooth_noise(fp.D1.shape, self.m1_noise, zlib.crc32(f"m1/{name}/{key[1]}".encode()))
                fp = Footprint(fp.name, fp.camera, fp.mask, (fp.D1 * (1 + f)).astype(np.float32))
            self.noisy[key] = fp
        return self.noisy[key]


def make_loader(ws, over: dict, m1_noise: float = 0.0):
    """(config, loader) of the stage on `ws` with reflection overrides `over`; the loader's
    reflectors are the computed planes (NoisyM1Loader for `m1_noise`)."""
    from ibr_pipeline.geometry.reflection_views import compute_planes, stage_configs
    dcfg, cfg = stage_configs(over)
    reflectors = compute_planes(Loader(ws, ws.scene(), dcfg))["reflectors"]
    loader = NoisyM1Loader(ws, ws.scene(), cfg, m1_noise)
    loader.reflectors = reflectors
    return cfg, loader


def true_depth(scene: Path, name: str, camera) -> np.ndarray:
    """The GT z-depth of view `name` (what --depth-noise perturbs) at `camera`'s size."""
    import cv2

    from ibr_pipeline.gt_workspace import gt_depth
    d = gt_depth(scene, name)
    if d.shape != (camera.height, camera.width):
        d = cv2.resize(d, (camera.width, camera.height), interpolation=cv2.INTER_NEAREST)
    return d


def depth_error(D, offset, true, mask) -> float:
    """Mean |D (1 + offset) / true - 1| over the mask's pixels where both depths exist."""
    D = D * (1 + (0.0 if offset is None else offset))
    k = mask & (true > 0) & (D > 0)
    return float(np.mean(np.abs(D[k] / true[k] - 1))) if k.any() else 0.0


def forget_passes(loader) -> None:
    """Drop the loader's first-pass reflection layers (multi-view pass) before another config."""
    loader.first.clear()


def ablation(ws, scene: Path, base: dict, rows=None, m1_noise: float = 0.0) -> list[dict]:
    """PSNR of I0 and beta*I1 vs the GT layers inside each (non-mirror) reflector's mask, median
    over the views, for each configuration row (`ABLATION`). Mirrors are exact in every row.
    Also M1's and M0's depth errors in the mask (mean |D (1 + delta) / D_true - 1|, median over
    views; M0's truth is the GT depth, which --depth-noise perturbs)."""
    from ibr_pipeline.geometry.reflection_views import decompose_reflector, stage_configs
    from ibr_pipeline.metrics import psnr
    from ibr_pipeline.render.oracle import GroundTruth
    gt = GroundTruth(scene)
    _, loader = make_loader(ws, base, m1_noise)
    out = []
    for label, over in rows or ABLATION:
        cfg = stage_configs(base, over)[1]
        opts = cfg.decompose
        forget_passes(loader)
        per: dict = {}
        c0, t0 = time.process_time(), time.perf_counter()
        for v in loader.names:
            g0, g1, gb = gt.layers(v)
            for refl in loader.reflectors:
                if refl.get("beta") == 1.0 or loader.mask(v, refl).sum() < cfg.min_mask_pixels:
                    continue
                info = decompose_reflector(loader, v, refl, opts)
                d = per.setdefault(refl["name"], {"I0": [], "betaI1": [], "discarded": 0,
                                                  "warp": [], "m1": [], "m0": []})
                for h in info.get("history", []):  # Eq. 5 energy after / before the GN warp
                    for e in (h.get("warp_energy") or {}).values():
                        if e and e[0] > 0:
                            d["warp"].append(e[-1] / e[0])
                if "discarded" in info:
                    d["discarded"] += 1
                    continue
                m = info["mask"] & (gb > 0)
                if m.sum() < 50:
                    continue
                I, R = info["geom"].image, info["R"]
                g = info["geom"]
                d["m1"].append(depth_error(g.D1, info.get("m1_offset"),
                                           loader.m1_true[(v, refl["name"])], info["mask"]))
                d["m0"].append(depth_error(g.depth, info.get("m0_offset"),
                                           true_depth(scene, v, g.camera), info["mask"]))
                d["I0"].append(psnr((I - R)[m], g0[m]))
                d["betaI1"].append(psnr(R[m], (gb[..., None] * g1)[m]))
        row = {"row": label, "config": over, "seconds": time.perf_counter() - t0,
               "cpu_seconds": time.process_time() - c0}
        for name, d in per.items():
            row[name] = {"I0_psnr": float(np.median(d["I0"])) if d["I0"] else None,
                         "betaI1_psnr": float(np.median(d["betaI1"])) if d["betaI1"] else None,
                         "I0_per_view": [round(x, 2) for x in d["I0"]], "views": len(d["I0"]),
                         "warp_energy_ratio": float(np.median(d["warp"])) if d["warp"] else None,
                         "m1_depth_error": float(np.median(d["m1"])) if d["m1"] else None,
                         "m0_depth_error": float(np.median(d["m0"])) if d["m0"] else None,
                         "discarded": d["discarded"]}
        out.append(row)
        print(json.dumps({k: v for k, v in row.items() if k != "config"}), flush=True)
    return out


def timing(ws, base: dict) -> dict:
    """Seconds per view of the stage's `run` in one process, views in order (like one worker:
    the Loader cache is shared, so later views reuse the masks / mirror points of earlier ones).
    Wall and CPU (process) seconds; reflective views = those that wrote I0.png."""
    from ibr_pipeline.geometry.reflection_views import compute_planes, stage_configs
    from ibr_pipeline.runner import StageContext
    from ibr_pipeline.stages.common import registered_views
    from ibr_pipeline.stages.reflection import run as run_view
    dcfg, cfg = stage_configs(base)
    ws.write_json(L.PLANES, compute_planes(Loader(ws, ws.scene(), dcfg)))
    ctx = StageContext(ws, "reflection", cfg, ws.scene())
    rows = []
    for v in registered_views(ctx):
        c0, t0 = time.process_time(), time.perf_counter()
        run_view(ctx, v)
        rows.append({"view": v, "wall": time.perf_counter() - t0, "cpu": time.process_time() - c0,
                     "reflective": ws.path(ws.view_file(v, L.I0)).is_file()})
    refl = [r for r in rows if r["reflective"]]
    plain = [r for r in rows if not r["reflective"]]
    med = (lambda rs, k: float(np.median([r[k] for r in rs])) if rs else None)  # noqa: E731
    return {"per_view": rows, "reflective_views": len(refl),
            "median_wall_reflective": med(refl, "wall"), "median_cpu_reflective": med(refl, "cpu"),
            "max_wall_reflective": max((r["wall"] for r in refl), default=None),
            "median_wall_plain": med(plain, "wall"), "first_view_wall": rows[0]["wall"]}


def add_arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--scene", default="mirror_room",
                    help="tiny (generated in OUT) | mirror_room (sample_data/) | a scene folder")
    ap.add_argument("--out", type=Path, default=Path("out/bench_reflection"),
                    help="output folder (default out/bench_reflection)")
    ap.add_argument("--repeats", type=int, default=3, help="runs of the timed view (default 3)")
    ap.add_argument("--scale", type=float, default=1.0, help="reflection.work_scale")
    ap.add_argument("--multiview", action="store_true", help="reflection.multiview = true")
    ap.add_argument("--no-user-reflectors", action="store_true",
                    help="ignore the scene's reflectors.json (detect = auto then detects the planes; "
                         "the file is still the ground truth of the plane accuracy)")
    ap.add_argument("--no-decompose", action="store_true",
                    help="with --no-user-reflectors: stop after the planes (no decomposition)")
    ap.add_argument("--workspace", type=Path, help="score this existing workspace (reflection "
                    "already run, e.g. the demo's out/demo) instead of building one from ground "
                    "truth; --scene is its input folder (default: the sample)")
    ap.add_argument("--ablation", action="store_true", help="the ablation table (ABLATION rows)")
    ap.add_argument("--heldout", action="store_true",
                    help="leave-one-out re-rendering of reflector pixels: layers vs unsplit image")
    ap.add_argument("--timing", action="store_true",
                    help="seconds per view of the stage's run, in-process (wall and CPU)")
    ap.add_argument("--rows", help="ablation rows to run: comma-separated indices into ABLATION")
    ap.add_argument("--heldout-neighbours", type=int, default=2,
                    help="--heldout: neighbour views predicting each held-out view (default 2)")
    ap.add_argument("--depth-noise", type=float, default=0.0,
                    help="smooth relative depth error of the GT workspace (MVS-like), e.g. 0.01 "
                         "(M0's source: what M0's vertex optimisation fixes)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="reflection config override for --ablation / --heldout / --timing "
                         "(repeatable; VALUE parsed as JSON, e.g. decompose.optimise_m0_vertices=true)")
    ap.add_argument("--m1-noise", type=float, default=0.0,
                    help="--ablation / --heldout: smooth relative error of every view's M1 depth "
                         "(mirror-world points), e.g. 0.02 (what M1's vertex optimisation fixes)")


def _scene(args) -> Path:
    from .common import SAMPLE, tiny_scene
    if args.scene == "mirror_room":
        return SAMPLE
    if args.scene == "tiny":
        return tiny_scene(args.out / "tiny_scene")
    return Path(args.scene)


def _write(args, result: dict) -> int:
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "reflection_bench.json").write_text(json.dumps(result, indent=1))
    print(json.dumps(result, indent=1))
    return 0


def main(args: argparse.Namespace) -> int:
    if args.workspace is not None:
        return _score_workspace(args)
    scene = _scene(args)
    ws_dir = args.out / "ws"
    if ws_dir.exists():
        shutil.rmtree(ws_dir)
    ws = make_gt_workspace(scene, ws_dir, depth_noise=args.depth_noise)
    result: dict = {"scene": str(scene), "work_scale": args.scale, "depth_noise": args.depth_noise,
                    "m1_noise": args.m1_noise}
    if args.ablation or args.heldout or args.timing:
        from ibr_pipeline.config import nest
        sets = {k: _json_or_str(v) for k, v in (a.split("=", 1) for a in args.set)}
        result["set"] = sets
        base = {"work_scale": args.scale, "detect": "off", **nest(sets)}
        if args.ablation:
            rows = ([ABLATION[int(i)] for i in args.rows.split(",")] if args.rows else None)
            result["ablation"] = ablation(ws, scene, base, rows, args.m1_noise)
        if args.heldout:
            from .reflection_heldout import heldout
            result["heldout"] = heldout(ws, scene, base, args.heldout_neighbours, args.m1_noise)
        if args.timing:
            result["timing"] = timing(ws, {"work_scale": args.scale, **nest(sets)})
        return _write(args, result)
    t0 = time.perf_counter()
    over = {"work_scale": args.scale, "decompose": {"multiview": args.multiview}}
    if args.no_user_reflectors:
        over["use_user_reflectors"] = False
    if args.no_decompose:
        from ibr_pipeline.geometry.reflection_views import compute_planes, stage_configs
        c0 = time.process_time()
        ws.write_json(L.PLANES, compute_planes(Loader(ws, ws.scene(), stage_configs(over)[0])))
        result["planes_seconds"] = time.perf_counter() - t0
        result["planes_cpu_seconds"] = time.process_time() - c0
        result["planes"] = plane_accuracy(ws, scene)
        result["candidates"] = json.loads(ws.path(L.PLANES).read_text())["candidates"]
        return _write(args, result)
    run_stage(ws, over)
    result["stage_seconds"] = time.perf_counter() - t0
    result.update(_timings(ws))
    result["layers"] = layer_accuracy(ws, scene)
    result["planes"] = plane_accuracy(ws, scene)
    return _write(args, result)


def _json_or_str(v: str):
    try:
        return json.loads(v)
    except json.JSONDecodeError:
        return v


def _timings(ws) -> dict:
    """Views and median seconds per reflective / plain view, from the runner's records."""
    recs = [json.loads(p.read_text()) for p in ws.state_dir("reflection").glob("*.json")]
    refl = [r for r in recs if any(k.endswith(L.I0) for k in r.get("outputs", {}))]
    plain = [r for r in recs if r not in refl]
    med = (lambda rs: float(np.median([r["seconds"] for r in rs])) if rs else None)  # noqa: E731
    return {"views": len(recs), "reflective_views": len(refl),
            "seconds_per_reflective_view": med(refl), "seconds_per_plain_view": med(plain)}


def _score_workspace(args) -> int:
    """Layer (and, when planes were detected, plane) accuracy of a real workspace's outputs."""
    from ibr_pipeline.workspace import Workspace

    from .common import SAMPLE
    ws = Workspace(args.workspace)
    scene = SAMPLE if args.scene == "mirror_room" else Path(args.scene)
    result = {"workspace": str(args.workspace), "scene": str(scene), **_timings(ws),
              "layers": layer_accuracy(ws, scene)}
    if ws.path(L.PLANES).is_file():
        result["planes"] = plane_accuracy(ws, scene)
    return _write(args, result)
