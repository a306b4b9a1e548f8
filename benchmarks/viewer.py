"""The browser viewer on one workspace, in headless Chromium (software WebGL2, SwiftShader, on the
CPU): bundle size and export time, page load (first frame, every view resident), frame time
along the fly-through against the offline renderer's in the same run, and the agreement of the
two renderers on the held-out cameras (PSNR of the page's canvas against the offline frame).

    ibr bench viewer WS [--frames N] [--out FILE]

Both renderers draw the same cameras with the same selection (hysteresis along the path); each
is timed on a second pass (the first compiles shaders and uploads textures). Frame times are
medians; the ratio browser / offline is of medians measured in this run, on this machine.
"""
from __future__ import annotations

import base64
import io
import json
import time
from pathlib import Path

import numpy as np


def add_arguments(p) -> None:
    p.add_argument("workspace", type=Path, help="a workspace after view_mesh (and reflection)")
    p.add_argument("--frames", type=int, default=48, help="fly-through frames to time (default 48)")
    p.add_argument("--out", type=Path, help="results JSON (default WS/bench/viewer.json)")


def _canvas(page) -> np.ndarray:
    from PIL import Image
    url = page.evaluate("document.getElementById('view').toDataURL('image/png')")
    return np.asarray(Image.open(io.BytesIO(base64.b64decode(url.split(",", 1)[1]))).convert("RGB"))


def _camera(c: dict):
    from ibr_pipeline.scene import Camera
    return Camera(np.array(c["K"]), np.vstack([np.array(c["cam_from_world"]), [0, 0, 0, 1]]),
                  c["width"], c["height"])


def main(args) -> int:
    from playwright.sync_api import sync_playwright
    from tqdm import tqdm

    from ibr_pipeline.errors import InputError
    from ibr_pipeline.io.images import linear_to_srgb
    from ibr_pipeline.render.ibr import IBRModel
    from ibr_pipeline.viewer.browser import launch
    from ibr_pipeline.viewer.bundle import render_settings, write_bundle
    from ibr_pipeline.viewer.server import serve_in_thread
    from ibr_pipeline.workspace import Workspace

    if not (args.workspace / "ibr.toml").is_file():
        raise InputError(f"{args.workspace}: not a workspace (no ibr.toml)")
    ws = Workspace(args.workspace)
    t0 = time.perf_counter()
    out = write_bundle(ws, progress=True)
    export_s = time.perf_counter() - t0
    man = json.loads((out / "manifest.json").read_text())
    size_mb = sum(f.stat().st_size for f in out.iterdir()) / 2 ** 20
    fly = man.get("fly", [])[:args.frames]
    held = man.get("heldout", [])
    model = IBRModel.load(ws, settings=render_settings(ws))
    res = {"workspace": str(ws.root), "views": len(man["views"]),
           "size": [man["views"][0]["width"], man["views"][0]["height"]],
           "visibility": man["settings"]["visibility"], "bundle_mb": size_mb, "export_s": export_s}
    srv, url = serve_in_thread(out)
    try:
        with sync_playwright() as p:
            b = launch(p)
            page = b.new_page(viewport={"width": 1280, "height": 800})
            errors = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            t1 = time.perf_counter()
            page.goto(url + "?frusta=0")
            page.wait_for_function("window.ibr !== undefined && (window.ibr.error || "
                                   "window.ibr.firstFrame)", timeout=300_000)
            if errors or page.evaluate("window.ibr.error || null"):
                why = errors or page.evaluate("window.ibr.error")
                raise RuntimeError(f"viewer page failed: {why}")
            res["first_frame_s"] = page.evaluate("window.ibr.loadMs") / 1e3
            res["page_open_s"] = time.perf_counter() - t1
            res["all_views_s"] = page.evaluate("window.ibr.prefetched") / 1e3
            res["resident_mb"] = page.evaluate("window.ibr.stats().bytes") / 2 ** 20
            ms_web, ms_off = [], []
            for rep in range(2):
                prev, web, off = None, [], []
                for cam in tqdm(fly, desc=f"fly-through pass {rep + 1}", unit="frame", leave=False):
                    web.append(page.evaluate("async (c) => (await window.ibr.renderCamera(c, "
                                             "{sequence: true})).ms", cam))
                    f = model.render(_camera(cam), previous=prev)
                    prev = f
                    off.append(f.ms)
                ms_web, ms_off = web, off
            psnr = []
            for cam in held:
                page.evaluate("async (c) => await window.ibr.renderCamera(c)", cam)
                shot = _canvas(page).astype(np.float64)
                ref = np.rint(linear_to_srgb(model.render(_camera(cam)).color) * 255)
                psnr.append(float(10 * np.log10(255 ** 2 / max(np.mean((shot - ref) ** 2), 1e-12))))
            b.close()
    finally:
        srv.shutdown()
        srv.server_close()
        model.release()
    if ms_web:
        res.update({"fly_frames": len(fly), "browser_median_ms": float(np.median(ms_web)),
                    "offline_median_ms": float(np.median(ms_off)),
                    "browser_over_offline": float(np.median(ms_web) / np.median(ms_off))})
    if psnr:
        res.update({"heldout_cameras": len(psnr), "agreement_psnr_min": min(psnr),
                    "agreement_psnr_median": float(np.median(psnr))})
    path = args.out or ws.path("bench/viewer.json")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(res, indent=1))
    print(f"viewer bench: {path}")
    for k, v in res.items():
        print(f"  {k:<22} {v:.3f}" if isinstance(v, float) else f"  {k:<22} {v}")
    return 0
