"""SfM that estimates a distorted lens (`poses.camera_model`): every image and depth frame is
undistorted into sfm/, and every later stage reads those (layout.posed_scene). SfM itself is
replaced by its answer for a known lens, so what is tested is what the stage does with it."""
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from ibr_pipeline import layout as L
from ibr_pipeline.cli import main
from ibr_pipeline.geometry import sfm
from ibr_pipeline.io.capture import Lens, colmap_camera
from ibr_pipeline.io.colmap import build_reconstruction
from ibr_pipeline.io.images import read_depth_png, read_image, write_depth_png, write_image
from ibr_pipeline.io.undistort import resample, scaled_lens, undistorted_lens
from ibr_pipeline.scene import cameras_from_json
from ibr_pipeline.workspace import Workspace

SAMPLE = Path(__file__).resolve().parents[2] / "sample_data" / "mirror_room"


@pytest.fixture
def distorted(tmp_path):
    """Six sample views photographed through SIMPLE_RADIAL k = -0.08, with depth; no poses."""
    cams = cameras_from_json(SAMPLE / "cameras.json")
    cams = {n: cams[n] for n in sorted(cams)[:6]}
    c0 = next(iter(cams.values()))
    pin = Lens.from_K(c0.K, c0.width, c0.height)
    lens = Lens("SIMPLE_RADIAL", (c0.K[0, 0], c0.K[0, 2] + 0.5, c0.K[1, 2] + 0.5, -0.08),
                c0.width, c0.height)
    root = tmp_path / "in"
    for n in cams:
        img = (read_image(SAMPLE / "images" / n) * 255).round().astype(np.uint8)
        write_image(root / "images" / n, resample(img, pin, lens))
        d = read_depth_png(SAMPLE / "depth" / n)
        write_depth_png(root / "depth" / n, resample(d, scaled_lens(pin, *d.shape[::-1]),
                                                     scaled_lens(lens, *d.shape[::-1]), nearest=True))
    return root, cams, lens, pin


def _fake_sfm(monkeypatch, cams, lens):
    def run_sfm(image_dir, names, work_dir, *a, camera_model="SIMPLE_PINHOLE", **k):
        rec = build_reconstruction(cams)
        if camera_model != "SIMPLE_PINHOLE":
            rec.cameras[1] = colmap_camera(lens, camera_id=1)
        stats = {"models": 1, "model_sizes": [len(cams)], "reprojection_error_px": 0.2,
                 "registered": len(cams)}
        return sfm.SfMResult(dict(cams), rec, stats)
    monkeypatch.setattr(sfm, "run_sfm", run_sfm)


def test_distorted_sfm_lens_is_undistorted_for_every_later_stage(distorted, tmp_path, monkeypatch):
    root, cams, lens, pin = distorted
    _fake_sfm(monkeypatch, cams, lens)
    ws = tmp_path / "ws"
    base = ["run", str(ws), "--input", str(root), "--until", "poses", "--no-progress",
            "--set", "poses.scale=1"]
    assert main(base + ["--set", "poses.camera_model=SIMPLE_RADIAL"]) == 0
    out = undistorted_lens(lens)
    views = json.loads((ws / L.POSED_VIEWS).read_text())["views"]
    assert set(views) == set(cams)
    reg = cameras_from_json(ws / L.REGISTERED_CAMERAS)
    w = Workspace(ws)
    scene = L.posed_scene(w)
    for n in cams:
        stem = Path(n).stem
        assert views[n] == {"image": f"sfm/images/{stem}.png", "depth": f"sfm/depth/{stem}.png"}
        assert scene.view(n).image == views[n]["image"]
        assert np.abs(reg[n].K - out.pinhole_K()).max() < 1e-9 and reg[n].size == (out.width, out.height)
        assert np.abs(reg[n].cam_from_world - cams[n].cam_from_world).max() < 1e-9
        got = read_image(ws / views[n]["image"])
        want = resample(read_image(SAMPLE / "images" / n), pin, out)
        assert np.median(np.abs(got - want)[8:-8, 8:-8]) < 2 / 255
        assert read_depth_png(ws / views[n]["depth"]).shape[1] == round(out.width / 2)
    assert "SIMPLE_RADIAL" not in (ws / "sfm" / "cameras.txt").read_text()
    # the stages after poses read the undistorted files: they are in view_depth's inputs
    assert main(["status", str(ws)]) == 0
    from ibr_pipeline.pipeline import scene_for
    assert scene_for(w, "view_depth").view(sorted(cams)[0]).image.startswith("sfm/images/")
    assert scene_for(w, "poses").view(sorted(cams)[0]).image.startswith("input/")
    # back to a pinhole SfM: the overlay goes, later stages read the input's images again
    assert main(base + ["--set", "poses.camera_model=SIMPLE_PINHOLE"]) == 0
    assert not (ws / L.POSED_VIEWS).exists()
    assert L.posed_scene(Workspace(ws)).view(sorted(cams)[0]).image.startswith("input/")


def test_broken_views_file_is_one_line(distorted, tmp_path, monkeypatch):
    from ibr_pipeline.errors import InputError
    root, cams, lens, _ = distorted
    _fake_sfm(monkeypatch, cams, lens)
    ws = tmp_path / "ws"
    assert main(["run", str(ws), "--input", str(root), "--until", "poses", "--no-progress",
                 "--set", "poses.scale=1", "--set", "poses.camera_model=SIMPLE_RADIAL"]) == 0
    (ws / L.POSED_VIEWS).write_text("{")
    with pytest.raises(InputError, match="views.json"):
        L.posed_scene(Workspace(ws))
    shutil.rmtree(ws)
