"""Stage `poses` and geometry/scale.py: the scene frame is the same whatever units the input
uses, held-out images stay out of the reconstruction, the path check names the frames."""
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from ibr_pipeline.cli import main
from ibr_pipeline.geometry import scale
from ibr_pipeline.geometry.align import transform_reflector
from ibr_pipeline.io.images import read_image
from ibr_pipeline.io.inputs import read_input
from ibr_pipeline.scene import Reflector, cameras_from_json


# --- pure functions ---------------------------------------------------------------------------
def test_normalising_scale_is_equivariant():
    rng = np.random.default_rng(0)
    d = rng.uniform(0.5, 6.0, 500)
    s = scale.normalising_scale(d, 2.5)
    assert np.median(d * s) == pytest.approx(2.5, rel=1e-12)
    assert scale.normalising_scale(d * 1000, 2.5) == pytest.approx(s / 1000, rel=1e-12)
    with pytest.raises(ValueError, match="too few"):
        scale.normalising_scale(np.r_[d[:5], np.zeros(100), np.full(10, np.nan)], 2.5)


def test_path_jumps_names_the_jumps_and_only_them():
    t = np.linspace(0, 1, 30)
    smooth = np.c_[np.cos(3 * t), np.sin(3 * t), 0.1 * t]
    assert scale.path_jumps(smooth, 4.0) == []
    saw = smooth.copy()
    saw[12] += [1.0, 0, 0]   # one frame placed far off: two long steps, into it and out of it
    jumps = scale.path_jumps(saw, 4.0)
    assert [i for i, _ in jumps] == [11, 12] and all(r > 4 for _, r in jumps)


@pytest.mark.parametrize("names,expected", [
    (["frame_0001.jpg", "frame_0002.jpg", "frame_0003.jpg"], True),
    (["IMG_4026.JPG", "IMG_4027.JPG", "IMG_4031.JPG", "IMG_4032.JPG"], True),
    (["a.jpg", "b.jpg", "c.jpg"], False),
    (["img1.png", "shot2.png", "img3.png"], False),
    (["0001.png", "0500.png", "0990.png"], False),    # numbered, but not one sequence
])
def test_numbered_sequence(names, expected):
    assert scale.numbered_sequence(names) is expected


def test_holdout_is_the_llff_split():
    names = [f"{i:03d}.jpg" for i in range(20)]
    assert scale.holdout_names(names, 8) == ["000.jpg", "008.jpg", "016.jpg"]
    assert scale.holdout_names(names, 0) == []


def test_transform_reflector_keeps_points_on_the_plane():
    rng = np.random.default_rng(1)
    n = rng.normal(size=3)
    n /= np.linalg.norm(n)
    refl = Reflector("m", (*n, -0.7), polygon=tuple(map(tuple, rng.normal(size=(4, 3)))))
    # points on the plane: x = p0 + a u + b v
    p0 = 0.7 * n
    u = np.cross(n, [1, 0, 0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    pts = p0 + rng.normal(size=(50, 1)) * u + rng.normal(size=(50, 1)) * v
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    R = q * np.sign(np.linalg.det(q))
    s, t = 123.0, rng.normal(size=3)
    out = transform_reflector(refl, s, R, t)
    moved = s * pts @ R.T + t
    assert np.abs(moved @ np.asarray(out.plane[:3]) + out.plane[3]).max() < 1e-9 * s
    assert np.allclose(out.polygon, s * np.asarray(refl.polygon) @ R.T + t)


def test_triangulated_depths_match_the_true_depth(sample_scene):
    """SIFT matches triangulated with the exact poses land on the true surface: z-depth vs the
    scene's exact depth at the keypoint, median relative error <= 1 %."""
    scene = read_input(sample_scene)
    cams = {v.name: v.camera for v in scene.views[:8]}
    images = {n: read_image(sample_scene / "images" / n) for n in cams}
    got = scale.triangulate_given(images, cams, scale.neighbour_pairs(cams, k=2))
    errs = []
    for n, (uv, z) in got.items():
        with np.load(sample_scene / "gt" / "geom" / (Path(n).stem + ".npz")) as g:
            d = g["depth"].astype(np.float64)
        iu, iv = np.round(uv).astype(int).T
        errs.append(np.abs(z - d[iv, iu]) / d[iv, iu])
    e = np.concatenate(errs)
    assert len(e) >= 200, len(e)
    assert np.median(e) <= 0.01, np.median(e)


# --- the stage --------------------------------------------------------------------------------
def _rgb_input(src: Path, dst: Path, unit: float = 1.0, drop=("depth", "sparse", "gt")) -> Path:
    """`src` without depth frames (and without the COLMAP model), cameras.json and reflectors.json
    in units of `unit` metres."""
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns(*drop))
    p = dst / "cameras.json"
    data = json.loads(p.read_text())
    for c in data["cameras"].values():
        T = np.asarray(c["cam_from_world"])
        T[:3, 3] /= unit   # world coordinates in units of `unit` metres
        c["cam_from_world"] = T.tolist()
    p.write_text(json.dumps(data))
    r = dst / "reflectors.json"
    if r.is_file():
        data = json.loads(r.read_text())
        for refl in data["reflectors"]:
            refl["plane"][3] /= unit
            refl["polygon"] = (np.asarray(refl["polygon"]) / unit).tolist()
        r.write_text(json.dumps(data))
    return dst


def test_rgb_only_scene_is_normalised_whatever_the_units(sample_scene, tmp_path):
    """The same capture with its poses in metres and in millimetres gives the same normalised
    scene frame (cameras and the MVS global mesh), and the scale says how the units relate."""
    meshes, frames, cams = [], [], []
    for unit in (1.0, 0.001):
        inp = _rgb_input(sample_scene, tmp_path / f"in_{unit}", unit)
        ws = tmp_path / f"ws_{unit}"
        assert main(["run", str(ws), "--input", str(inp), "--until", "global_mesh", "--no-progress",
                     "--set", "global_mesh.mvs_scale=0.25"]) == 0
        frames.append(json.loads((ws / "global" / "poses.json").read_text()))
        cams.append(cameras_from_json(ws / "global" / "cameras.json"))
        from ibr_pipeline.io.mesh import read_ply
        meshes.append(read_ply(ws / "global" / "mesh.ply"))
    a, b = frames
    assert a["units"] == b["units"] == "normalised"
    assert a["median_scene_depth"] == pytest.approx(2.5) and b["median_scene_depth"] == pytest.approx(2.5)
    assert b["scale"] == pytest.approx(a["scale"] / 1000, rel=1e-6)   # float32 triangulation
    for n in cams[0]:
        assert np.allclose(cams[0][n].cam_from_world, cams[1][n].cam_from_world, atol=1e-6)
    # the meshes: same surface (vertex sets within 1e-4 of the scene depth of each other)
    from scipy.spatial import cKDTree
    va, vb = meshes[0].vertices, meshes[1].vertices
    assert abs(len(va) - len(vb)) <= 0.01 * len(va)
    d, _ = cKDTree(vb).query(va)
    assert np.quantile(d, 0.99) < 1e-4 * 2.5


def test_heldout_images_leave_the_reconstruction_and_become_the_test_set(tiny_scene, tmp_path):
    src = tmp_path / "input"
    shutil.copytree(tiny_scene[0], src, ignore=shutil.ignore_patterns("test_cameras.json"))
    ws = tmp_path / "ws"
    assert main(["run", str(ws), "--input", str(src), "--until", "render_views", "--no-progress",
                 "--set", "poses.holdout_every=4", "--set", "render_views.leave_one_out=false"]) == 0
    rep = json.loads((ws / "global" / "poses.json").read_text())
    assert rep["heldout"] == ["0000.png", "0004.png"]
    train = cameras_from_json(ws / "global" / "cameras.json")
    held = cameras_from_json(ws / "global" / "heldout_cameras.json")
    assert set(held) == {"0000.png", "0004.png"} and not set(held) & set(train)
    assert not (ws / "views" / "0000.png").exists() and (ws / "views" / "0001.png").is_dir()
    timings = json.loads((ws / "renders" / "test" / "timings.json").read_text())
    assert timings["source"] == "heldout_captures" and len(timings["frames"]) == 2
    assert main(["evaluate", str(ws), "--no-progress", "--flip", "false"]) == 0
    m = json.loads((ws / "eval" / "metrics.json").read_text())
    assert m["source"] == "heldout_captures"
    # the held-out photo is the reference: rendering from the others beats showing the nearest one
    assert m["summary"]["psnr"] > m["summary"]["nearest_psnr"], m["summary"]


def test_a_jump_in_the_camera_path_is_named(tiny_scene, tmp_path, capsys):
    src = tmp_path / "input"
    shutil.copytree(tiny_scene[0], src, ignore=shutil.ignore_patterns("sparse"))
    p = src / "cameras.json"
    data = json.loads(p.read_text())
    T = np.asarray(data["cameras"]["0005.png"]["cam_from_world"])
    T[:3, 3] -= T[:3, :3] @ np.array([8.0, 0, 0])   # move camera 5 eight metres along x
    data["cameras"]["0005.png"]["cam_from_world"] = T.tolist()
    p.write_text(json.dumps(data))
    ws = tmp_path / "ws"
    assert main(["run", str(ws), "--input", str(src), "--until", "poses", "--no-progress"]) == 0
    msg = next(line for line in capsys.readouterr().err.splitlines() if "jumps" in line)
    assert "0004.png -> 0005.png" in msg and "0005.png -> 0006.png" in msg, msg
    rep = json.loads((ws / "global" / "poses.json").read_text())
    assert [j["from"] for j in rep["path_jumps"]] == ["0004.png", "0005.png"]
