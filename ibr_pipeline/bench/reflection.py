"""Benchmark of stage `reflection` (issue #6) against synthetic ground truth.

    .venv/bin/python -m ibr_pipeline.bench.reflection [--scene tiny|mirror_room] [--out DIR]
        [--repeats 3] [--scale 1.0]

Builds a workspace whose upstream outputs are the exact synthetic geometry (global/cameras.json,
global/mesh.ply = gt/mesh.ply, views/<v>/depth.npy from gt/geom, a grid mesh.ply), runs the stage
through the runner and reports: plane accuracy of the detection (normal angle, offset vs GT),
PSNR of I0 and beta*I1 inside each reflector vs gt/I0, gt/I1, gt/beta, the mirror's I1, the
held-out re-rendering gain over warping the unsplit image, the ablation table, and seconds per
reflective view (median of --repeats runs of one view). Prints and writes JSON.
"""
from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]


def make_gt_workspace(scene: Path, ws_dir: Path, mesh_step: int = 4):
    """A workspace over `scene` whose global_mesh / view_depth / view_mesh outputs are exact GT."""
    from ..geometry.planes import depth_points, grid_mesh
    from ..io.mesh import Mesh, write_ply
    from ..pipeline import load_configs, run, select_stages
    from ..scene import cameras_from_json, cameras_to_json
    from ..stages import STAGES
    from ..workspace import Workspace

    scene, ws_dir = Path(scene), Path(ws_dir)
    ws_dir.mkdir(parents=True, exist_ok=True)
    (ws_dir / "ibr.toml").write_text(f"[input]\npath = {json.dumps(str(scene.resolve()))}\n")
    ws = Workspace(ws_dir)
    sel = select_stages(STAGES, only="ingest")
    run(STAGES, ws, load_configs(STAGES, ws), sel, progress=False)
    cams = cameras_from_json(scene / "cameras.json")
    ws.write_text("global/cameras.json", cameras_to_json(cams))
    shutil.copyfile(scene / "gt" / "mesh.ply", ws.path("global/mesh.ply"))
    for name, cam in cams.items():
        stem = Path(name).stem
        depth = np.load(scene / "gt" / "geom" / f"{stem}.npz")["depth"].astype(np.float32)
        with ws.atomic_write(ws.view_file(name, "depth.npy")) as f:
            np.save(f, depth)
        v, fc = grid_mesh(depth_points(cam, depth), depth, step=mesh_step)
        write_ply(ws.path(ws.view_file(name, "mesh.ply")), Mesh(v, fc))
    return ws


def run_stage(ws, overrides: dict | None = None, force: bool = False):
    from ..pipeline import load_configs, run, select_stages
    from ..stages import STAGES
    sel = select_stages(STAGES, only="reflection")
    return run(STAGES, ws, load_configs(STAGES, ws, {"reflection": overrides or {}}), sel,
               force=force, progress=False)


def read_gt(scene: Path, name: str):
    from ..io.images import read_image
    stem = Path(name).stem
    g = scene / "gt"
    return (read_image(g / "I0" / f"{stem}.png"), read_image(g / "I1" / f"{stem}.png"),
            read_image(g / "beta" / f"{stem}.png")[..., 0])


def layer_accuracy(ws, scene: Path) -> dict:
    """PSNR of I0 and beta*I1 per reflector (pixels of our beta support with that reflectance)."""
    from ..io.images import read_image
    from ..metrics import psnr
    out: dict = {}
    for lay in sorted(ws.root.glob("views/*/layers.json")):
        rep = json.loads(lay.read_text())
        if rep["reflector"] is None:
            continue
        vdir = lay.parent
        name = next(n for n in json.loads((Path(scene) / "cameras.json").read_text())["cameras"]
                    if vdir.name == Path(n).name or vdir.name == n)
        I0, I1, beta = read_image(vdir / "I0.png"), read_image(vdir / "I1.png"), np.load(vdir / "beta.npy")
        g0, g1, gb = read_gt(scene, name)
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
    planes = json.loads(ws.path("reflection/planes.json").read_text())
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


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m ibr_pipeline.bench.reflection")
    ap.add_argument("--scene", default="mirror_room", help="tiny | mirror_room | a scene folder")
    ap.add_argument("--out", type=Path, default=Path("out/bench_reflection"))
    ap.add_argument("--repeats", type=int, default=3)
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
    args = ap.parse_args(argv)
    if args.workspace is not None:
        return _score_workspace(args)
    if args.scene == "mirror_room":
        scene = REPO / "sample_data" / "mirror_room"
    elif args.scene == "tiny":
        from ..synthetic.generate import SynthOptions, generate
        scene = args.out / "tiny_scene"
        if not (scene / "cameras.json").is_file():
            generate(SynthOptions("tiny", seed=3, progress=False), scene)
    else:
        scene = Path(args.scene)
    ws_dir = args.out / "ws"
    if ws_dir.exists():
        shutil.rmtree(ws_dir)
    ws = make_gt_workspace(scene, ws_dir)
    result: dict = {"scene": str(scene), "work_scale": args.scale}
    t0 = time.perf_counter()
    over = {"work_scale": args.scale, "multiview": args.multiview}
    if args.no_user_reflectors:
        over["use_user_reflectors"] = False
    if args.no_decompose:
        from ..config import build_config
        from ..runner import StageContext
        from ..stages.reflection import Loader, ReflectionConfig, get_planes
        ctx = StageContext(ws, "reflection", build_config(ReflectionConfig, "reflection", over),
                           ws.scene())
        c0 = time.process_time()
        get_planes(ctx, Loader(ctx))
        result["planes_seconds"] = time.perf_counter() - t0
        result["planes_cpu_seconds"] = time.process_time() - c0
        result["planes"] = plane_accuracy(ws, scene)
        result["candidates"] = json.loads(ws.path("reflection/planes.json").read_text())["candidates"]
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "reflection_bench.json").write_text(json.dumps(result, indent=1))
        print(json.dumps(result, indent=1))
        return 0
    run_stage(ws, over)
    result["stage_seconds"] = time.perf_counter() - t0
    recs = [json.loads(p.read_text()) for p in ws.state_dir("reflection").glob("*.json")]
    refl_views = [r["view"] for r in recs if any(k.endswith("I0.png") for k in r["outputs"])]
    result["views"] = len(recs)
    result["reflective_views"] = len(refl_views)
    result["seconds_per_reflective_view"] = float(np.median(
        [r["seconds"] for r in recs if r["view"] in refl_views])) if refl_views else None
    result["seconds_per_plain_view"] = float(np.median(
        [r["seconds"] for r in recs if r["view"] not in refl_views])) if len(refl_views) < len(recs) else None
    result["layers"] = layer_accuracy(ws, scene)
    result["planes"] = plane_accuracy(ws, scene)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "reflection_bench.json").write_text(json.dumps(result, indent=1))
    print(json.dumps(result, indent=1))
    return 0


def _timings(ws) -> dict:
    recs = [json.loads(p.read_text()) for p in ws.state_dir("reflection").glob("*.json")]
    refl = [r for r in recs if any(k.endswith("I0.png") for k in r.get("outputs", {}))]
    plain = [r for r in recs if r not in refl]
    med = (lambda rs: float(np.median([r["seconds"] for r in rs])) if rs else None)  # noqa: E731
    return {"views": len(recs), "reflective_views": len(refl),
            "seconds_per_reflective_view": med(refl), "seconds_per_plain_view": med(plain)}


def _score_workspace(args) -> int:
    """Layer (and, when planes were detected, plane) accuracy of a real workspace's outputs."""
    from ..workspace import Workspace
    ws = Workspace(args.workspace)
    scene = REPO / "sample_data" / "mirror_room" if args.scene == "mirror_room" else Path(args.scene)
    result = {"workspace": str(args.workspace), "scene": str(scene), **_timings(ws),
              "layers": layer_accuracy(ws, scene)}
    if ws.path("reflection/planes.json").is_file():
        result["planes"] = plane_accuracy(ws, scene)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "reflection_bench.json").write_text(json.dumps(result, indent=1))
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
