"""`ibr view WS [--port N] [--host H] [--rebuild]`: walk through a workspace in the browser.

Writes (or reuses, when it is newer than everything it was made from) the web bundle
WS/export/web (viewer/bundle.py), then serves it with the WebGL2 viewer (viewer/static) on
http://127.0.0.1:PORT/ until Ctrl-C. Light at import time.
"""
from __future__ import annotations

import argparse
from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser("view", help="serve an interactive two-layer IBR viewer of a workspace "
                       "in the browser (WebGL2)",
                       description="Render the workspace's per-view two-layer meshes live in the "
                       "browser, with the same view selection, fuzzy depth test and blending as "
                       "`ibr render`; record camera paths for `ibr render --cameras`.")
    p.add_argument("workspace", type=Path, help="workspace folder (after render_views' inputs "
                   "exist: view_mesh, and reflection for two layers)")
    p.add_argument("--port", type=int, default=8000, help="port (default 8000; 0 = any free one)")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1: "
                   "this machine only)")
    p.add_argument("--rebuild", action="store_true", help="rewrite the web bundle even when it is "
                   "up to date")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    import time

    from ..errors import InputError
    from ..viewer.bundle import bundle_is_current, write_bundle
    from ..viewer.server import make_server
    from ..workspace import Workspace

    if not 0 <= args.port <= 65535:
        raise InputError(f"--port must be in 0..65535, got {args.port}")
    if not (args.workspace / "ibr.toml").is_file():
        raise InputError(f"{args.workspace}: not a workspace (no ibr.toml; make one with "
                         f"`ibr run {args.workspace} --input PHOTOS`)")
    ws = Workspace(args.workspace)
    out = ws.path("export/web")
    if args.rebuild or not bundle_is_current(ws, out):
        t0 = time.perf_counter()
        write_bundle(ws, out, progress=not args.no_progress)
        print(f"view: web bundle written to {out} in {time.perf_counter() - t0:.1f} s")
    try:
        srv = make_server(out, args.host, args.port)
    except OSError as e:
        raise InputError(f"--port {args.port}: cannot listen on {args.host} ({e.strerror}); "
                         "pick another with --port, or --port 0 for any free one") from None
    url = f"http://{args.host}:{srv.server_port}/"
    print(f"view: open {url} in a browser (WebGL2); Ctrl-C stops the server", flush=True)
    try:
        srv.serve_forever()
    except KeyboardInterrupt:
        print("view: stopped")
    finally:
        srv.server_close()
    return 0
