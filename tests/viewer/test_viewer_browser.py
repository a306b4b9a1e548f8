"""The browser viewer in headless Chromium (software WebGL2) against the offline renderer.

The page renders a camera with the bundle's meshes and textures through the WebGL2 port of
render/ibr.py; the offline frame of the same camera (IBRModel, moderngl on Mesa) is the
reference. Same pixels by a different rasteriser: PSNR >= 30 dB on the whole frame (holes and
their push-pull fill included), the same selected views, Eq. 3 holding between the layer modes,
and key frames that come back from `camera_path.json` as the cameras they were recorded at."""
import dataclasses
import json
import os
import shutil

import numpy as np
import pytest

from ibr_pipeline.cli import main
from ibr_pipeline.io.images import linear_to_srgb, srgb_to_linear
from ibr_pipeline.render.ibr import IBRModel
from ibr_pipeline.scene import Camera
from ibr_pipeline.viewer.bundle import render_settings, write_bundle
from ibr_pipeline.workspace import Workspace

PSNR_MIN = 30.0


def camera(c: dict) -> Camera:
    return Camera(np.array(c["K"]), np.vstack([np.array(c["cam_from_world"]), [0, 0, 0, 1]]),
                  c["width"], c["height"])


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float(10 * np.log10(255.0 ** 2 / max(mse, 1e-12)))


def offline(model: IBRModel, cam: dict, previous=None):
    """The offline frame as the page displays it: sRGB, 8 bits."""
    f = model.render(camera(cam), previous=previous)
    return np.rint(linear_to_srgb(f.color) * 255).astype(np.uint8), f


@pytest.fixture(scope="module")
def bundle(layered_ws):
    out = write_bundle(Workspace(layered_ws), progress=False)
    return out, json.loads((out / "manifest.json").read_text())


@pytest.fixture(scope="module")
def model(layered_ws):
    ws = Workspace(layered_ws)
    m = IBRModel.load(ws, settings=render_settings(ws))
    yield m
    m.release()


def test_capture_and_heldout_cameras_match_the_offline_renderer(bundle, model, open_viewer,
                                                                tmp_path):
    out, man = bundle
    assert man["heldout"], "the tiny scene has held-out cameras (gt/test_cameras.json)"
    page = open_viewer(out).open()
    times = {}
    for cam in (man["views"][3], man["heldout"][0]):
        r = page.render(cam)
        shot = page.canvas()
        ref, f = offline(model, cam)
        assert shot.shape == ref.shape == (cam["height"], cam["width"], 3)
        assert r["selected"] == f.selected
        assert psnr(shot, ref) >= PSNR_MIN, (cam["name"], psnr(shot, ref))
        assert np.isfinite(r["ms"]) and r["ms"] > 0
        times[cam["name"]] = {"ms": r["ms"], "psnr": psnr(shot, ref)}
    (tmp_path / "frame_times.json").write_text(json.dumps(times, indent=1))
    print("browser frames:", times)


def test_single_layer_mode_matches_the_offline_baseline(layered_ws, bundle, open_viewer):
    out, man = bundle
    ws = Workspace(layered_ws)
    base = IBRModel.load(ws, layers=False, settings=render_settings(ws))
    try:
        page = open_viewer(out).open()
        cam = man["heldout"][1]
        page.render(cam, mode="single")
        ref, _ = offline(base, cam)
        assert psnr(page.canvas(), ref) >= PSNR_MIN
    finally:
        base.release()


def test_layer_modes_add_up_to_the_composite(bundle, model, open_viewer):
    """Eq. 3 on screen: linear(I0 + beta I1) = linear(I0) + linear(beta I1), up to 8 bits."""
    out, man = bundle
    page = open_viewer(out).open()
    layered = [v for v in man["views"] if "reflection" in v["layers"]]
    cam = max(layered, key=lambda v: offline(model, v)[1].beta.mean())
    refl = offline(model, cam)[1].beta > 0.2
    assert refl.mean() > 0.01, "the tiny scene's mirror is in view"
    shots = {}
    for mode in ("composite", "surface", "reflection"):
        page.render(cam, mode=mode)
        shots[mode] = srgb_to_linear(page.canvas() / 255.0)
    total = shots["surface"] + shots["reflection"]
    ok = total.max(-1) < 0.98  # clipped pixels cannot add up
    assert np.abs(shots["composite"] - total)[ok].mean() < 0.005
    assert np.abs(shots["composite"] - shots["surface"])[refl & ok].mean() > 0.02


def test_selection_with_hysteresis_matches_along_the_fly_through(bundle, model, open_viewer):
    out, man = bundle
    page = open_viewer(out).open()
    prev_js, prev_py = None, None
    for cam in man["fly"][:24]:
        names = page.page.evaluate("([c, p]) => window.ibr.select(c, p)", [cam, prev_js])
        sel, _ = model.select(camera(cam), previous=prev_py)
        assert names == [model.names[k] for k in sel]
        idx = [page.page.evaluate("window.ibr.names").index(n) for n in names]
        c = camera(cam)
        prev_js = {"R": c.R.tolist(), "center": c.center.tolist(), "selected": idx}

        class Prev:  # what IBRModel.select reads of the previous frame
            camera, selected = c, names
        prev_py = Prev


def test_per_view_visibility_matches_too(tiny_scene, layered_ws, tmp_path, open_viewer):
    ws_dir = tmp_path / "ws"
    shutil.copytree(layered_ws, ws_dir)
    with open(ws_dir / "ibr.toml", "a") as f:
        f.write('\n[render_views.renderer]\nvisibility = "per_view"\n')
    ws = Workspace(ws_dir)
    assert render_settings(ws).visibility == "per_view"
    out = write_bundle(ws, progress=False)
    man = json.loads((out / "manifest.json").read_text())
    m = IBRModel.load(ws, settings=render_settings(ws))
    try:
        page = open_viewer(out).open()
        cam = man["heldout"][-1]
        r = page.render(cam)
        ref, f = offline(m, cam)
        assert r["selected"] == f.selected and len(f.selected) <= m.settings.per_view_max
        assert psnr(page.canvas(), ref) >= PSNR_MIN
    finally:
        m.release()


def test_key_frames_become_a_camera_path_that_ibr_render_reads(layered_ws, bundle, open_viewer,
                                                               tmp_path):
    from ibr_pipeline.io.nerfstudio import read_camera_path
    out, man = bundle
    page = open_viewer(out).open("?frusta=1")
    p = page.page
    for _ in range(3):  # next capture camera, key frame: views 1, 2, 3
        p.keyboard.press("n")
        p.keyboard.press("k")
    assert p.locator("#keys").inner_text() == "3"
    with p.expect_download() as dl:
        p.locator("[data-key=x]").click()
    path = tmp_path / "camera_path.json"
    dl.value.save_as(path)
    cams = read_camera_path(path)
    assert len(cams) == 2 * 2 * 24 + 1  # 2 intervals x 2 s x 24 fps, both ends
    for cam, view in ((cams[0], man["views"][1]), (cams[-1], man["views"][3])):
        ref = camera(view)
        assert np.allclose(cam.center, ref.center, atol=1e-5)
        assert np.allclose(cam.R, ref.R, atol=1e-5)
    mid = camera(man["views"][2])
    assert min(np.linalg.norm(c.center - mid.center) for c in cams) < 1e-5  # through key 2
    steps = np.linalg.norm(np.diff([c.center for c in cams], axis=0), axis=1)
    assert steps.max() < 3 * np.median(steps)  # smooth: no jumps
    assert main(["render", str(layered_ws), "--cameras", str(path), "--frames", "3",
                 "--out", str(tmp_path / "r"), "--no-progress"]) == 0
    assert len(list((tmp_path / "r").glob("*.png"))) == 3


def test_navigation_keeps_the_image_upright(bundle, open_viewer):
    """Leaving a capture camera for free navigation keeps its viewing direction and up."""
    out, man = bundle
    page = open_viewer(out).open()
    for view in man["views"][:4]:
        page.page.evaluate("(n) => window.ibr.goTo(n)", view["name"])
        nav = np.array(page.page.evaluate("window.ibr.navCamera().R"))
        R = np.array(view["cam_from_world"])[:, :3]
        assert nav[2] @ R[2] > 0.9999                 # same optical axis
        assert nav[1] @ R[1] > 0.9                    # image y still points down
        assert abs(np.linalg.det(nav) - 1) < 1e-9


def test_page_screenshot_shows_the_view_and_the_frame_time(layered_ws, open_viewer, tmp_path):
    """The viewer as a person sees it (docs/figures/viewer.png is this test's screenshot of the
    demo: IBR_VIEWER_WS=out/demo IBR_VIEWER_SCREENSHOT=docs/figures/viewer.png)."""
    ws = Workspace(os.environ.get("IBR_VIEWER_WS", layered_ws))
    out = write_bundle(ws, tmp_path / "web", progress=False)
    page = open_viewer(out, viewport=(1100, 560)).open("?frusta=1")
    p = page.page
    p.keyboard.press("n")
    p.keyboard.down("s")  # walk back: the neighbouring views' frusta come into sight
    p.wait_for_timeout(700)
    p.keyboard.up("s")
    p.wait_for_timeout(500)
    assert "ms" in p.locator("#ms").inner_text()
    assert p.locator("#sel").inner_text().strip() not in ("", "-")
    shot = tmp_path / "viewer.png"
    p.screenshot(path=str(shot))
    target = os.environ.get("IBR_VIEWER_SCREENSHOT")
    if target:
        shutil.copy(shot, target)
    from PIL import Image
    img = np.asarray(Image.open(shot).convert("RGB")).astype(int)
    canvas = p.locator("#view").bounding_box()
    x0, y0 = int(canvas["x"]), int(canvas["y"])
    region = img[y0 + 5:y0 + int(canvas["height"]) - 5, x0 + 5:x0 + int(canvas["width"]) - 5]
    assert region.std() > 10, "the canvas shows a picture, not a flat colour"
    r, g, b = region[..., 0], region[..., 1], region[..., 2]
    frusta = (r > 200) & (g > 100) & (g < 170) & (b < 60)
    assert frusta.sum() > 10, "the selected views' frusta (orange) are drawn"


def test_srgb_photographs_blend_as_stored_as_offline(tiny_scene, tmp_path, open_viewer):
    """An sRGB scene: the page blends the stored sRGB values and decodes before Eq. 3, as the
    offline renderer does (RenderSettings.blend_space = stored); linear blending differs."""
    from scene_copies import srgb_copy
    from ibr_pipeline.gt_workspace import write_gt_workspace
    ws_dir = tmp_path / "ws"
    write_gt_workspace(srgb_copy(tiny_scene[0], tmp_path / "scene"), ws_dir, "reflection",
                       global_mesh="none")
    ws = Workspace(ws_dir)
    s = render_settings(ws)
    assert ws.scene().image_encoding == "srgb" and s.blend_space == "stored"
    out = write_bundle(ws, progress=False)
    man = json.loads((out / "manifest.json").read_text())
    models = {b: IBRModel.load(ws, settings=dataclasses.replace(s, blend_space=b))
              for b in ("stored", "linear")}
    try:
        page = open_viewer(out).open()
        cam = man["heldout"][0]
        page.render(cam)
        shot = page.canvas()
        ref = {b: offline(m, cam)[0] for b, m in models.items()}
        assert psnr(shot, ref["stored"]) >= PSNR_MIN
        a, b = (ref[k].astype(np.int16) for k in ("stored", "linear"))
        differ = np.abs(a - b).max(-1) > 2  # where the two blending spaces give other pixels
        assert differ.mean() > 0.005
        err = {k: np.abs(shot.astype(np.int16) - ref[k].astype(np.int16))[differ].mean()
               for k in ref}
        assert err["stored"] < 0.5 * err["linear"], err
    finally:
        for m in models.values():
            m.release()
