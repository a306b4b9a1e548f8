"""`ibr render WS --cameras FILE | --heldout | --path fly [--supersample] [--out DIR]`.

Renders new views of a workspace with the two-layer renderer (`render/ibr.py`): PNG frames (linear
8-bit, scene.py convention), an MP4 (display sRGB) when there are two frames or more, and
`timings.json` (per-frame milliseconds, selected views). Light at import time.
"""
from __future__ import annotations

import argparse
from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser("render", help="render new views of a workspace (PNGs, MP4, timings)",
                       description="Render novel views with view selection, fuzzy depth test and "
                       "two-layer blending (Xu et al. 2021 §5.1). Needs view_mesh outputs; uses "
                       "the reflection layers when the reflection stage has run.")
    p.add_argument("workspace", type=Path, help="workspace folder")
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--cameras", type=Path, metavar="FILE",
                   help="the views to render: cameras.json, a nerfstudio transforms.json or "
                   "camera_path.json (rendered as a sequence, with its MP4)")
    g.add_argument("--heldout", action="store_true",
                   help="the input's held-out cameras (gt/test_cameras.json); leave-one-out "
                   "capture views when there are none")
    g.add_argument("--path", choices=("fly",), help="fly: gt/flythrough_cameras.json, or a smooth "
                   "path through the registered cameras")
    p.add_argument("--frame", choices=("scene", "input"), default="scene",
                   help="--cameras are in the scene frame (what `ibr export` writes; default) or "
                   "in the input's own frame (the poses the capture came with), mapped through "
                   "global/poses.json")
    p.add_argument("--out", type=Path, help="output folder (default WS/renders/cli_<what>)")
    p.add_argument("--supersample", nargs="?", const="on", default="off",
                   choices=("on", "off", "auto"),
                   help="render at low resolution and upsample with DSRNet (needs the supersample "
                   "stage); 'auto': only when that is as good, or faster and within 0.5 dB, on "
                   "this machine, measured on DSRNet's validation views first (the log says which)")
    p.add_argument("--self-ensemble", action="store_true",
                   help="with --supersample: average DSRNet on the frame and its mirror image "
                   "(+0.06 dB on held-out views, 1.75x the network time; docs/DSRNET.md)")
    p.add_argument("--single-layer", action="store_true", help="decomposition off (baseline)")
    p.add_argument("--frames", type=int, default=0, help="render at most N frames (0 = all)")
    p.add_argument("--fps", type=float, default=24.0, help="video frame rate (default 24)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=main)


def _supersampler(ws, self_ensemble: bool = False):
    from .. import layout as L
    from ..errors import InputError
    from ..nn.infer import SuperSampler
    if not ws.path(L.MODEL).is_file():
        raise InputError(f"{ws.path(L.MODEL)}: no trained DSRNet (run `ibr supersample {ws.root}`)")
    s = SuperSampler.load(ws, self_ensemble=self_ensemble)
    s.reset()
    return s


def _measure_supersampling(ws, model, sampler, enc, views: int = 2) -> dict:
    """Render DSRNet's validation views (capture views left out, nn/train.json) at full resolution
    and through DSRNet, against their photographs: median ms and mean PSNR of each, and the
    choice (`nn.infer.prefer_dsrnet`). Each view is rendered once untimed first (GL start-up)."""
    import json
    import time

    import numpy as np

    from .. import layout as L
    from ..io.images import read_image
    from ..metrics import psnr
    from ..nn.data import low_res_camera, supersampled_size
    from ..nn.infer import prefer_dsrnet
    cams = L.registered_cameras(ws)
    names = [n for n in json.loads(ws.path(L.TRAIN_JSON).read_text()).get("val_views", [])
             if n in cams][:views] if ws.path(L.TRAIN_JSON).is_file() else []
    names = names or list(cams)[:views]
    scene = L.posed_scene(ws)
    scale = int(getattr(sampler, "scale", 2))
    ms = {"direct": [], "dsrnet": []}
    score = {"direct": [], "dsrnet": []}
    for n in names:
        cam, photo = cams[n], read_image(ws.path(scene.view(n).image), enc)
        w, h = supersampled_size(cam.width, cam.height, scale)
        lr = low_res_camera(cam, scale)
        model.render(cam, exclude=(n,))
        for kind in ("direct", "dsrnet"):
            sampler.reset()
            t0 = time.perf_counter()
            if kind == "direct":
                img = model.render(cam, exclude=(n,)).color
            else:
                f = model.render(lr, exclude=(n,))
                img = np.asarray(sampler(f.color, f.depth, lr), np.float32)
            ms[kind].append((time.perf_counter() - t0) * 1000.0)
            score[kind].append(psnr(np.clip(img[:h, :w], 0, 1), photo[:h, :w]))
    sampler.reset()
    fig = {k: (float(np.median(ms[k])), float(np.mean(score[k]))) for k in ms}
    use, why = prefer_dsrnet(fig["direct"][0], fig["dsrnet"][0], fig["direct"][1], fig["dsrnet"][1])
    return {"use": use, "why": why, "views": names,
            **{f"{k}_ms": round(v[0], 2) for k, v in fig.items()},
            **{f"{k}_psnr": round(v[1], 3) for k, v in fig.items()}}


def read_camera_file(path: Path) -> tuple[list, bool]:
    """([(name, Camera)], is it a path) of a camera file: our cameras.json, a nerfstudio
    transforms.json (its cameras; the images need not exist) or camera_path.json (a trajectory,
    rendered as a sequence)."""
    from ..errors import InputError
    from ..io.nerfstudio import is_camera_path, is_transforms, read_camera_path, read_transforms
    from ..scene import Camera, cameras_from_json
    if not Path(path).is_file():
        raise InputError(f"{path}: camera file not found")
    if is_camera_path(path):
        return [(f"path_{i:04d}", c) for i, c in enumerate(read_camera_path(path))], True
    if is_transforms(path):
        cap = read_transforms(path, Path(path).parent, images=False)
        bent = [f.name for f in cap.frames if f.lens.distorted]
        if bent:
            raise InputError(f"{path}: frames {bent[:3]} have a distorted lens; cameras to render "
                             "must be pinhole (set k1..k4, p1, p2 to 0)")
        return [(f.name, Camera(f.lens.pinhole_K(), f.cam_from_world, f.lens.width, f.lens.height))
                for f in cap.frames], False
    return list(cameras_from_json(path).items()), False


def _to_scene_frame(ws, cams: list) -> list:
    """Cameras given in the input's frame (the poses it came with) -> the scene frame, through the
    map the poses stage recorded (docs/DESIGN.md "Scene frame")."""
    import numpy as np

    from .. import layout as L
    from ..errors import InputError
    from ..geometry.align import transform_camera
    p = ws.path(L.POSES_REPORT)
    if not p.is_file():
        raise InputError(f"{p}: no scene frame yet (run `ibr poses {ws.root}`)")
    import json
    tr = json.loads(p.read_text())["transform"]
    s, R, t = float(tr["scale"]), np.asarray(tr["R"]), np.asarray(tr["t"])
    return [(n, transform_camera(c, s, R, t)) for n, c in cams]


def main(args: argparse.Namespace) -> int:
    import json
    import logging

    import numpy as np
    from tqdm import tqdm

    from .. import layout as L
    from ..errors import InputError
    from ..io.images import write_image
    from ..runner import StageContext
    from ..scene import cameras_to_json
    from ..stages import render_views as rv
    from ..workspace import Workspace, atomic_path
    from ..render.ibr import IBRModel
    from ..render.video import write_mp4

    log = logging.getLogger("ibr_pipeline.render")
    ws = Workspace(args.workspace)
    if args.frames < 0 or not (0 < args.fps <= 240):
        raise InputError("--frames must be >= 0 and --fps in (0, 240]")
    from ..config import build_config
    cfg = build_config(rv.RenderViewsConfig, "render_views", ws.config().get("render_views", {}))
    ctx = StageContext(ws, "render_views", cfg, L.posed_scene(ws))
    enc = ctx.scene.image_encoding  # frames are stored like the photographs
    if args.cameras is not None:
        cams, sequential = read_camera_file(args.cameras)
        if args.frame == "input":
            cams = _to_scene_frame(ws, cams)
        excl, what = [None] * len(cams), "cameras"
    else:
        sets = rv.render_sets(ctx)
        key = "test" if args.heldout else "fly"
        if key not in sets:
            raise InputError(f"{ws.root}: no camera path (need >= 2 registered views)")
        cams, excl = sets[key]["cameras"], sets[key]["exclude"]
        what, sequential = ("heldout", False) if args.heldout else ("fly", True)
        if args.heldout and sets[key]["source"] == "leave_one_out":
            log.info("render: no gt/test_cameras.json: rendering every capture view left out")
    if args.frames:
        cams, excl = cams[:args.frames], excl[:args.frames]
    sampler, choice = None, None
    if args.self_ensemble and args.supersample == "off":
        raise InputError("--self-ensemble needs --supersample")
    if args.supersample == "on" or (args.supersample == "auto" and ws.path(L.MODEL).is_file()):
        sampler = _supersampler(ws, args.self_ensemble)
    elif args.supersample == "auto":
        log.info("render: no trained DSRNet (%s): rendering at full resolution", ws.path(L.MODEL))
    out = args.out or ws.path(f"{L.RENDERS}/cli_{what}")
    model = IBRModel.load(ws, layers=not args.single_layer, settings=cfg.renderer)
    from ..nn.data import low_res_camera
    if args.supersample == "auto" and sampler is not None:
        choice = _measure_supersampling(ws, model, sampler, enc)
        log.info("render: --supersample auto: %s", choice["why"])
        if not choice["use"]:
            sampler = None
    frames, rows, prev = [], [], None
    try:
        for i, ((name, cam), ex) in enumerate(tqdm(list(zip(cams, excl)), desc="render",
                                                   unit="frame", disable=args.no_progress)):
            if sampler is not None:
                scale = int(getattr(sampler, "scale", 2))
                lr = low_res_camera(cam, scale)   # odd sizes lose the last row / column
                f = model.render(lr, exclude=() if ex is None else (ex,),
                                 previous=prev if sequential else None)
                if not sequential:  # unrelated views: no previous frame (M_d = 0)
                    sampler.reset()
                color = np.asarray(sampler(f.color, f.depth, lr), dtype=np.float32)
            else:
                f = model.render(cam, exclude=() if ex is None else (ex,),
                                 previous=prev if sequential else None)
                color = f.color
            prev = f
            write_image(out / f"{i:04d}.png", color, enc)
            frames.append(color)
            rows.append({"index": i, "name": name, "ms": round(f.ms, 3), "selected": f.selected,
                         **{k: round(v, 3) for k, v in f.timings.items()}})
    finally:
        model.release()
    ms = [r["ms"] for r in rows]
    with atomic_path(out / "timings.json") as tmp:
        tmp.write_text(json.dumps({"what": what, "supersample": bool(sampler),
                                   "supersample_choice": choice,
                                   "self_ensemble": bool(sampler) and args.self_ensemble,
                                   "single_layer": args.single_layer,
                                   "median_ms": float(np.median(ms)) if ms else None,
                                   "frames": rows}, indent=1))
    with atomic_path(out / "cameras.json") as tmp:
        tmp.write_text(cameras_to_json(dict(cams)))
    if len(frames) >= 2:
        write_mp4(out / "video.mp4", frames, fps=args.fps)
    print(f"{len(frames)} frames in {out} (median {np.median(ms):.1f} ms/frame)"
          + (f", video {out / 'video.mp4'}" if len(frames) >= 2 else ""))
    return 0
