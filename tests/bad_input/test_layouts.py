"""Input layouts that are recognised but cannot be used: one line naming the file, exit 2, the input
and the workspace as they were, and never a silent fallback to SfM."""
import json

import numpy as np
from conftest import cameras, refused

from ibr_pipeline.cli import main
from ibr_pipeline.io.images import write_image


def _ws(tmp_path, root):
    ws = tmp_path / "ws"
    assert main(["init", str(ws), "--input", str(root)]) == 0
    return ws


def _images(root, n=4):
    rng = np.random.default_rng(0)
    for name in list(cameras(n))[:n]:
        write_image(root / "images" / name, rng.random((30, 40, 3)))


def test_sparse_folder_without_a_model(capsys, tmp_path):
    root = tmp_path / "in"
    _images(root)
    (root / "sparse" / "1").mkdir(parents=True)  # a second model only, 0/ renamed away
    ws = _ws(tmp_path, root)
    refused(capsys, ["run", ws], root, ws, "sparse", "holds no COLMAP model", "sparse/0")


def test_empty_colmap_model(capsys, tmp_path):
    root = tmp_path / "in"
    _images(root)
    (root / "sparse" / "0").mkdir(parents=True)
    for f in ("cameras.txt", "images.txt", "points3D.txt"):
        (root / "sparse" / "0" / f).write_text("# empty\n")
    ws = _ws(tmp_path, root)
    refused(capsys, ["run", ws], root, ws, "sparse/0", "registers no image")


def test_transforms_json_broken(capsys, tmp_path):
    root = tmp_path / "in"
    _images(root)
    (root / "transforms.json").write_text('{"frames": [{"file_path": "images/0.png"')
    ws = _ws(tmp_path, root)
    refused(capsys, ["run", ws], root, ws, "transforms.json")


def test_transforms_json_unsupported_camera(capsys, tmp_path):
    root = tmp_path / "in"
    _images(root)
    frames = [{"file_path": f"images/{n}", "transform_matrix": np.eye(4).tolist()} for n in cameras()]
    (root / "transforms.json").write_text(json.dumps({
        "camera_model": "EQUIRECTANGULAR", "fl_x": 20, "fl_y": 20, "cx": 20, "cy": 15, "w": 40,
        "h": 30, "frames": frames}))
    ws = _ws(tmp_path, root)
    refused(capsys, ["run", ws], root, ws, "transforms.json", "EQUIRECTANGULAR")


def test_poses_bounds_count_mismatch(capsys, tmp_path):
    root = tmp_path / "in"
    _images(root)
    np.save(root / "poses_bounds.npy", np.zeros((3, 17)))
    ws = _ws(tmp_path, root)
    refused(capsys, ["run", ws], root, ws, "poses_bounds.npy", "3", "4")


def test_tum_without_intrinsics(capsys, tmp_path):
    root = tmp_path / "some_sequence"
    for d in ("rgb", "depth"):
        (root / d).mkdir(parents=True)
    write_image(root / "rgb" / "1.0.png", np.zeros((30, 40, 3)))
    from ibr_pipeline.io.images import write_depth_png
    write_depth_png(root / "depth" / "1.0.png", np.full((30, 40), 1.0))
    (root / "rgb.txt").write_text("1.0 rgb/1.0.png\n")
    (root / "depth.txt").write_text("1.0 depth/1.0.png\n")
    ws = _ws(tmp_path, root)
    refused(capsys, ["run", ws], root, ws, "intrinsics.txt")


def test_two_videos(capsys, tmp_path):
    root = tmp_path / "in"
    root.mkdir()
    for n in ("a.mp4", "b.mov"):
        (root / n).write_bytes(b"\0" * 64)
    ws = _ws(tmp_path, root)
    refused(capsys, ["run", ws], root, ws, "2 videos", "one video per input folder")


def test_broken_video(capsys, tmp_path):
    root = tmp_path / "in"
    root.mkdir()
    (root / "walk.mp4").write_bytes(b"not a video at all" * 10)
    ws = _ws(tmp_path, root)
    refused(capsys, ["run", ws], root, ws, "walk.mp4")


def test_refused_during_undistortion_leaves_nothing(capsys, tmp_path):
    """Frames are prepared into a staging folder: a bad frame found after good ones were
    undistorted leaves no ingest/ file behind."""
    from ibr_pipeline.io.capture import Lens, colmap_camera
    from ibr_pipeline.io.colmap import build_reconstruction
    root = tmp_path / "in"
    _images(root)
    cams = cameras()
    write_image(root / "images" / "3.png", np.zeros((30, 50, 3)))  # the last one is the wrong size
    rec = build_reconstruction(cams)
    rec.cameras[1] = colmap_camera(Lens("SIMPLE_RADIAL", (35.0, 20.0, 15.0, -0.05), 40, 30))
    (root / "sparse" / "0").mkdir(parents=True)
    rec.write_text(str(root / "sparse" / "0"))
    ws = _ws(tmp_path, root)
    refused(capsys, ["run", ws], root, ws, "3.png", "50x30", "40x30")
    assert not (ws / "ingest").exists()
