"""Every input layout ingests to the same views and poses (issue "Captures in the forms people have
them", deliverable 4). Each fixture is made from the sample scene by our own code: its cameras
converted to each format, its images distorted with a lens and undistorted again by ingest, its
depth rewritten in another unit. The reference is the sample's own cameras.json.
"""
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from ibr_pipeline.cli import main
from ibr_pipeline.io.capture import Lens
from ibr_pipeline.io.colmap import build_reconstruction, write_colmap_model
from ibr_pipeline.io.images import read_depth_png, read_image, write_image
from ibr_pipeline.io.undistort import resample, undistorted_lens
from ibr_pipeline.scene import Camera, Scene, cameras_from_json, cameras_to_json

SAMPLE = Path(__file__).resolve().parents[2] / "sample_data" / "mirror_room"
N = 5  # views used: enough for sorting and naming, cheap to check


@pytest.fixture(scope="module")
def sample():
    cams = cameras_from_json(SAMPLE / "cameras.json")
    names = sorted(cams)[:N]
    return {n: cams[n] for n in names}


def _copy_images(sample, dst: Path, depth: bool = False) -> None:
    (dst / "images").mkdir(parents=True, exist_ok=True)
    for n in sample:
        shutil.copy(SAMPLE / "images" / n, dst / "images" / n)
        if depth:
            (dst / "depth").mkdir(exist_ok=True)
            shutil.copy(SAMPLE / "depth" / n, dst / "depth" / n)


def ingest(root: Path, ws: Path, *extra: str) -> Scene:
    assert main(["init", str(ws), "--input", str(root)]) == 0
    assert main(["ingest", str(ws), "--no-progress", *extra]) == 0
    return Scene.from_json((ws / "scene.json").read_text())


def assert_same_poses(scene: Scene, sample, K_too: bool = True, tol: float = 1e-6) -> None:
    assert sorted(scene.names) == sorted(sample)
    for n, ref in sample.items():
        cam = scene.view(n).camera
        assert cam is not None, n
        assert np.abs(cam.cam_from_world - ref.cam_from_world).max() < tol, n
        if K_too:
            assert np.abs(cam.K - ref.K).max() < tol and cam.size == ref.size, n


def test_cameras_json(sample, tmp_path):
    root = tmp_path / "in"
    _copy_images(sample, root, depth=True)
    (root / "cameras.json").write_text(cameras_to_json(sample))
    scene = ingest(root, tmp_path / "ws")
    assert scene.source == "cameras.json"
    assert_same_poses(scene, sample)
    assert all(v.image == f"input/images/{v.name}" for v in scene.views)  # nothing prepared
    assert all(v.depth == f"input/depth/{v.name}" for v in scene.views)


@pytest.mark.parametrize("layout,text", [("sparse/0", True), ("sparse/0", False), ("sparse", True),
                                         ("colmap/sparse/0", False)])
def test_colmap_layouts(sample, tmp_path, layout, text):
    root = tmp_path / "in"
    _copy_images(sample, root)
    write_colmap_model(sample, root / layout, text=text)
    scene = ingest(root, tmp_path / "ws")
    assert scene.source == {"sparse/0": "colmap", "sparse": "colmap-undistorted",
                            "colmap/sparse/0": "nerfstudio-colmap"}[layout]
    assert_same_poses(scene, sample)
    assert scene.sparse == f"input/{layout}"


@pytest.mark.parametrize("fmt", ["nerfstudio", "llff"])
def test_pose_files(sample, tmp_path, fmt):
    from ibr_pipeline.io.llff import write_poses_bounds
    from ibr_pipeline.io.nerfstudio import write_transforms
    root = tmp_path / "in"
    _copy_images(sample, root)
    if fmt == "nerfstudio":
        write_transforms(sample, root / "transforms.json")
    else:
        write_poses_bounds(sample, root / "poses_bounds.npy")
    scene = ingest(root, tmp_path / "ws")
    assert scene.source == fmt
    assert_same_poses(scene, sample)


def test_other_pose_sources_are_named(sample, tmp_path, capsys):
    root = tmp_path / "in"
    _copy_images(sample, root)
    write_colmap_model(sample, root / "sparse" / "0")
    (root / "cameras.json").write_text(cameras_to_json(sample))
    scene = ingest(root, tmp_path / "ws")
    assert scene.source == "colmap"
    assert "also present, not used: cameras.json" in capsys.readouterr().err


def _images_and_depths(sample):
    images = {n: read_image(SAMPLE / "images" / n) for n in sample}
    depths = {n: read_depth_png(SAMPLE / "depth" / n) for n in sample}  # half size
    return images, depths


@pytest.mark.parametrize("fmt", ["tum", "scannet"])
def test_rgbd_formats(sample, tmp_path, fmt):
    """TUM (5000 depth units per metre, timestamps, interpolated ground truth) and ScanNet (its own
    depth intrinsics): the same poses, and depth rewritten in millimetres on the colour camera."""
    from ibr_pipeline.io import rgbd
    root = tmp_path / "rgbd_dataset_freiburg3_fixture"
    images, depths = _images_and_depths(sample)
    import cv2  # full-size depth, as a Kinect gives it registered to colour
    depths = {n: cv2.resize(d, (320, 240), interpolation=cv2.INTER_NEAREST) for n, d in depths.items()}
    names = (rgbd.write_tum if fmt == "tum" else rgbd.write_scannet)(root, sample, images, depths)
    ws = tmp_path / "ws"
    scene = ingest(root, ws)
    assert scene.source == fmt
    renamed = {names[n]: c for n, c in sample.items()}
    assert_same_poses(scene, renamed)
    for n, tum_name in names.items():
        v = scene.view(tum_name)
        assert v.depth is not None and v.depth.startswith("ingest/depth/")
        got = read_depth_png(ws / v.depth)
        want = depths[n]
        if got.shape != want.shape:  # ScanNet: half size, 2x2 means where all four are valid
            import cv2
            want = cv2.resize(want, got.shape[::-1], interpolation=cv2.INTER_NEAREST)
        ok = (got > 0) & (want > 0)
        assert ok.sum() > 0.8 * (want > 0).sum()
        assert np.median(np.abs(got - want)[ok]) <= 0.002  # metres: unit rounding


def test_video(sample, tmp_path):
    """A video of the sample's frames: frames extracted into the workspace, unposed (SfM)."""
    import imageio_ffmpeg
    root = tmp_path / "in"
    root.mkdir()
    w = imageio_ffmpeg.write_frames(str(root / "walk.mp4"), (320, 240), fps=10, codec="libx264",
                                    quality=None, output_params=["-qp", "0"], macro_block_size=1)
    w.send(None)
    for n in sample:
        frame = (read_image(SAMPLE / "images" / n) * 255).round().astype(np.uint8)
        for _ in range(2):
            w.send(np.ascontiguousarray(frame))
    w.close()
    scene = ingest(root, tmp_path / "ws", "--video-frames", "4")
    assert scene.source == "video" and len(scene.views) == 4
    assert all(v.camera is None and v.image.startswith("ingest/images/frame_") for v in scene.views)
    assert read_image(tmp_path / "ws" / scene.views[0].image).shape == (240, 320, 3)


LENSES = [("SIMPLE_RADIAL", lambda f, cx, cy: (f, cx, cy, -0.08)),
          ("RADIAL", lambda f, cx, cy: (f, cx, cy, -0.06, 0.02)),
          ("OPENCV", lambda f, cx, cy: (f, f * 1.01, cx + 1.5, cy - 1.0, -0.05, 0.01, 0.001, -0.0005)),
          ("OPENCV_FISHEYE", lambda f, cx, cy: (f, f, cx, cy, 0.02, -0.01, 0.0, 0.0))]


def _distorted_input(sample, root: Path, model: str, params, with_depth: bool = False):
    """The sample's images as seen through a distorted lens: a COLMAP model with that lens."""
    import pycolmap

    from ibr_pipeline.io.capture import colmap_camera
    cam0 = next(iter(sample.values()))
    f, cx, cy = cam0.K[0, 0], cam0.K[0, 2] + 0.5, cam0.K[1, 2] + 0.5
    lens = Lens(model, params(f, cx, cy), cam0.width, cam0.height)
    pin = Lens.from_K(cam0.K, cam0.width, cam0.height)
    (root / "images").mkdir(parents=True)
    for n in sample:
        img = (read_image(SAMPLE / "images" / n) * 255).round().astype(np.uint8)
        write_image(root / "images" / n, resample(img, pin, lens))
        if with_depth:
            d = read_depth_png(SAMPLE / "depth" / n)
            from ibr_pipeline.io.images import write_depth_png
            from ibr_pipeline.io.undistort import scaled_lens
            small = scaled_lens(lens, d.shape[1], d.shape[0])
            write_depth_png(root / "depth" / n, resample(d, scaled_lens(pin, d.shape[1], d.shape[0]),
                                                         small, nearest=True))
    rec = build_reconstruction(sample)
    rec.cameras[1] = colmap_camera(lens, camera_id=1)
    (root / "sparse" / "0").mkdir(parents=True)
    rec.write_text(str(root / "sparse" / "0"))  # written by pycolmap, as COLMAP would
    assert pycolmap.Reconstruction(str(root / "sparse" / "0")).cameras[1].model_name == model
    return lens, pin


@pytest.mark.parametrize("model,params", LENSES, ids=[m for m, _ in LENSES])
def test_distorted_colmap_is_undistorted(sample, tmp_path, model, params):
    root = tmp_path / "in"
    lens, pin = _distorted_input(sample, root, model, params)
    before = {p: p.read_bytes() for p in root.rglob("*") if p.is_file()}
    ws = tmp_path / "ws"
    scene = ingest(root, ws)
    assert {p: p.read_bytes() for p in root.rglob("*") if p.is_file()} == before  # input untouched
    out = undistorted_lens(lens)
    assert_same_poses(scene, sample, K_too=False)
    for v in scene.views:
        assert v.image == f"ingest/images/{Path(v.name).stem}.png"
        assert np.abs(v.camera.K - out.pinhole_K()).max() < 1e-9
        # the undistorted frame is the original photograph seen by the new pinhole camera
        got = read_image(ws / v.image)
        want = resample(read_image(SAMPLE / "images" / v.name), pin, out)
        inner = (slice(8, -8), slice(8, -8))
        err = np.abs(got - want)[inner]
        assert np.median(err) < 2 / 255 and np.mean(err) < 6 / 255, (np.median(err), err.mean())
    # the poses stage reads the undistorted model (pinhole cameras)
    assert scene.sparse == "ingest/sparse"
    text = (ws / "ingest" / "sparse" / "cameras.txt").read_text()
    assert "PINHOLE" in text and model not in text.replace("PINHOLE", "")


def test_distorted_depth_follows_its_image(sample, tmp_path):
    root = tmp_path / "in"
    lens, pin = _distorted_input(sample, root, "SIMPLE_RADIAL", LENSES[0][1], with_depth=True)
    ws = tmp_path / "ws"
    scene = ingest(root, ws)
    from ibr_pipeline.io.undistort import scaled_lens
    out = undistorted_lens(lens)
    for v in scene.views:
        assert v.depth == f"ingest/depth/{Path(v.name).stem}.png"
        got = read_depth_png(ws / v.depth)
        d = read_depth_png(SAMPLE / "depth" / v.name)
        want = resample(d, scaled_lens(pin, d.shape[1], d.shape[0]),
                        scaled_lens(out, got.shape[1], got.shape[0]), nearest=True)
        ok = (got > 0) & (want > 0)
        assert ok.sum() > 0.9 * (want > 0).sum()  # the sample's own frames have holes
        assert np.median(np.abs(got - want)[ok]) < 0.01  # metres; nearest resampling twice


def test_exif_rotation(sample, tmp_path):
    """A phone photo stored sideways with EXIF orientation 6 is turned upright for SfM; with a
    camera made for the stored pixels it is left as stored."""
    from PIL import Image
    root = tmp_path / "in"
    (root / "images").mkdir(parents=True)
    for n in sample:
        im = Image.open(SAMPLE / "images" / n).convert("RGB")
        stored = im.transpose(Image.Transpose.ROTATE_90)  # what the sensor wrote
        exif = Image.Exif()
        exif[0x0112] = 6  # "rotate 90 CW to display"
        stored.save(root / "images" / Path(n).with_suffix(".jpg"), exif=exif, quality=95)
    scene = ingest(root, tmp_path / "ws")
    v = scene.views[0]
    assert v.image.startswith("ingest/images/")
    up = read_image(tmp_path / "ws" / v.image)
    assert up.shape == (240, 320, 3)
    ref = read_image(SAMPLE / "images" / Path(v.name).with_suffix(".png"))
    assert np.abs(up - ref).mean() < 0.03  # JPEG
    # the same files with cameras for the stored (sideways) pixels: not rotated
    cams = {Path(n).with_suffix(".jpg").as_posix(): Camera(np.array([[100, 0, 119.5], [0, 100, 159.5], [0, 0, 1.0]]),
                                                           c.cam_from_world, 240, 320)
            for n, c in sample.items()}
    (root / "cameras.json").write_text(cameras_to_json(cams))
    scene = ingest(root, tmp_path / "ws2")
    assert all(v.image.startswith("input/images/") for v in scene.views)


def test_colour_encoding(sample, tmp_path):
    root = tmp_path / "in"
    _copy_images(sample, root)
    (root / "cameras.json").write_text(cameras_to_json(sample))
    assert ingest(root, tmp_path / "a").image_encoding == "srgb"  # photographs by default
    (root / "gt").mkdir()
    (root / "gt" / "scene.json").write_text(json.dumps({"image_encoding": "linear"}))
    assert ingest(root, tmp_path / "b").image_encoding == "linear"  # a synthetic scene says so
    assert ingest(root, tmp_path / "c", "--colour", "srgb").image_encoding == "srgb"


def test_symlinked_images_folder(sample, tmp_path):
    """An images/ that is a symlink to the photos elsewhere (a common way to share them) is read
    through the link: path checks are lexical (docs/DESIGN.md "Errors")."""
    photos = tmp_path / "photos"
    _copy_images(sample, photos)
    root = tmp_path / "in"
    root.mkdir()
    (root / "images").symlink_to(photos / "images", target_is_directory=True)
    (root / "cameras.json").write_text(cameras_to_json(sample))
    scene = ingest(root, tmp_path / "ws")
    assert_same_poses(scene, sample)
    assert all(v.image == f"input/images/{v.name}" for v in scene.views)


def test_nerfstudio_frames_outside_images_are_fingerprinted(sample, tmp_path):
    """nerfstudio frames often live in images_4/ or elsewhere: ingest's inputs are the files the
    transforms.json names, so changing one of them makes ingest rerun."""
    from ibr_pipeline.io.inputs import input_files
    from ibr_pipeline.io.nerfstudio import write_transforms
    root = tmp_path / "in"
    (root / "images_4").mkdir(parents=True)
    for n in sample:
        shutil.copy(SAMPLE / "images" / n, root / "images_4" / n)
    write_transforms(sample, root / "transforms.json", image_prefix="images_4/")
    files = set(input_files(root))
    assert {root / "images_4" / n for n in sample} | {root / "transforms.json"} <= files
