"""Per-image intrinsics and sizes: a capture whose views come at two resolutions (a phone and a
camera, or a zoomed shot) runs through the pipeline, each view at its own size."""
import json
import shutil

import cv2
import numpy as np

from ibr_pipeline.cli import main
from ibr_pipeline.io.images import read_image, write_image
from ibr_pipeline.scene import Scene, cameras_from_json, cameras_to_json


def test_two_resolutions_through_render_views(tiny_scene, tmp_path):
    root = tmp_path / "in"
    shutil.copytree(tiny_scene[0], root)
    shutil.rmtree(root / "sparse", ignore_errors=True)
    cams = cameras_from_json(root / "cameras.json")
    new = {}
    for i, (n, c) in enumerate(sorted(cams.items())):
        if i % 3 == 1:  # every third view at twice the resolution, its K scaled
            img = read_image(root / "images" / n)
            write_image(root / "images" / n, cv2.resize(img, (2 * c.width, 2 * c.height)))
            c = c.resized(2 * c.width, 2 * c.height)
        new[n] = c
    (root / "cameras.json").write_text(cameras_to_json(new))
    ws = tmp_path / "ws"
    assert main(["run", str(ws), "--input", str(root), "--until", "render_views", "--no-progress"]) == 0
    scene = Scene.from_json((ws / "scene.json").read_text())
    assert {v.camera.size for v in scene.views} == {(160, 120), (320, 240)}
    for n, c in new.items():  # every view's depth and mesh at its own size
        assert np.load(ws / "views" / n / "depth.npy").shape == (c.height, c.width)
    t = json.loads((ws / "renders" / "test" / "timings.json").read_text())
    assert len(t["frames"]) > 0
    for f in sorted((ws / "renders" / "test").glob("*.png")):
        im = read_image(f)
        assert im.shape == (120, 160, 3) and im.max() > 0.05
