"""The viewer's web bundle, its server, `ibr view` and `ibr export --web` (no browser)."""
import http.client
import json
import os
import shutil

import numpy as np
import pytest

from ibr_pipeline import layout as L
from ibr_pipeline.cli import main
from ibr_pipeline.io.images import read_image
from ibr_pipeline.io.mesh import read_ply
from ibr_pipeline.render import shaders
from ibr_pipeline.render.ibr import load_view
from ibr_pipeline.viewer.bundle import (
    bundle_is_current,
    render_settings,
    webgl_shader,
    write_bundle,
)
from ibr_pipeline.viewer.server import serve_in_thread
from ibr_pipeline.workspace import Workspace


@pytest.fixture(scope="module")
def bundle(layered_ws):
    out = write_bundle(Workspace(layered_ws), progress=False)
    return out, json.loads((out / "manifest.json").read_text())


def test_bundle_holds_the_offline_renderers_layers(layered_ws, bundle):
    out, man = bundle
    ws = Workspace(layered_ws)
    cams = L.registered_cameras(ws)
    assert [v["name"] for v in man["views"]] == [n for n in ws.scene().names if n in cams]
    s = render_settings(ws)
    assert man["settings"]["visibility"] == s.visibility == "fuzzy"  # no global report: RGB-D
    layered = [v for v in man["views"] if "reflection" in v["layers"]]
    assert layered, "the tiny scene's mirror gives some views two layers"
    v = layered[0]
    data = load_view(ws, v["name"], cams[v["name"]], ws.scene().view(v["name"]).image, True, s,
                     ws.scene().image_encoding).layers
    m0 = read_ply(ws.path(L.view_file(v["name"], L.M0)))
    pos = np.fromfile(out / v["layers"]["surface"]["pos"], "<f4").reshape(-1, 3)
    idx = np.fromfile(out / v["layers"]["surface"]["idx"], "<u4").reshape(-1, 3)
    assert np.array_equal(pos, m0.vertices.astype(np.float32)) and np.array_equal(idx, m0.faces)
    aux = read_image(out / v["layers"]["surface"]["aux"])  # 8-bit, linear values
    assert np.abs(aux[..., 0] ** 2 - data[0].alpha).max() < 2.5 / 255  # sqrt-coded alpha
    assert aux[..., 0].min() > 0, "the 1e-3 weight floor survives 8 bits"
    assert np.abs(aux[..., 1] - data[0].beta).max() <= 0.5 / 255 + 1e-6
    rgb = read_image(out / v["layers"]["reflection"]["rgb"], ws.scene().image_encoding)
    assert np.abs(rgb - data[1].rgb).max() < 1.0 / 255
    plain = [v for v in man["views"] if "reflection" not in v["layers"]]
    for v in plain:  # a view without a reflector is its single layer in the two-layer model
        assert v["layers"]["surface"] == v["layers"]["single"]


def test_webgl_shaders_are_the_offline_ones_with_an_es_header():
    for name in ("VERTEX", "COST", "FRONT", "BLEND", "SINGLE"):
        src = getattr(shaders, name)
        es = webgl_shader(src)
        assert es.startswith("#version 300 es\n") and "#version 330" not in es
        body = src.split("void main()")[-1]  # main() is the offline one, textures rewritten
        assert es.split("void main()")[-1] == body.replace("texture(tex_rgba, uv)", "ibr_rgba(uv)"
                                                           ).replace("texture(tex_beta, uv).r",
                                                                     "texture(tex_aux, uv).g")
        head = src.split("void main()")[0].split("\n", 2)[2]  # after the version line
        assert head.strip() in es
    with pytest.raises(ValueError):
        webgl_shader("#version 410\nvoid main() {}")
    with pytest.raises(ValueError):
        webgl_shader("#version 330\nuniform sampler2D tex_rgba;\n"
                     "void main() { texture(tex_rgba, p); }")


def test_bundle_is_rebuilt_when_a_source_changes(layered_ws, tmp_path):
    ws_dir = tmp_path / "ws"
    shutil.copytree(layered_ws, ws_dir, ignore=shutil.ignore_patterns("export"))
    ws = Workspace(ws_dir)
    out = write_bundle(ws, progress=False)
    assert bundle_is_current(ws, out)
    name = next(iter(L.registered_cameras(ws)))
    mesh = ws.path(L.view_file(name, L.MESH))
    t = mesh.stat().st_mtime - 10  # the bundle predates a rewritten mesh
    os.utime(out / "manifest.json", (t, t))
    assert not bundle_is_current(ws, out)
    (out / "marker").write_text("old bundle")
    write_bundle(ws, out, progress=False)
    assert bundle_is_current(ws, out) and not (out / "marker").exists()
    assert not [p for p in out.parent.iterdir() if p.name.startswith(".web-")]  # no staging left


def test_a_failed_bundle_leaves_the_previous_one(layered_ws, tmp_path):
    ws_dir = tmp_path / "ws"
    shutil.copytree(layered_ws, ws_dir, ignore=shutil.ignore_patterns("export"))
    ws = Workspace(ws_dir)
    out = write_bundle(ws, progress=False)
    before = sorted(p.name for p in out.iterdir())
    name = list(L.registered_cameras(ws))[-1]
    ws.path(L.view_file(name, L.MESH)).unlink()
    assert main(["export", str(ws_dir), "--web", "--no-progress"]) == 2
    assert sorted(p.name for p in out.iterdir()) == before


def test_server_serves_the_page_and_the_bundle_only(bundle):
    out, _ = bundle
    srv, url = serve_in_thread(out)
    try:
        def get(path):
            c = http.client.HTTPConnection("127.0.0.1", srv.server_port, timeout=10)
            c.request("GET", path)
            r = c.getresponse()
            return r.status, r.read()
        status, body = get("/")
        assert status == 200 and b"main.js" in body
        status, body = get("/data/manifest.json")
        assert status == 200 and json.loads(body)["format"] == "ibr-web-bundle"
        for bad in ("/data/../../ibr.toml", "/../ibr.toml", "/data/%2e%2e/%2e%2e/ibr.toml",
                    "/../../../../etc/passwd"):
            assert get(bad)[0] == 404, bad
    finally:
        srv.shutdown()
        srv.server_close()


def test_cli_errors_are_one_line_exit_2(layered_ws, tmp_path, capsys):
    assert main(["view", str(layered_ws), "--port", "70000"]) == 2
    assert "--port" in capsys.readouterr().err
    assert main(["export", str(layered_ws), "--web", "--views", "x"]) == 2
    assert "--views" in capsys.readouterr().err
    assert main(["view", str(tmp_path)]) == 2
    assert "not a workspace" in capsys.readouterr().err


def test_export_web_writes_the_bundle(layered_ws, tmp_path, capsys):
    assert main(["export", str(layered_ws), "--web", "--out", str(tmp_path / "e"),
                 "--no-progress"]) == 0
    assert (tmp_path / "e" / "web" / "manifest.json").is_file()
    assert "web/" in capsys.readouterr().out


def test_ibr_view_prints_its_url_serves_and_stops_on_ctrl_c(layered_ws, tmp_path):
    import re
    import signal
    import subprocess
    import sys
    import urllib.request
    ws_dir = tmp_path / "ws"
    shutil.copytree(layered_ws, ws_dir, ignore=shutil.ignore_patterns("export"))
    # SIGINT as a terminal delivers it: a suite started in the background by a non-interactive
    # shell (`sh -c "make test" &`) passes SIGINT on ignored, and Python then installs no handler
    p = subprocess.Popen([sys.executable, "-m", "ibr_pipeline", "view", str(ws_dir), "--port", "0",
                          "--no-progress"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        lines = [p.stdout.readline(), p.stdout.readline()]
        assert "web bundle written" in lines[0]
        url = re.search(r"http://127\.0\.0\.1:\d+/", lines[1]).group(0)
        with urllib.request.urlopen(url + "data/manifest.json", timeout=10) as r:
            assert json.loads(r.read())["views"]
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=20)
        assert p.returncode == 0 and "stopped" in out, err
    finally:
        if p.poll() is None:
            p.kill()


def test_bundle_takes_the_settings_render_views_rendered_with(layered_ws, tmp_path):
    """`ibr run --set render_views.renderer.*` is not written to ibr.toml: the bundle follows
    renders/settings.json, which render_views writes, and rebuilds when it changes."""
    import dataclasses
    ws_dir = tmp_path / "ws"
    shutil.copytree(layered_ws, ws_dir)
    ws = Workspace(ws_dir)
    assert render_settings(ws).per_view_max == 4  # no render_views yet: ibr.toml's (defaults)
    out = write_bundle(ws, progress=False)
    assert bundle_is_current(ws, out)
    ran = dataclasses.replace(render_settings(ws), per_view_max=2, delta=0.05)
    ws.write_json(L.RENDER_SETTINGS, dataclasses.asdict(ran))
    t = (out / "manifest.json").stat().st_mtime + 1
    os.utime(ws.path(L.RENDER_SETTINGS), (t, t))
    assert render_settings(ws) == ran
    assert not bundle_is_current(ws, out)
    man = json.loads((write_bundle(ws, progress=False) / "manifest.json").read_text())
    assert (man["settings"]["per_view_max"], man["settings"]["delta"]) == (2, 0.05)
