"""render_views + evaluate through the runner/CLI on a workspace built from ground truth, the
`ibr render` command, and bad input."""
import json
import shutil

import numpy as np
import pytest

from ibr_pipeline import layout as L
from ibr_pipeline.cli import main
from ibr_pipeline.errors import InputError
from ibr_pipeline.io.images import read_image
from ibr_pipeline.gt_workspace import write_gt_workspace
from ibr_pipeline.render.ibr import RenderSettings
from ibr_pipeline.workspace import Workspace


@pytest.fixture(scope="module")
def gt_ws(tiny_scene, tmp_path_factory):
    ws = tmp_path_factory.mktemp("render") / "ws"
    write_gt_workspace(tiny_scene[0], ws, "reflection", global_mesh="none")
    return ws


def test_render_views_and_evaluate_through_cli(gt_ws, tiny_scene):
    assert main(["-q", "render_views", str(gt_ws), "--no-progress"]) == 0
    tim = json.loads((gt_ws / "renders" / "test" / "timings.json").read_text())
    assert tim["source"] == "heldout" and len(tim["frames"]) == 2 and tim["layers"]
    assert not (gt_ws / "renders" / "loo").exists()  # leave_one_out is off by default
    for s, n in (("test", 2), ("test_single", 2), ("fly", 4), ("fly_single", 4), ("tour", 96)):
        pngs = sorted((gt_ws / "renders" / s).glob("*.png"))
        assert len(pngs) == n, s
        img = read_image(pngs[0])
        assert img.shape == (120, 160, 3) and img.max() > 0.1
    assert main(["-q", "evaluate", str(gt_ws), "--no-progress"]) == 0
    m = json.loads((gt_ws / "eval" / "metrics.json").read_text())
    s = m["summary"]
    # built from GT, "ours" is the oracle representation: identical scores, and a sane PSNR
    assert s["psnr"] > 20.0 and abs(s["oracle_gap_db"]) < 0.05
    assert 0 < s["ssim"] <= 1 and 0 <= s["flip"] <= 1
    assert s["fly_flicker_error"] >= 0 and "single_psnr" in s
    assert (gt_ws / "eval" / "metrics.png").stat().st_size > 1000
    import imageio.v2 as imageio
    with imageio.get_reader(str(gt_ws / "eval" / "fly.mp4"), format="FFMPEG") as r:
        assert r.get_meta_data()["duration"] >= 3.9  # the 96-frame tour at 24 fps, watchable
    sbs = read_image(gt_ws / "eval" / "side_by_side" / "0000.png")
    assert sbs.shape == (120, 4 * 160, 3)
    # a rerun is up to date
    assert main(["-q", "render_views", str(gt_ws), "--no-progress"]) == 0


def test_evaluate_in_workers_gives_the_same_figures(gt_ws):
    """--jobs 2 scores the held-out views and builds the oracle in worker processes: every figure
    of metrics.json but the naive warp's frame time is that of the in-process run."""
    def figures(m):
        m = dict(m)
        m["summary"] = {k: v for k, v in m["summary"].items() if k != "naive_ms"}
        return m
    assert main(["-q", "render_views", str(gt_ws), "--no-progress"]) == 0
    assert main(["-q", "evaluate", str(gt_ws), "--no-progress", "--force"]) == 0
    one = json.loads((gt_ws / "eval" / "metrics.json").read_text())
    assert main(["-q", "evaluate", str(gt_ws), "--no-progress", "--force", "--jobs", "2"]) == 0
    two = json.loads((gt_ws / "eval" / "metrics.json").read_text())
    assert len(one["per_view"]) == 2 and "oracle" in one["methods"] and "flip_mask" in one["methods"]["ours"]
    assert figures(two) == figures(one)


def test_render_views_in_workers_gives_the_same_renders(gt_ws):
    """--jobs 2 renders the sets in two worker processes (the single-layer model built from the
    layered one there): every frame's pixels, selected views and holes are the in-process run's."""
    def frames():
        out = {}
        for d in sorted(p for p in (gt_ws / "renders").iterdir() if p.is_dir()):
            t = json.loads((d / "timings.json").read_text())
            out[d.name] = ([(f["name"], f["selected"], f["holes"]) for f in t["frames"]],
                           [read_image(p) for p in sorted(d.glob("*.png"))])
        return out
    loo = ["--leave-one-out", "true"]
    assert main(["-q", "render_views", str(gt_ws), "--no-progress", "--force"] + loo) == 0
    one = frames()
    assert main(["-q", "render_views", str(gt_ws), "--no-progress", "--force", "--jobs", "2"]
                + loo) == 0
    two = frames()
    assert sorted(one) == sorted(two) and {"test_single", "loo"} <= set(one)
    assert len(one["loo"][1]) == 8 and all(n not in sel for n, sel, _ in one["loo"][0])
    assert json.loads((gt_ws / "renders" / "test" / "timings.json").read_text())["processes"] == 2
    for s in one:
        assert one[s][0] == two[s][0], s
        assert all(np.array_equal(a, b) for a, b in zip(one[s][1], two[s][1])), s


def test_single_layer_model_from_the_layered_one_is_the_loaded_one(gt_ws):
    from ibr_pipeline.render.ibr import IBRModel
    from ibr_pipeline.render.sets import single_layer_of
    ws = Workspace(gt_ws)
    layered = IBRModel.load(ws, layers=True)
    loaded = IBRModel.load(ws, layers=False)
    built = single_layer_of(ws, layered)
    assert layered.has_layer1 and not built.has_layer1 and built.names == loaded.names
    assert any(a is not b for a, b in zip(built.views, layered.views))  # reflective views reloaded
    for a, b in zip(built.views, loaded.views):
        assert a.layers[1] is None and b.layers[1] is None
        for f in ("vertices", "faces", "rgb", "alpha"):
            assert np.array_equal(getattr(a.layers[0], f), getattr(b.layers[0], f)), (a.name, f)
    for m in (layered, loaded, built):
        m.release()


def test_ibr_render_command(gt_ws, tmp_path, capsys):
    out = tmp_path / "fly"
    assert main(["render", str(gt_ws), "--path", "fly", "--out", str(out), "--no-progress"]) == 0
    t = json.loads((out / "timings.json").read_text())
    assert len(t["frames"]) == 4 and all(f["ms"] > 0 for f in t["frames"])
    assert (out / "video.mp4").is_file() and len(list(out.glob("*.png"))) == 4
    cams = tmp_path / "cams.json"
    shutil.copy(tiny_scene_cameras(gt_ws), cams)
    assert main(["render", str(gt_ws), "--cameras", str(cams), "--frames", "1",
                 "--out", str(tmp_path / "c"), "--no-progress"]) == 0
    assert len(list((tmp_path / "c").glob("*.png"))) == 1


def tiny_scene_cameras(ws):
    import tomllib
    root = tomllib.loads((ws / "ibr.toml").read_text())["input"]["path"]
    return f"{root}/gt/test_cameras.json"


def test_supersample_without_model_exits_2(gt_ws, tmp_path, capsys):
    rc = main(["render", str(gt_ws), "--heldout", "--supersample", "--out", str(tmp_path / "s")])
    assert rc == 2
    assert "supersample" in capsys.readouterr().err.lower()
    assert not (tmp_path / "s").exists()


def test_bad_input_is_one_line_and_writes_nothing(tiny_scene, tmp_path, capsys):
    ws = tmp_path / "bad"
    write_gt_workspace(tiny_scene[0], ws, "view_mesh", global_mesh="none")
    (ws / "views" / "0003.png" / "mesh.ply").write_bytes(b"ply\nnot a mesh")
    assert main(["render_views", str(ws), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "mesh.ply" in err
    assert not (ws / "renders").exists() or not list((ws / "renders").rglob("*.png"))
    assert main(["render_views", str(ws), "--renderer.delta", "-1"]) == 2
    assert "render_views.renderer.delta" in capsys.readouterr().err


def test_single_layer_workspace_renders(tiny_scene, tmp_path):
    ws = tmp_path / "one"
    write_gt_workspace(tiny_scene[0], ws, "view_mesh", global_mesh="none")
    from ibr_pipeline.render.ibr import IBRModel
    from ibr_pipeline.scene import cameras_from_json
    from ibr_pipeline.workspace import Workspace
    model = IBRModel.load(Workspace(ws), layers=True)  # no reflection outputs: single layer
    assert not model.has_layer1
    cam = cameras_from_json(tiny_scene[0] / "cameras.json")["0002.png"]
    f = model.render(cam, exclude=("0002.png",))
    assert f.color.shape == (120, 160, 3) and np.isfinite(f.color).all() and "0002.png" not in f.selected
    model.release()


def test_without_reflection_layers_single_sets_are_the_layered_renders(tiny_scene, tmp_path):
    """No view has a second layer: `<set>_single` is copied from `<set>`, and is what the
    single-layer model renders."""
    ws = tmp_path / "nolayers"
    write_gt_workspace(tiny_scene[0], ws, "view_mesh", global_mesh="none")
    assert main(["-q", "render_views", str(ws), "--no-progress"]) == 0
    for s in ("test", "fly"):
        a, b = sorted((ws / "renders" / s).glob("*.png")), sorted((ws / "renders" / f"{s}_single").glob("*.png"))
        assert len(a) == len(b) > 0 and all(x.read_bytes() == y.read_bytes() for x, y in zip(a, b))
        t = json.loads((ws / "renders" / f"{s}_single" / "timings.json").read_text())
        assert t["set"] == f"{s}_single" and t["copied_from"] == s and not t["layers"]
    from ibr_pipeline.render.ibr import IBRModel
    from ibr_pipeline.scene import cameras_from_json
    from ibr_pipeline.workspace import Workspace
    cam = next(iter(cameras_from_json(ws / "renders" / "test_single" / "cameras.json").values()))
    model = IBRModel.load(Workspace(ws), layers=False)
    f = model.render(cam)
    model.release()
    got = read_image(ws / "renders" / "test_single" / "0000.png")
    assert np.abs(np.clip(f.color, 0, 1) - got).max() < 2.0 / 255


def test_leave_one_out_when_input_has_no_test_cameras(tiny_scene, tmp_path):
    src = tmp_path / "input"
    shutil.copytree(tiny_scene[0], src)
    (src / "gt" / "test_cameras.json").unlink()
    (src / "gt" / "flythrough_cameras.json").unlink()
    ws = tmp_path / "ws"
    write_gt_workspace(src, ws, "reflection", global_mesh="none")
    assert main(["-q", "render_views", str(ws), "--no-progress", "--fly-frames", "3",
                 "--leave-one-out", "false"]) == 0
    tim = json.loads((ws / "renders" / "test" / "timings.json").read_text())
    assert tim["source"] == "leave_one_out" and len(tim["frames"]) == 8
    assert all(f["name"] not in f["selected"] for f in tim["frames"])  # a view never renders itself
    assert json.loads((ws / "renders" / "fly" / "timings.json").read_text())["source"] == "interpolated"
    assert not (ws / "renders" / "loo").exists()
    assert main(["-q", "evaluate", str(ws), "--no-progress", "--flip", "false"]) == 0
    m = json.loads((ws / "eval" / "metrics.json").read_text())
    assert m["source"] == "leave_one_out" and m["summary"]["psnr"] > 8.0
    assert "flip" not in m["summary"] and "gt_frame_change" not in m["temporal"]["ours"]


def test_reflection_energy_chart(tmp_path):
    """evaluate's convergence chart (Xu Fig. 11) reads the Eq. 7 energies that the reflection
    stage records per step; views without a decomposition add no line; bad JSON is one error."""
    from ibr_pipeline.errors import InputError
    from ibr_pipeline.stages import evaluate as ev
    from ibr_pipeline.workspace import Workspace

    hist = [{"step": "init", "warp_energy": {}}, {"step": "start", "energy": 2.0},
            {"step": "image", "energy": 1.2}, {"step": "pose", "energy": 1.1},
            {"step": "end", "energy": 1.1}]
    for view, layers in (("a.png", {"reflectors": [{"name": "tv", "history": hist},
                                                   {"name": "mirror", "history": []}]}),
                         ("b.png", {"reflector": None})):
        (tmp_path / "views" / view).mkdir(parents=True)
        (tmp_path / "views" / view / "layers.json").write_text(json.dumps(layers))
    ws = Workspace(tmp_path)
    h = ev._energy_histories(ws)
    assert h == {("a.png", "tv", 1): [2.0, 1.2, 1.1, 1.1]}
    ev._energy_chart(tmp_path / "e.png", h)
    assert read_image(tmp_path / "e.png").shape[2] == 3
    (tmp_path / "views" / "b.png" / "layers.json").write_text("{")
    with pytest.raises(InputError, match="b.png"):
        ev._energy_histories(ws)


def test_render_cameras_in_every_format(gt_ws, tmp_path):
    """The same cameras as our cameras.json, a nerfstudio transforms.json and a camera_path.json
    render the same frames (the tiny scene's cameras are centred and square, which camera_path
    requires)."""
    from ibr_pipeline.io.nerfstudio import write_camera_path, write_transforms
    from ibr_pipeline.scene import cameras_from_json
    cams = cameras_from_json(tiny_scene_cameras(gt_ws))
    files = {"json": tmp_path / "cams.json", "transforms": tmp_path / "transforms.json",
             "path": tmp_path / "camera_path.json"}
    shutil.copy(tiny_scene_cameras(gt_ws), files["json"])
    # as `ibr export` writes it: image paths lead out of the json's folder; only cameras are read
    write_transforms(cams, files["transforms"], image_prefix="../../elsewhere/images/")
    write_camera_path([cams[n] for n in sorted(cams)], files["path"])
    frames = {}
    for k, f in files.items():
        out = tmp_path / k
        assert main(["render", str(gt_ws), "--cameras", str(f), "--out", str(out), "--no-progress"]) == 0
        frames[k] = [read_image(p) for p in sorted(out.glob("*.png"))]
        assert len(frames[k]) == len(cams)
    order = sorted(cams)  # cameras.json keeps its order; transforms.json sorts by name
    by_name = dict(zip(list(cams), frames["json"]))
    for i, n in enumerate(order):
        assert np.abs(frames["transforms"][i] - by_name[n]).max() <= 1 / 255 + 1e-6
        assert np.abs(frames["path"][i] - by_name[n]).max() <= 1 / 255 + 1e-6
    assert (tmp_path / "path" / "video.mp4").is_file()  # a camera path is a sequence


def test_supersample_trains_on_the_render_views_settings(tiny_scene, tmp_path, capsys):
    """render_views writes the settings it rendered with; supersample's leave-one-out renderer
    loads them (and lists the file as an input), so DSRNet learns the renders it will upsample."""
    from ibr_pipeline.render.ibr import stored_settings
    from ibr_pipeline.render.low_res import IBRRenderer
    from ibr_pipeline.runner import StageContext
    from ibr_pipeline.stages import supersample
    ws_dir = tmp_path / "ws"
    write_gt_workspace(tiny_scene[0], ws_dir, "reflection", global_mesh="none")
    ws = Workspace(ws_dir)
    assert stored_settings(ws) == RenderSettings()  # before render_views: the defaults
    assert main(["-q", "render_views", str(ws_dir), "--no-progress", "--fly-frames", "2",
                 "--renderer.per-view-max", "3", "--renderer.blend-space", "linear"]) == 0
    s = stored_settings(ws)
    assert (s.per_view_max, s.blend_space, s.visibility) == (3, "linear", "fuzzy")  # auto resolved
    r = IBRRenderer(ws)
    assert r.model.settings == s
    r.model.release()
    ctx = StageContext(ws, "supersample", supersample.SupersampleConfig(), ws.scene())
    assert L.RENDER_SETTINGS in supersample.inputs(ctx)
    ws.path(L.RENDER_SETTINGS).write_text('{"per_view_max": 0}')
    with pytest.raises(InputError, match="settings.json: not render settings"):
        stored_settings(ws)
