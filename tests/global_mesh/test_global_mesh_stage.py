"""Stage `global_mesh` through the CLI on the `tiny` scene: accuracy vs gt/mesh.ply, reflectors,
bad input."""
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from ibr_pipeline.cli import main
from ibr_pipeline.geometry.fusion import mirror_world_points
from ibr_pipeline.geometry.mesh_metrics import fscore, observed_points
from ibr_pipeline.io.mesh import read_ply
from ibr_pipeline.io.inputs import read_input


def _evaluate(ws: Path, scene_dir: Path):
    scene = read_input(scene_dir)
    cams = [v.camera for v in scene.views]
    depths = [np.load(scene_dir / "gt" / "geom" / (Path(v.name).stem + ".npz"))["depth"] for v in scene.views]
    gt = read_ply(scene_dir / "gt" / "mesh.ply")
    mesh = read_ply(ws / "global" / "mesh.ply")
    mirror = lambda p: mirror_world_points(p, scene.reflectors, cams)  # noqa: E731
    res = fscore(mesh.vertices, mesh.faces, gt.vertices, gt.faces, observed_points(cams, depths),
                 tau=0.05, n_samples=30000, exclude=mirror)
    res["mirror_world_fraction"] = float(mirror(mesh.vertices).mean())
    return res


def test_rgbd_fusion_with_reflectors_is_accurate(tiny_scene, tmp_path):
    scene_dir = tiny_scene[0]
    ws = tmp_path / "ws"
    assert main(["run", str(ws), "--input", str(scene_dir), "--until", "global_mesh",
                 "--set", "global_mesh.progress=false"]) == 0
    rep = json.loads((ws / "global" / "report.json").read_text())
    poses = json.loads((ws / "global" / "poses.json").read_text())
    assert rep["units"] == poses["units"] == "metres" and poses["scale"] == 1.0
    assert poses["unregistered"] == [] and len(poses["registered"]) == 8
    assert rep["counts"]["reflector_pixels"] > 0
    # voxel_size 0 (default) = auto: a 5 mm multiple in the allowed range, recorded as auto
    v = rep["voxel_size"]
    assert v["auto"] and 0.005 <= v["value"] <= 0.05 and abs(v["value"] / 0.005 - round(v["value"] / 0.005)) < 1e-9
    for f in ("sfm/cameras.txt", "sfm/images.txt", "global/cameras.json"):
        assert (ws / f).is_file()
    res = _evaluate(ws, scene_dir)
    assert res["fscore"] >= 0.90, res          # F-score at 5 cm >= 0.90 with RGB-D
    assert res["mirror_world_fraction"] < 0.01, res


def test_without_reflectors_mirror_world_is_kept_and_reported(tiny_scene, tmp_path):
    src = tmp_path / "input"
    shutil.copytree(tiny_scene[0], src, ignore=shutil.ignore_patterns("reflectors.json"))
    ws = tmp_path / "ws"
    assert main(["run", str(ws), "--input", str(src), "--until", "global_mesh",
                 "--set", "global_mesh.progress=false"]) == 0
    rep = json.loads((ws / "global" / "report.json").read_text())
    assert rep["mirror_world"].startswith("NOT masked")
    # the depth sensor saw the mirror world, and it is in the mesh (documented behaviour)
    res = _evaluate(ws, tiny_scene[0])
    assert res["mirror_world_fraction"] > 0.02, res


def test_depth_count_mismatch_is_a_clean_error(tiny_scene, tmp_path, capsys):
    src = tmp_path / "input"
    shutil.copytree(tiny_scene[0], src)
    (src / "depth" / "0003.png").unlink()
    ws = tmp_path / "ws"
    code = main(["run", str(ws), "--input", str(src), "--until", "global_mesh",
                 "--set", "global_mesh.dense=rgbd", "--set", "global_mesh.progress=false"])
    err = capsys.readouterr().err
    assert code == 2 and "0003.png" in err.strip().splitlines()[-1]
    assert "7 of 8 images have a depth frame" in err.strip().splitlines()[-1]
    # refused at ingest, before any stage wrote: a partial set must not switch the dense method
    assert not (ws / "scene.json").exists() and not (ws / "global").exists()


@pytest.mark.parametrize("value", ["-1", "1e-6"])
def test_absurd_config_is_rejected(tiny_scene, tmp_path, capsys, value):
    ws = tmp_path / "ws"
    code = main(["run", str(ws), "--input", str(tiny_scene[0]), "--set", f"global_mesh.fusion.voxel_size={value}"])
    assert code == 2 and "global_mesh.fusion.voxel_size" in capsys.readouterr().err


@pytest.mark.slow
def test_sfm_recovers_poses_on_synthetic_scene(tmp_path):
    """SfM (forced) on a 640x480 mirror_room with 40 views: poses vs the exact cameras."""
    from ibr_pipeline.geometry.align import pose_errors
    from ibr_pipeline.synthetic.generate import SynthOptions, generate
    from ibr_pipeline.scene import cameras_from_json
    out = tmp_path / "mr"
    opts = SynthOptions("mirror_room", seed=0, views=40, test_views=1, flythrough=2, jobs=1,
                        progress=False)
    generate(opts, out)
    ws = tmp_path / "ws"
    assert main(["run", str(ws), "--input", str(out), "--until", "global_mesh",
                 "--set", "poses.force_sfm=true", "--set", "poses.matching=sequential",
                 "--set", "global_mesh.progress=false"]) == 0
    rep = json.loads((ws / "global" / "poses.json").read_text())
    assert rep["pose_source"] == "sfm" and rep["units"] == "metres"
    est = cameras_from_json(ws / "global" / "cameras.json")
    truth = cameras_from_json(out / "cameras.json")
    err = pose_errors(est, truth)
    assert err["rotation_deg"]["median"] <= 0.5 and err["center_m"]["median"] <= 0.05
    assert len(est) >= 0.3 * len(truth)


def test_a_reflector_given_by_its_outline_in_one_photo_is_placed(sample_scene, tmp_path):
    """reflectors.json with the TV screen's corners in one image instead of its plane (the only
    reflector of the sample some view sees whole): global_mesh fits the plane to the depth around
    the outline, moves it onto the screen that stands proud of the wall, and masks with it."""
    from ibr_pipeline.geometry.user_reflectors import user_reflectors
    from ibr_pipeline.scene import Scene
    from ibr_pipeline.workspace import Workspace
    src = tmp_path / "input"
    shutil.copytree(sample_scene, src, ignore=shutil.ignore_patterns("gt"))
    true = {r.name: r for r in read_input(sample_scene).reflectors}
    tv = true["tv_screen"]
    view = next(v for v in read_input(sample_scene).views if v.name == "0007.png")
    uv, z = view.camera.project(np.asarray(tv.polygon))
    assert np.all(z > 0) and np.all(uv > 10) and np.all(uv < [310, 230])  # seen whole
    (src / "reflectors.json").write_text(json.dumps({"reflectors": [
        {"name": "tv", "outline": {"view": "0007.png", "points": uv.tolist()}}]}))
    ws = tmp_path / "ws"
    assert main(["run", str(ws), "--input", str(src), "--until", "global_mesh",
                 "--set", "global_mesh.progress=false"]) == 0
    placed = user_reflectors(Workspace(ws), Scene.from_json((ws / "scene.json").read_text()))[0]
    n = np.asarray(placed.plane[:3])
    assert np.degrees(np.arccos(min(1.0, abs(n @ tv.normal)))) < 1.0
    corners = np.asarray(tv.polygon)
    assert np.abs(corners @ n + placed.plane[3]).max() < 0.01     # on the screen, not the wall
    assert np.abs(np.asarray(placed.polygon) - corners).max() < 0.03
    assert json.loads((ws / "global" / "report.json").read_text())["counts"]["reflector_pixels"] > 0
