"""The local web server of `ibr view`: the static viewer page and one workspace's web bundle.

    /            viewer/static/index.html (and its scripts, under /)
    /data/...    the bundle folder (bundle.py): manifest.json, meshes, textures

Only files below those two folders are served (the standard library's handler drops `..`
components), on 127.0.0.1 by default.
"""
from __future__ import annotations

import functools
import http.server
import os
import threading
from pathlib import Path

STATIC = Path(__file__).resolve().parent / "static"


class _Handler(http.server.SimpleHTTPRequestHandler):
    data_dir: Path = Path(".")
    quiet = True

    def translate_path(self, path: str) -> str:
        # the parent maps the URL below self.directory, dropping '..' and '.' components
        bare = path.split("?", 1)[0].split("#", 1)[0]
        if bare == "/data" or bare.startswith("/data/"):
            self.directory, path = os.fspath(self.data_dir), path[len("/data"):] or "/"
        else:
            self.directory = os.fspath(STATIC)
        return super().translate_path(path)

    def end_headers(self) -> None:
        self.send_header("Cache-Control", "no-cache")
        super().end_headers()

    def log_message(self, fmt: str, *args) -> None:
        if not self.quiet:
            super().log_message(fmt, *args)


def make_server(data_dir: Path, host: str = "127.0.0.1", port: int = 8000,
                quiet: bool = True) -> http.server.ThreadingHTTPServer:
    """A server (not yet serving) for `data_dir`; port 0 picks a free port (server.server_port)."""
    handler = type("Handler", (_Handler,), {"data_dir": Path(data_dir).resolve(), "quiet": quiet})
    factory = functools.partial(handler, directory=os.fspath(STATIC))
    http.server.ThreadingHTTPServer.allow_reuse_address = True
    return http.server.ThreadingHTTPServer((host, port), factory)


def serve_in_thread(data_dir: Path, host: str = "127.0.0.1", port: int = 0):
    """(server, url) with the server running in a daemon thread (tests; `server.shutdown()`)."""
    srv = make_server(data_dir, host, port)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    return srv, f"http://{host}:{srv.server_port}/"
