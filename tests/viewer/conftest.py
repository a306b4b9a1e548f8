"""Fixtures of the browser-viewer tests: a two-layer workspace, its web bundle served on
127.0.0.1, and Debian's headless Chromium driven by Playwright (software WebGL: SwiftShader)."""
import base64
import io

import numpy as np
import pytest


@pytest.fixture(scope="module")
def layered_ws(tiny_scene, tmp_path_factory):
    """The tiny scene (8 views, 160x120, a mirror) with ground-truth stages through reflection:
    per-view meshes and two layers, fuzzy visibility (no global report)."""
    from ibr_pipeline.gt_workspace import write_gt_workspace
    ws = tmp_path_factory.mktemp("viewer") / "ws"
    write_gt_workspace(tiny_scene[0], ws, "reflection", global_mesh="none")
    return ws


class Page:
    """A viewer page on a served bundle, with the helpers the tests need."""

    def __init__(self, page, url):
        self.page, self.url = page, url
        self.errors: list[str] = []
        page.on("pageerror", lambda e: self.errors.append(str(e)))

    def open(self, query: str = "?frusta=0&prefetch=0", timeout_ms: int = 120_000):
        self.page.goto(self.url + query)
        self.page.wait_for_function("window.ibr !== undefined && (window.ibr.error || "
                                    "window.ibr.firstFrame)", timeout=timeout_ms)
        err = self.page.evaluate("window.ibr.error || null")
        assert err is None and not self.errors, (err, self.errors)
        return self

    def render(self, cam: dict, **opts) -> dict:
        return self.page.evaluate("async ([c, o]) => await window.ibr.renderCamera(c, o)",
                                  [cam, opts])

    def canvas(self) -> np.ndarray:
        """The canvas's pixels (H, W, 3) uint8: what the page shows, at the camera's size."""
        from PIL import Image
        url = self.page.evaluate("document.getElementById('view').toDataURL('image/png')")
        png = base64.b64decode(url.split(",", 1)[1])
        return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))


@pytest.fixture
def open_viewer(browser):
    """open_viewer(bundle_dir) -> Page served from a local server (stopped after the test)."""
    from ibr_pipeline.viewer.server import serve_in_thread
    servers, contexts = [], []

    def make(bundle, viewport=(900, 640)):
        srv, url = serve_in_thread(bundle)
        servers.append(srv)
        ctx = browser.new_context(viewport={"width": viewport[0], "height": viewport[1]},
                                  accept_downloads=True)
        contexts.append(ctx)
        return Page(ctx.new_page(), url)

    yield make
    for c in contexts:
        c.close()
    for s in servers:
        s.shutdown()
        s.server_close()
