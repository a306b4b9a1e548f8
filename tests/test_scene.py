"""Scene types, camera conventions and the input readers (COLMAP, cameras.json, bare images)."""
import json

import numpy as np
import pytest

from ibr_pipeline.errors import InputError
from ibr_pipeline.io.colmap import read_colmap_model, write_colmap_model
from ibr_pipeline.io.images import read_depth_png, write_depth_png, write_image
from ibr_pipeline.io.inputs import read_input
from ibr_pipeline.scene import Camera, Reflector, Scene, cameras_to_json


def _cams(n=4, w=64, h=48):
    K = Camera.intrinsics_from_fov(w, h, 60)
    rng = np.random.default_rng(0)
    return {f"img_{i:02d}.png": Camera.look_at(rng.uniform(-1, 1, 3), [0, 0, 4] + rng.uniform(-.5, .5, 3),
                                               [0, 0, 1], K, w, h) for i in range(n)}


def test_project_unproject_round_trip():
    cam = next(iter(_cams().values()))
    rng = np.random.default_rng(1)
    uv = rng.uniform([0, 0], [63, 47], (50, 2))
    depth = rng.uniform(0.5, 8, 50)
    pts = cam.unproject(uv, depth)
    uv2, z = cam.project(pts)
    np.testing.assert_allclose(uv2, uv, atol=1e-9)
    np.testing.assert_allclose(z, depth, atol=1e-9)
    # the optical axis points along +z of the camera and the centre projects to depth 0
    np.testing.assert_allclose(cam.R @ cam.viewing_direction, [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(cam.world_from_cam @ cam.cam_from_world, np.eye(4), atol=1e-12)


def test_look_at_is_upright():
    K = Camera.intrinsics_from_fov(64, 48, 60)
    cam = Camera.look_at([0, 0, 1], [0, 3, 1], [0, 0, 1], K, 64, 48)  # z-up world, looking along +y
    (u_c, v_c), = cam.project(np.array([[0, 3, 1.0]]))[0]
    (u_up, v_up), = cam.project(np.array([[0, 3, 1.5]]))[0]  # above the target: higher in the image
    (u_r, v_r), = cam.project(np.array([[0.5, 3, 1.0]]))[0]  # +x is to the right when facing +y
    assert v_up < v_c and abs(u_up - u_c) < 1e-9
    assert u_r > u_c and abs(v_r - v_c) < 1e-9


def test_outputs_are_readable_by_others(tmp_path):
    import os
    import stat

    from ibr_pipeline.workspace import atomic_path
    with atomic_path(tmp_path / "x.txt") as tmp:
        tmp.write_text("x")
    mode = stat.S_IMODE(os.stat(tmp_path / "x.txt").st_mode)
    umask = os.umask(0)
    os.umask(umask)
    assert mode == 0o666 & ~umask


def test_resized_keeps_pixel_centres():
    cam = next(iter(_cams().values()))
    half = cam.resized(32, 24)
    pts = cam.unproject(np.array([[10.0, 20.0]]), np.array([3.0]))
    uv_full, _ = cam.project(pts)
    uv_half, _ = half.project(pts)
    np.testing.assert_allclose(uv_half, (uv_full + 0.5) / 2 - 0.5, atol=1e-9)


def test_camera_rejects_bad_matrices():
    cam = next(iter(_cams().values()))
    with pytest.raises(InputError, match="NaN"):
        Camera(np.full((3, 3), np.nan), cam.cam_from_world, 64, 48)
    bad = cam.cam_from_world.copy()
    bad[:3, :3] *= 2
    with pytest.raises(InputError, match="not a proper rotation"):
        Camera(cam.K, bad, 64, 48)
    with pytest.raises(InputError, match="size must be positive"):
        Camera(cam.K, cam.cam_from_world, 0, 48)


@pytest.mark.parametrize("text", [True, False])
def test_colmap_model_round_trip(tmp_path, text):
    cams = _cams()
    write_colmap_model(cams, tmp_path / "sparse", text=text)
    back = read_colmap_model(tmp_path / "sparse")
    assert set(back) == set(cams)
    for name, cam in cams.items():
        np.testing.assert_allclose(back[name].K, cam.K, atol=1e-9)
        np.testing.assert_allclose(back[name].cam_from_world, cam.cam_from_world, atol=1e-9)
        # pycolmap projects with its own (+0.5) convention: same pixel after our conversion
        assert back[name].size == cam.size


def test_colmap_pixel_convention_matches_pycolmap(tmp_path):
    import pycolmap
    cams = _cams(1)
    write_colmap_model(cams, tmp_path / "m")
    rec = pycolmap.Reconstruction(str(tmp_path / "m"))
    image = next(iter(rec.images.values()))
    cam = cams[image.name]
    X = cam.unproject(np.array([[20.0, 30.0]]), np.array([2.5]))[0]
    uv_colmap = image.project_point(X)
    np.testing.assert_allclose(uv_colmap, [20.5, 30.5], atol=1e-6)


def _write_input(root, cams, depth=True, fmt="colmap"):
    for name, cam in cams.items():
        write_image(root / "images" / name, np.random.default_rng(0).random((cam.height, cam.width, 3)))
        if depth:
            write_depth_png(root / "depth" / name, np.full((cam.height // 2, cam.width // 2), 2.0))
    if fmt == "colmap":
        write_colmap_model(cams, root / "sparse" / "0")
    elif fmt == "json":
        (root / "cameras.json").write_text(cameras_to_json(cams))
    (root / "gt").mkdir(exist_ok=True)
    write_image(root / "gt" / "not_a_view.png", np.zeros((4, 4, 3)))


@pytest.mark.parametrize("fmt", ["colmap", "json", "images"])
def test_read_input_layouts(tmp_path, fmt):
    cams = _cams()
    _write_input(tmp_path, cams, fmt=fmt)
    scene = read_input(tmp_path)
    assert scene.names == sorted(cams)
    assert scene.source == {"colmap": "colmap", "json": "cameras.json", "images": "images"}[fmt]
    assert all(v.depth == f"input/depth/{v.name}" for v in scene.views)
    if fmt == "images":
        assert scene.posed_views == []
    else:
        for v in scene.views:
            np.testing.assert_allclose(v.camera.cam_from_world, cams[v.name].cam_from_world, atol=1e-9)
    again = Scene.from_json(scene.to_json())
    assert again.names == scene.names and again.source == scene.source


def test_depth_png_is_millimetres(tmp_path):
    d = np.array([[0.0, 1.2345, np.nan], [70.0, -1.0, 2.0]])
    write_depth_png(tmp_path / "d.png", d)
    back = read_depth_png(tmp_path / "d.png")
    np.testing.assert_allclose(back, [[0, 1.234, 0], [0, 0, 2.0]], atol=1e-6)  # 1 mm steps; invalid -> 0


def test_png_round_trip_keeps_every_pixel_and_channel_order(tmp_path):
    """write_image's PNGs read back by PIL (an independent decoder) as the same 8-bit values, in
    RGB(A) order: grey, RGB, RGBA, and 16-bit depth in millimetres."""
    from PIL import Image
    rng = np.random.default_rng(0)
    for shape in [(7, 5), (7, 5, 3), (7, 5, 4)]:
        a = rng.integers(0, 256, shape, dtype=np.uint8)
        a[0, 0] = 255 if a.ndim == 2 else [255, 0, 0, 255][:shape[2]]   # pure red: not BGR
        write_image(tmp_path / "a.png", a)
        np.testing.assert_array_equal(np.asarray(Image.open(tmp_path / "a.png")), a)
    mm = rng.integers(0, 65536, (6, 9)).astype(np.float64)
    write_depth_png(tmp_path / "d.png", mm / 1000.0)
    np.testing.assert_array_equal(np.asarray(Image.open(tmp_path / "d.png")).astype(np.int64),
                                  mm.astype(np.int64))


def test_reflectors_parse_and_validate(tmp_path):
    r = Reflector.from_dict({"name": "m", "plane": [0, 2, 0, -4], "beta": 0.5}, "r")
    np.testing.assert_allclose(r.plane, [0, 1, 0, -2])
    assert r.material is None and Reflector.from_dict(r.to_dict(), "r") == r
    m = Reflector.from_dict({"plane": [1, 0, 0, 0], "material": "mirror"}, "r")
    assert m.beta == 1.0 and m.material == "mirror"  # a mirror reflects everything
    g = Reflector.from_dict({"plane": [1, 0, 0, 0], "material": "glass", "beta": 0.08}, "r")
    assert g.beta == 0.08 and g.to_dict()["material"] == "glass"
    for bad, msg in [({"plane": [0, 0, 0, 1]}, "normal is zero"), ({"plane": [1, 2]}, "4 finite"),
                     ({"plane": [0, 0, 1, 0], "beta": 2}, "beta"), ({}, "needs a 'plane'"),
                     ({"plane": [0, 0, 1, 0], "material": "chrome"}, "material")]:
        with pytest.raises(InputError, match=msg):
            Reflector.from_dict(bad, "reflectors.json: reflector 0")
    cams = _cams()
    _write_input(tmp_path, cams)
    (tmp_path / "reflectors.json").write_text(json.dumps({"reflectors": [{"plane": [1, 0, 0, 1]}]}))
    assert len(read_input(tmp_path).reflectors) == 1
    (tmp_path / "reflectors.json").write_text("{not json")
    with pytest.raises(InputError, match="reflectors.json: cannot read reflectors"):
        read_input(tmp_path)


def test_colmap_model_naming_unknown_image_is_an_error(tmp_path):
    cams = _cams()
    _write_input(tmp_path, cams)
    (tmp_path / "images" / "img_00.png").unlink()
    with pytest.raises(InputError, match="refers to images not in"):
        read_input(tmp_path)


def test_registered_cameras_are_read_once_per_file_version_and_handed_out_as_copies(tmp_path):
    from ibr_pipeline import layout as L
    from ibr_pipeline.workspace import Workspace
    ws = Workspace(tmp_path)
    p = ws.path(L.REGISTERED_CAMERAS)
    with pytest.raises(InputError, match="no registered cameras"):
        L.registered_cameras(ws)
    p.parent.mkdir(parents=True)
    cams = _cams(4)
    p.write_text(cameras_to_json(cams))
    a, b = L.registered_cameras(ws), L.registered_cameras(ws)
    assert list(a) == list(cams) and all(np.array_equal(a[n].K, cams[n].K) for n in cams)
    a[next(iter(a))].K[0, 0] = -1.0   # a caller writing into its copy changes nobody else's
    a.clear()
    assert list(b) == list(cams) == list(L.registered_cameras(ws))
    assert L.registered_cameras(ws)[next(iter(cams))].K[0, 0] > 0
    tmp = p.with_suffix(".tmp")       # replaced (as the workspace writes files): read again
    tmp.write_text(cameras_to_json(dict(list(cams.items())[:2])))
    tmp.replace(p)
    assert list(L.registered_cameras(ws)) == list(cams)[:2]
