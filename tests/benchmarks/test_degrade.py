"""Stability-sweep degradations: each changes exactly the input it names, by the amount asked."""
import json

import numpy as np
import pytest

from benchmarks.degrade import degrade_input
from ibr_pipeline.errors import InputError
from ibr_pipeline.io.images import read_depth_png, read_image
from ibr_pipeline.io.inputs import read_input
from ibr_pipeline.scene import cameras_from_json


def _angle_deg(Ra, Rb):
    c = (np.trace(Ra.T @ Rb) - 1) / 2
    return np.degrees(np.arccos(np.clip(c, -1, 1)))


def test_pose_noise_has_the_asked_size(tiny_scene, tmp_path):
    src = tiny_scene[0]
    ref = cameras_from_json(src / "cameras.json")
    rot = degrade_input(src, tmp_path / "r", "pose_rot", 0.5)
    trn = degrade_input(src, tmp_path / "t", "pose_trans", 0.03)
    assert not (rot / "sparse").exists()  # the pipeline must read the noisy cameras.json
    for name, cam in cameras_from_json(rot / "cameras.json").items():
        assert _angle_deg(cam.R, ref[name].R) == pytest.approx(0.5, abs=1e-3)
        assert np.linalg.norm(cam.center - ref[name].center) < 1e-6
    for name, cam in cameras_from_json(trn / "cameras.json").items():
        assert np.linalg.norm(cam.center - ref[name].center) == pytest.approx(0.03, abs=1e-6)
    assert read_input(rot).source == "cameras.json"


def test_depth_holes_and_view_subsets(tiny_scene, tmp_path):
    src = tiny_scene[0]
    holes = degrade_input(src, tmp_path / "h", "depth_holes", 0.3)
    frac = np.mean([(read_depth_png(p) == 0).mean() for p in (holes / "depth").glob("*.png")])
    base = np.mean([(read_depth_png(p) == 0).mean() for p in (src / "depth").glob("*.png")])
    assert 0.2 < frac - base < 0.4
    few = degrade_input(src, tmp_path / "v", "views", 0.5)
    assert len(read_input(few).views) == 4 and len(list((few / "depth").glob("*.png"))) == 4


def test_reflector_and_texture_degradations(tiny_scene, tmp_path):
    src = tiny_scene[0]
    gone = degrade_input(src, tmp_path / "m", "reflector_missing", 1)
    assert json.loads((gone / "reflectors.json").read_text())["reflectors"] == []
    wrong = degrade_input(src, tmp_path / "w", "reflector_wrong", 0.2)
    a = json.loads((src / "reflectors.json").read_text())["reflectors"][0]["plane"]
    b = json.loads((wrong / "reflectors.json").read_text())["reflectors"][0]["plane"]
    assert not np.allclose(a, b, atol=0.05)
    flat = degrade_input(src, tmp_path / "f", "textureless", 1.0)
    mats = json.loads((src / "gt" / "scene.json").read_text())["materials"]
    walls = [m["index"] for m in mats if m["name"].startswith("wall")]
    for p in sorted((src / "images").glob("*.png"))[:3]:
        with np.load(src / "gt" / "geom" / f"{p.stem}.npz") as z:
            m = np.isin(z["material"], walls)
        if m.sum() > 20:
            assert read_image(flat / "images" / p.name)[m].std(0).max() < 0.3 * read_image(p)[m].std(0).max()


def test_bad_degradation_is_a_clear_error(tiny_scene, tmp_path):
    with pytest.raises(InputError, match="unknown kind"):
        degrade_input(tiny_scene[0], tmp_path / "x", "blur", 1)
    with pytest.raises(InputError, match="amount"):
        degrade_input(tiny_scene[0], tmp_path / "x", "pose_rot", float("nan"))


def test_far_cameras_get_new_ground_truth(tiny_scene, tmp_path):
    src = tiny_scene[0]
    far = degrade_input(src, tmp_path / "far", "far_camera", 1.0)
    a = cameras_from_json(src / "gt" / "test_cameras.json")
    b = cameras_from_json(far / "gt" / "test_cameras.json")
    for name in a:
        assert np.linalg.norm(a[name].center - b[name].center) == pytest.approx(1.0, abs=1e-6)
        old = read_image(src / "gt" / "test" / "images" / name)
        new = read_image(far / "gt" / "test" / "images" / name)
        assert np.abs(old - new).mean() > 0.01  # re-rendered from the new viewpoint
        with np.load(far / "gt" / "test" / "geom" / f"{name[:-4]}.npz") as z:
            assert z["depth"].shape == old.shape[:2]
