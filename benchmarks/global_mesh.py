"""Benchmark of stage `global_mesh` against synthetic ground truth.

    ibr bench global_mesh [--scene tiny|mirror_room|sample|PATH] [--views 30]
        [--parts rgbd,mvs,sfm,mvs_speed] [--repeats 3] [--device cpu|cuda] [--output FILE.json]

* rgbd: poses given, TSDF fusion of the depth frames with reflectors.json: F-score at 5 cm vs
  gt/mesh.ply (mirror-world points excluded from precision and reported separately), fusion ms/frame.
* mvs: poses given, no depth (dense=mvs): the same F-score, MVS s/view.
* sfm: forced SfM (--matching, default auto), Sim(3)-aligned pose errors, registration rate, s/image.
* mvs_speed: one plane sweep with the stage's MVS defaults (working size = mvs_scale x image
  size, 4 sources), median wall and CPU time of --repeats.
`mirror_room` is generated at 640x480 with --views capture views (default 30, ~1 min).
"""
from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from ibr_pipeline import layout as L
from ibr_pipeline.errors import InputError

PARTS = ("rgbd", "mvs", "sfm", "mvs_speed")


def _scene(name: str, views: int, work: Path, size: tuple[int, int] | None = None) -> Path:
    if name == "sample":
        from .common import SAMPLE
        return SAMPLE
    if name not in ("tiny", "mirror_room"):
        return Path(name)
    from ibr_pipeline.synthetic.generate import SynthOptions, generate
    out = work / name
    w, h = size or (None, None)
    opts = SynthOptions(name, seed=0, width=w, height=h, views=None if name == "tiny" else views,
                        test_views=1, flythrough=2, gt_layers=False, raytree_pairs=0, jobs=1,
                        progress=False)
    generate(opts, out)
    return out


def _run_stage(scene: Path, ws: Path, sets: list[str]) -> dict:
    from ibr_pipeline.cli import main as cli
    args = ["run", str(ws), "--input", str(scene), "--until", "global_mesh"]
    for s in sets + ["global_mesh.progress=false"]:
        args += ["--set", s]
    if cli(args) != 0:
        raise RuntimeError(f"global_mesh failed on {scene}")
    return json.loads((ws / L.GLOBAL_REPORT).read_text())


def _fscore(scene: Path, ws: Path) -> dict:
    from ibr_pipeline.geometry.fusion import mirror_world_points
    from ibr_pipeline.geometry.mesh_metrics import distance_to_mesh, fscore, observed_points
    from ibr_pipeline.gt_workspace import gt_depth
    from ibr_pipeline.io.inputs import read_input
    from ibr_pipeline.io.mesh import read_ply
    sc = read_input(scene)
    cams = [v.camera for v in sc.views]
    depths = [gt_depth(scene, v.name) for v in sc.views]
    gt, mesh = read_ply(scene / "gt" / "mesh.ply"), read_ply(ws / L.GLOBAL_MESH)
    excl = lambda p: mirror_world_points(p, sc.reflectors, cams)  # noqa: E731
    res = fscore(mesh.vertices, mesh.faces, gt.vertices, gt.faces, observed_points(cams, depths),
                 tau=0.05, exclude=excl)
    raw = fscore(mesh.vertices, mesh.faces, gt.vertices, gt.faces, observed_points(cams, depths), tau=0.05)
    res["fscore_without_exclusion"] = raw["fscore"]
    mw = excl(mesh.vertices)
    far = distance_to_mesh(mesh.vertices[mw], gt.vertices, gt.faces) > 0.05 if mw.any() else mw[mw]
    res["mirror_world_vertex_fraction"] = float(far.sum() / max(len(mesh.vertices), 1))
    return res


def bench_mvs_speed(scene: Path, repeats: int, device: str, threads: int = 1) -> dict:
    """One plane sweep of the middle view with the stage's defaults (working size = image size x
    mvs_scale, pyramid, window, hypotheses, 4 sources), median wall and CPU time of `repeats`."""
    import cv2
    import torch

    from ibr_pipeline.geometry.mvs import plane_sweep, select_sources
    from ibr_pipeline.io.images import read_image
    from ibr_pipeline.io.inputs import read_input
    from ibr_pipeline.stages.global_mesh import GlobalMeshConfig
    cfg = GlobalMeshConfig()
    sc = read_input(scene)
    full = {v.name: v.camera for v in sc.views}
    W, H = full[sc.names[0]].size
    w, h = round(W * cfg.mvs_scale), round(H * cfg.mvs_scale)
    cams = {n: c.resized(w, h) for n, c in full.items()}
    ref = sc.names[len(sc.names) // 2]
    src = select_sources(cams[ref], cams, k=cfg.mvs_sources)
    imgs = {n: cv2.resize(read_image(scene / "images" / n), (w, h), interpolation=cv2.INTER_AREA)
            for n in [ref] + src}
    prev = torch.get_num_threads()
    torch.set_num_threads(threads)
    times, cpu = [], []
    try:
        for _ in range(repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            plane_sweep(imgs[ref], cams[ref], [imgs[s] for s in src], [cams[s] for s in src],
                        cfg.mvs_depth_min, cfg.mvs_depth_max, num_depths=cfg.mvs_depths,
                        window=cfg.mvs_window, device=device, max_cost=cfg.mvs_max_cost,
                        coarse_levels=cfg.mvs_coarse_levels, refine_depths=cfg.mvs_refine_depths,
                        refine_levels=0 if cfg.mvs_coarse_levels > 0 else 1)
            if device == "cuda":
                torch.cuda.synchronize()
            times.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
    finally:
        torch.set_num_threads(prev)
    return {"image_size": [W, H], "working_size": [w, h], "sources": len(src),
            "s_per_view_median": statistics.median(times), "cpu_s_per_view_median": statistics.median(cpu),
            "runs": times, "device": device, "torch_threads": threads}


def add_arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--scene", default="tiny", help="tiny, mirror_room (generated), sample, or a folder")
    ap.add_argument("--views", type=int, default=30, help="capture views when generating mirror_room")
    ap.add_argument("--size", default=None, help="WxH when generating mirror_room (default 640x480)")
    ap.add_argument("--matching", default="auto", choices=("auto", "sequential", "exhaustive"),
                    help="poses.matching for the sfm part")
    ap.add_argument("--parts", default=",".join(PARTS),
                    help=f"comma-separated parts to run (default {','.join(PARTS)})")
    ap.add_argument("--repeats", type=int, default=3, help="runs of the rgbd and mvs_speed parts (3)")
    ap.add_argument("--device", default="cpu", choices=("cpu", "cuda"), help="global_mesh.device")
    ap.add_argument("--threads", type=int, default=None, help="global_mesh.threads (pycolmap and "
                    "torch threads; default: the stage default)")
    ap.add_argument("--mvs-scale", type=float, default=None, help="global_mesh.mvs_scale (default: "
                    "1.0 for tiny, else the stage default)")
    ap.add_argument("--output", default="bench_global_mesh.json",
                    help="JSON result (default bench_global_mesh.json)")


def main(args: argparse.Namespace) -> int:
    parts = [p.strip() for p in args.parts.split(",") if p.strip()]
    bad = [p for p in parts if p not in PARTS]
    if bad:
        raise InputError(f"--parts: unknown part(s) {bad} (choose from {', '.join(PARTS)})")
    out: dict = {"scene": args.scene, "machine_note": "2 shared cores unless stated", "results": {}}
    with tempfile.TemporaryDirectory(prefix="bench-gm-") as tmp:
        tmp = Path(tmp)
        size = tuple(int(x) for x in args.size.lower().split("x")) if args.size else None
        scene = _scene(args.scene, args.views, tmp, size)
        mvs_scale = args.mvs_scale or (1.0 if args.scene == "tiny" else None)
        common = [f"global_mesh.threads={args.threads}"] if args.threads else []
        for part in parts:
            t0 = time.perf_counter()
            if part == "rgbd":
                runs = []
                for i in range(args.repeats):
                    rep = _run_stage(scene, tmp / f"rgbd{i}", common)
                    runs.append(rep["timings"]["fusion_ms_per_frame"])
                res = {"fusion_ms_per_frame_median": statistics.median(runs), "runs": runs,
                       "stage_total_s": rep["timings"]["total_s"], **_fscore(scene, tmp / f"rgbd{i}")}
            elif part == "mvs":
                sets = common + ["global_mesh.dense=mvs", f"global_mesh.device={args.device}"]
                if mvs_scale:
                    sets.append(f"global_mesh.mvs_scale={mvs_scale}")
                rep = _run_stage(scene, tmp / "mvs", sets)
                res = {"mvs_s_per_view": rep["timings"]["mvs_s_per_view"],
                       "mvs_cpu_s_per_view": rep["timings"].get("mvs_cpu_s_per_view"),
                       "mvs_filter_s_per_view": rep["timings"].get("mvs_filter_s_per_view"),
                       "stage_total_s": rep["timings"]["total_s"],
                       "mvs_valid_fraction": rep.get("mvs_valid_fraction"), **_fscore(scene, tmp / "mvs")}
            elif part == "sfm":
                from ibr_pipeline.geometry.align import pose_errors
                from ibr_pipeline.io.inputs import read_input
                from ibr_pipeline.scene import cameras_from_json
                rep = _run_stage(scene, tmp / "sfm", common + ["poses.force_sfm=true",
                                                               f"poses.matching={args.matching}"])
                truth = {v.name: v.camera for v in read_input(scene).views}
                est = cameras_from_json(tmp / "sfm" / L.REGISTERED_CAMERAS)
                keep = Path(args.output).with_suffix(".sfm_cameras.json")  # for later analysis
                keep.write_text((tmp / "sfm" / L.REGISTERED_CAMERAS).read_text())
                lo, hi = np.array([0, 0, 0]), np.array([5, 4, 2.7])  # room box (docs/SYNTHETIC.md)
                diag = float(np.linalg.norm(hi - lo))
                err = pose_errors(est, truth)
                res = {"registered": len(est), "views": len(truth),
                       "registration_rate": len(est) / len(truth),
                       "sfm_s_per_image": rep["timings"]["poses_s"] / len(truth),
                       "sfm_stats": rep.get("sfm"),
                       "reprojection_error_px": rep["reprojection_error_px"], "alignment": rep.get("alignment"),
                       "pose_errors": err,
                       "center_error_pct_of_room_diagonal": 100 * err["center_m"]["median"] / diag}
            else:  # mvs_speed
                res = bench_mvs_speed(scene, args.repeats, args.device, args.threads or 1)
            res["wall_s"] = time.perf_counter() - t0
            out["results"][part] = res
            print(part, json.dumps(res, indent=1, default=float), flush=True)
    Path(args.output).write_text(json.dumps(out, indent=1, default=float))
    print(f"wrote {args.output}")
    return 0
