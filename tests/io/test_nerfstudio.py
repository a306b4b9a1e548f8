"""io/nerfstudio.py: transforms.json and camera_path.json, read and written."""
import json
import math
from pathlib import Path

import numpy as np
import pytest

from ibr_pipeline.errors import InputError
from ibr_pipeline.io.nerfstudio import (is_camera_path, is_transforms, read_camera_path,
                                        read_transforms, write_camera_path, write_transforms)
from ibr_pipeline.scene import Camera, cameras_from_json

SAMPLE = Path(__file__).parents[2] / "sample_data" / "mirror_room" / "cameras.json"


def touch_images(root: Path, rels) -> None:
    for rel in rels:  # the reader checks the files exist; it does not decode them
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_bytes(b"")


def transforms(root: Path, frames, touch=True, **meta) -> Path:
    """A hand-made transforms.json in `root`, with its images touched (`touch`)."""
    base = {"fl_x": 100.0, "fl_y": 100.0, "cx": 32.0, "cy": 24.0, "w": 64, "h": 48}
    base.update(meta)
    base = {k: v for k, v in base.items() if v is not None}
    base["frames"] = frames
    touch_images(root, [f["file_path"] for f in frames if touch
                        and isinstance(f, dict) and isinstance(f.get("file_path"), str)
                        and ".." not in f["file_path"] and not f["file_path"].startswith("/")])
    path = root / "transforms.json"
    path.write_text(json.dumps(base))
    return path


def frame(i=0, **kw):
    T = np.eye(4)
    T[:3, 3] = [0.1 * i, 0, 5]
    return {"file_path": f"images/frame_{i:05d}.png", "transform_matrix": T.tolist(), **kw}


def read_one(tmp_path, **meta):
    return read_transforms(transforms(tmp_path, [frame()], **meta), tmp_path).frames[0]


def refused(path, root, *words):
    with pytest.raises(InputError) as e:
        read_transforms(path, root)
    msg = str(e.value)
    assert str(path) in msg and "\n" not in msg
    for w in words:
        assert w in msg, msg
    return msg


def assert_same(cams: dict[str, Camera], capture):
    assert sorted(cams) == [f.name for f in capture.frames]
    for f in capture.frames:
        assert f.lens.model == "PINHOLE" and not f.lens.distorted
        np.testing.assert_allclose(f.cam_from_world, cams[f.name].cam_from_world, atol=1e-9)
        np.testing.assert_allclose(f.lens.pinhole_K(), cams[f.name].K, atol=1e-9)
        assert (f.lens.width, f.lens.height) == cams[f.name].size


# --- round trips ----------------------------------------------------------------------------------
def test_sample_cameras_round_trip_with_global_intrinsics(tmp_path):
    cams = cameras_from_json(SAMPLE)
    write_transforms(cams, tmp_path / "transforms.json")
    d = json.loads((tmp_path / "transforms.json").read_text())
    assert d["camera_model"] == "PINHOLE" and d["w"] == 320 and d["cx"] == 160.0
    assert "fl_x" not in d["frames"][0]
    touch_images(tmp_path, [f["file_path"] for f in d["frames"]])
    cap = read_transforms(tmp_path / "transforms.json", tmp_path)
    assert cap.format == "nerfstudio" and cap.image_encoding is None
    assert_same(cams, cap)
    assert cap.files[0] == tmp_path / "transforms.json" and len(cap.files) == 1 + len(cams)
    assert not list(tmp_path.glob(".*ibrtmp*"))  # written atomically, no temporary left


def test_per_frame_intrinsics_round_trip(tmp_path):
    cams = {f"v{i}.png": Camera.look_at([i, 0.5, -3], [0, 0, 0], [0, -1, 0],
                                        Camera.intrinsics_from_fov(40 + i, 30, 50 + 5 * i), 40 + i, 30)
            for i in range(3)}
    write_transforms(cams, tmp_path / "transforms.json", image_prefix="rgb/")
    d = json.loads((tmp_path / "transforms.json").read_text())
    assert "fl_x" not in d and all("fl_x" in f for f in d["frames"])
    touch_images(tmp_path, [f["file_path"] for f in d["frames"]])
    cap = read_transforms(tmp_path / "transforms.json", tmp_path)
    assert_same({f"rgb/{n}": c for n, c in cams.items()}, cap)  # only "images/" is stripped


def test_opengl_axes_from_first_principles(tmp_path):
    # OpenGL camera at (0, 0, 5), no rotation: it looks down world -z at the origin, y is up
    f = read_one(tmp_path)
    cam = Camera(f.lens.pinhole_K(), f.cam_from_world, 64, 48)
    uv, z = cam.project(np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]))
    np.testing.assert_allclose(uv[0], [31.5, 23.5], atol=1e-12)  # cx, cy = 32, 24 in COLMAP's
    assert z[0] == pytest.approx(5.0)
    assert uv[1, 0] > 31.5 and uv[1, 1] == pytest.approx(23.5)  # world +x: image right
    assert uv[2, 1] < 23.5 and uv[2, 0] == pytest.approx(31.5)  # world +y (up): image up


# --- lenses ---------------------------------------------------------------------------------------
def colmap_project(lens, xy):
    import pycolmap
    cam = pycolmap.Camera(model=lens.model, width=lens.width, height=lens.height, params=list(lens.params))
    return cam.img_from_cam(np.c_[xy, np.ones(len(xy))])


XY = np.array([[0.3, -0.2], [-0.25, 0.1], [0.05, 0.35]])


def test_opencv_distortion_maps_to_opencv(tmp_path):
    f = read_one(tmp_path, camera_model="OPENCV", k1=-0.1, k2=0.02, p1=0.001, p2=-0.002)
    assert f.lens.model == "OPENCV" and f.lens.distorted
    assert f.lens.params == (100, 100, 32, 24, -0.1, 0.02, 0.001, -0.002)


@pytest.mark.parametrize("k", [dict(k1=-0.1, k2=0.02, k3=0.005, p1=0.001, p2=-0.002),
                               dict(k1=0.05, k2=-0.01, p1=0.002, p2=0.001)])
def test_perspective_distortion_maths_matches_colmap(tmp_path, k):
    # nerfstudio (camera_utils._compute_residual_and_jacobian): d = 1 + k1 r + k2 r^2 + k3 r^3 +
    # k4 r^4 with r = x^2 + y^2; xd = x d + 2 p1 x y + p2 (r + 2 x^2); yd = y d + 2 p2 x y + p1 (r + 2 y^2)
    f = read_one(tmp_path, camera_model="OPENCV", fl_y=90.0, **k)
    assert f.lens.model == ("FULL_OPENCV" if "k3" in k else "OPENCV")
    k1, k2, k3, p1, p2 = (k.get(n, 0.0) for n in ("k1", "k2", "k3", "p1", "p2"))
    x, y = XY.T
    r = x * x + y * y
    d = 1 + r * (k1 + r * (k2 + r * k3))
    xd = x * d + 2 * p1 * x * y + p2 * (r + 2 * x * x)
    yd = y * d + 2 * p2 * x * y + p1 * (r + 2 * y * y)
    np.testing.assert_allclose(colmap_project(f.lens, XY), np.c_[100 * xd + 32, 90 * yd + 24], atol=1e-9)


def test_fisheye_maps_to_opencv_fisheye_and_maths_matches(tmp_path):
    k = dict(k1=0.05, k2=-0.01, k3=0.002, k4=-0.0005)
    f = read_one(tmp_path, camera_model="OPENCV_FISHEYE", **k)
    assert f.lens.model == "OPENCV_FISHEYE" and f.lens.params == (100, 100, 32, 24, *k.values())
    x, y = XY.T
    rad = np.hypot(x, y)
    th = np.arctan(rad)
    thd = th * (1 + k["k1"] * th**2 + k["k2"] * th**4 + k["k3"] * th**6 + k["k4"] * th**8)
    np.testing.assert_allclose(colmap_project(f.lens, XY),
                               np.c_[100 * x * thd / rad + 32, 100 * y * thd / rad + 24], atol=1e-9)


@pytest.mark.parametrize("meta, model, params", [
    (dict(camera_model="PINHOLE"), "PINHOLE", (100, 100, 32, 24)),
    (dict(camera_model=None, k1=0.0, p1=0.0), "PINHOLE", (100, 100, 32, 24)),  # no model, no distortion
    (dict(camera_model="OPENCV", k1=0.0, k2=0.0), "PINHOLE", (100, 100, 32, 24)),
    (dict(camera_model="SIMPLE_PINHOLE"), "PINHOLE", (100, 100, 32, 24)),
    (dict(camera_model="SIMPLE_RADIAL", k1=0.1), "SIMPLE_RADIAL", (100, 32, 24, 0.1)),
    (dict(camera_model="RADIAL", k1=0.1, k2=0.01), "RADIAL", (100, 32, 24, 0.1, 0.01)),
])
def test_lens_models(tmp_path, meta, model, params):
    f = read_one(tmp_path, **meta)
    assert (f.lens.model, f.lens.params) == (model, params)


def test_per_frame_intrinsics_override_the_global_ones(tmp_path):
    frames = [frame(0), frame(1, fl_x=120.0, w=80, camera_model="OPENCV", k1=-0.05)]
    cap = read_transforms(transforms(tmp_path, frames), tmp_path)
    a, b = cap.frames
    assert (a.lens.model, a.lens.params, a.lens.width) == ("PINHOLE", (100, 100, 32, 24), 64)
    assert (b.lens.model, b.lens.params[:5], b.lens.width) == ("OPENCV", (120, 100, 32, 24, -0.05), 80)


@pytest.mark.parametrize("model", ["EQUIRECTANGULAR", "FISHEYE624", "VR180_L", "OMNIDIRECTIONALSTEREO_L",
                                   "SOMETHING"])
def test_non_pinhole_models_are_refused(tmp_path, model):
    path = transforms(tmp_path, [frame()], camera_model=model)
    refused(path, tmp_path, model, "cannot be undistorted to a pinhole camera")


def test_per_frame_refused_model_names_the_frame(tmp_path):
    path = transforms(tmp_path, [frame(0), frame(1, camera_model="EQUIRECTANGULAR")])
    refused(path, tmp_path, "frame 1", "EQUIRECTANGULAR")


def test_k4_has_no_colmap_equivalent(tmp_path):
    refused(transforms(tmp_path, [frame()], camera_model="OPENCV", k4=0.01), tmp_path, "k4", "r^8")


# --- paths, depth, masks --------------------------------------------------------------------------
def test_names_depth_and_notes(tmp_path):
    touch_images(tmp_path, ["depth/a.png", "depth/b.png"])
    frames = [frame(0, depth_file_path="depth/a.png", mask_path="masks/a.png"),
              {**frame(1), "file_path": "./rgb/b.png", "depth_file_path": "depth/b.png"}]
    cap = read_transforms(transforms(tmp_path, frames, depth_unit_scale_factor=1e-4), tmp_path)
    assert [f.name for f in cap.frames] == ["frame_00000.png", "rgb/b.png"]
    assert cap.frames[0].depth == tmp_path / "depth/a.png"
    assert all(f.depth_units_per_m == pytest.approx(1e4) for f in cap.frames)
    assert tmp_path / "depth/b.png" in cap.files and tmp_path / "rgb/b.png" in cap.files
    assert any("mask_path" in n and "ignored" in n for n in cap.notes)


def test_depth_units_default_to_millimetres(tmp_path):
    touch_images(tmp_path, ["depth/a.png"])
    assert read_one(tmp_path).depth is None
    f = read_transforms(transforms(tmp_path, [frame(0, depth_file_path="depth/a.png")]), tmp_path).frames[0]
    assert f.depth_units_per_m == pytest.approx(1000.0)


def test_partial_depth_is_refused(tmp_path):
    touch_images(tmp_path, ["depth/a.png"])
    path = transforms(tmp_path, [frame(0, depth_file_path="depth/a.png"), frame(1)])
    refused(path, tmp_path, "1 of 2 frames")


def test_json_in_a_subfolder_may_name_images_beside_it(tmp_path):
    touch_images(tmp_path, ["images/a.png"])
    sub = tmp_path / "ns"
    sub.mkdir()
    path = transforms(sub, [{**frame(), "file_path": "../images/a.png"}])
    cap = read_transforms(path, tmp_path)
    assert cap.frames[0].name == "a.png" and cap.frames[0].image == tmp_path / "images/a.png"


@pytest.mark.parametrize("rel, words", [
    ("../x.png", ["climbs out"]), ("/etc/passwd", ["is absolute"]),
    ("images/missing.png", ["not found", "images/missing.png"])])
def test_bad_image_paths_are_refused(tmp_path, rel, words):
    root = tmp_path / "in"
    root.mkdir()
    (tmp_path / "x.png").write_bytes(b"")  # exists: the refusal is the escape, not a missing file
    path = transforms(root, [{**frame(), "file_path": rel}], touch=False)
    refused(path, root, "frame 0", "file_path", *words)


def test_escaping_depth_path_is_refused(tmp_path):
    root = tmp_path / "in"
    root.mkdir()
    (tmp_path / "d.png").write_bytes(b"")
    refused(transforms(root, [frame(0, depth_file_path="../d.png")]), root, "depth_file_path", "climbs out")


# --- malformed files ------------------------------------------------------------------------------
def test_malformed_json_is_refused(tmp_path):
    path = tmp_path / "transforms.json"
    path.write_text('{"frames": [ {"file_path": "a.png",, } ]}')
    refused(path, tmp_path, "not valid JSON", "line 1")


def test_missing_transforms_file(tmp_path):
    refused(tmp_path / "transforms.json", tmp_path, "cannot read")


def scaled():
    T = np.eye(4)
    T[:3, :3] *= 2
    return T.tolist()


@pytest.mark.parametrize("frames, meta, words", [
    ([], {}, ["non-empty"]),
    ("nope", {}, ["'frames'"]),
    ([42], {}, ["frame 0", "expected an object"]),
    ([{"file_path": "images/frame_00000.png"}], {}, ["frame 0", "transform_matrix"]),
    ([{"transform_matrix": np.eye(4).tolist()}], {}, ["frame 0", "file_path"]),
    ([frame()], {"fl_x": "100"}, ["frame 0", "fl_x", "number"]),
    ([frame()], {"fl_y": None}, ["frame 0", "fl_y", "missing"]),
    ([frame()], {"w": 64.5}, ["frame 0", "w", "whole number"]),
    ([frame()], {"fl_x": -1.0}, ["frame 0", "fl_x"]),
    ([frame()], {"k1": [0.1]}, ["frame 0", "k1"]),
    ([frame()], {"camera_model": 3}, ["frame 0", "camera_model"]),
    ([frame()], {"depth_unit_scale_factor": 0}, ["depth_unit_scale_factor"]),
    ([frame(0), {**frame(1), "transform_matrix": np.eye(4)[:3].tolist()}], {}, ["frame 1", "4x4"]),
    ([{**frame(), "transform_matrix": [[1, 0, 0, "x"]] * 4}], {}, ["frame 0", "number"]),
    ([{**frame(), "transform_matrix": scaled()}], {}, ["frame 0", "not a rotation"]),
    ([{**frame(), "transform_matrix": np.diag([1.0, 1, -1, 1]).tolist()}], {}, ["frame 0", "reflection"]),
    ([frame(0), frame(0)], {}, ["same image", "frame_00000.png"]),
])
def test_malformed_fields_are_refused(tmp_path, frames, meta, words):
    refused(transforms(tmp_path, frames, **meta), tmp_path, *words)


def test_nan_is_refused(tmp_path):
    path = transforms(tmp_path, [frame()])
    path.write_text(path.read_text().replace('"fl_x": 100.0', '"fl_x": NaN'))
    refused(path, tmp_path, "fl_x", "finite")


def test_slightly_off_rotation_is_made_exact(tmp_path):
    cams = cameras_from_json(SAMPLE)
    T = np.round(cams["0000.png"].world_from_cam @ np.diag([1.0, -1, -1, 1]), 5)  # 5 decimals
    f = read_transforms(transforms(tmp_path, [{**frame(), "transform_matrix": T.tolist()}]), tmp_path).frames[0]
    Camera(f.lens.pinhole_K(), f.cam_from_world, 64, 48)  # Camera's stricter check accepts it
    np.testing.assert_allclose(f.cam_from_world, cams["0000.png"].cam_from_world, atol=1e-4)


# --- camera_path.json -----------------------------------------------------------------------------
def path_cameras(n=5, w=64, h=48):
    K = Camera.intrinsics_from_fov(w, h, 70)
    return [Camera.look_at([math.cos(a) * 3, 1, math.sin(a) * 3], [0, 0, 0], [0, -1, 0], K, w, h)
            for a in np.linspace(0, 1, n)]


def test_camera_path_round_trip(tmp_path):
    cams = path_cameras()
    write_camera_path(cams, tmp_path / "camera_path.json", fps=10)
    d = json.loads((tmp_path / "camera_path.json").read_text())
    assert d["camera_type"] == "perspective" and (d["render_width"], d["render_height"]) == (64, 48)
    assert d["seconds"] == pytest.approx(0.5) and len(d["camera_path"][0]["camera_to_world"]) == 16
    back = read_camera_path(tmp_path / "camera_path.json")
    assert len(back) == len(cams)
    for a, b in zip(cams, back):
        np.testing.assert_allclose(b.cam_from_world, a.cam_from_world, atol=1e-9)
        np.testing.assert_allclose(b.K, a.K, atol=1e-9)
        assert b.size == a.size


def test_camera_path_from_first_principles(tmp_path):
    T = np.eye(4)
    T[:3, 3] = [0, 0, 5]
    d = {"camera_type": "perspective", "render_width": 101, "render_height": 81, "fps": 24, "seconds": 1,
         "camera_path": [{"camera_to_world": T.ravel().tolist(), "fov": 90, "aspect": 101 / 81},
                         {"camera_to_world": T.tolist(), "fov": 60}]}
    (tmp_path / "p.json").write_text(json.dumps(d))
    a, b = read_camera_path(tmp_path / "p.json")
    assert a.K[1, 1] == pytest.approx(40.5) and a.K[0, 0] == pytest.approx(40.5)  # (H/2) / tan(45°)
    assert b.K[1, 1] == pytest.approx(40.5 / math.tan(math.radians(30)))
    uv, z = a.project(np.array([[0.0, 0, 0], [0, 1, 0]]))
    np.testing.assert_allclose(uv[0], [50, 40], atol=1e-12)
    assert z[0] == pytest.approx(5) and uv[1, 1] < 40


@pytest.mark.parametrize("change, words", [
    ({"camera_type": "equirectangular"}, ["equirectangular"]),
    ({"camera_path": []}, ["camera_path"]),
    ({"render_width": "64"}, ["render_width"]),
    ({"camera_path": [{"camera_to_world": [1, 0, 0]}]}, ["camera_path[0]", "fov"]),
    ({"camera_path": [{"camera_to_world": [1.0] * 15, "fov": 50}]}, ["camera_path[0]", "4x4"]),
    ({"camera_path": [{"camera_to_world": np.eye(4).ravel().tolist(), "fov": 180}]}, ["fov"]),
])
def test_bad_camera_paths_are_refused(tmp_path, change, words):
    d = {"render_width": 64, "render_height": 48,
         "camera_path": [{"camera_to_world": np.eye(4).ravel().tolist(), "fov": 50}], **change}
    (tmp_path / "p.json").write_text(json.dumps(d))
    with pytest.raises(InputError) as e:
        read_camera_path(tmp_path / "p.json")
    assert str(tmp_path / "p.json") in str(e.value)
    for w in words:
        assert w in str(e.value)


def test_write_camera_path_refuses_what_it_cannot_store(tmp_path):
    cams = path_cameras(2)
    K = cams[0].K.copy()
    K[0, 0] *= 1.01
    with pytest.raises(ValueError, match="square"):
        write_camera_path([Camera(K, cams[0].cam_from_world, 64, 48)], tmp_path / "p.json")
    with pytest.raises(ValueError, match="size"):
        write_camera_path([cams[0], cams[1].resized(32, 24)], tmp_path / "p.json")
    assert not (tmp_path / "p.json").exists()


# --- sniffing -------------------------------------------------------------------------------------
def test_sniffing_never_raises(tmp_path):
    write_transforms(cameras_from_json(SAMPLE), tmp_path / "transforms.json")
    write_camera_path(path_cameras(2), tmp_path / "camera_path.json")
    assert is_transforms(tmp_path / "transforms.json") and not is_camera_path(tmp_path / "transforms.json")
    assert is_camera_path(tmp_path / "camera_path.json") and not is_transforms(tmp_path / "camera_path.json")
    junk = {"bin": b"\xff\xfe\x00junk", "list.json": b"[1, 2]", "broken.json": b'{"frames": [',
            "deep.json": b"{" + b'"a":[' * 100000, "frames_obj.json": b'{"frames": {}}', "empty.json": b""}
    for name, data in junk.items():
        (tmp_path / name).write_bytes(data)
        assert not is_transforms(tmp_path / name) and not is_camera_path(tmp_path / name)
    for p in (tmp_path / "nothing.json", tmp_path):
        assert not is_transforms(p) and not is_camera_path(p)
