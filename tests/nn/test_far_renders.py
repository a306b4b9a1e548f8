"""`supersample.exclude_nearest` (renders from farther source views, our extension beyond §6) and
the mirror-image self-ensemble of inference (`nn.infer.run_network`)."""
import json

import numpy as np
import pytest
import torch

from ibr_pipeline.cli import main
from ibr_pipeline.gt_workspace import write_gt_workspace
from ibr_pipeline.nn.data import low_res_camera, nearest_views
from ibr_pipeline.nn.infer import run_network
from ibr_pipeline.nn.model import DSRNet, preset
from ibr_pipeline.render.low_res import IBRRenderer
from ibr_pipeline.scene import Camera
from ibr_pipeline.layout import registered_cameras
from ibr_pipeline.workspace import Workspace


@pytest.fixture(scope="module")
def gt_ws(tiny_scene, tmp_path_factory):
    ws = tmp_path_factory.mktemp("far") / "ws"
    write_gt_workspace(tiny_scene[0], ws, "reflection", global_mesh="none")
    return ws


def _cam(x: float) -> Camera:
    K = np.array([[50.0, 0, 16], [0, 50.0, 12], [0, 0, 1]])
    T = np.eye(4)
    T[0, 3] = -x  # centre at (x, 0, 0)
    return Camera(K, T, 32, 24)


def test_nearest_views_by_optical_centre():
    cams = {n: _cam(x) for n, x in (("a", 0.0), ("b", 1.0), ("c", 0.4), ("d", -0.2), ("e", 3.0))}
    near = nearest_views(cams, ["a", "e"], 2)
    assert near == {"a": ["d", "c"], "e": ["b", "c"]}
    assert nearest_views(cams, ["b"], 0) == {"b": []}
    assert nearest_views(cams, ["b"], 10)["b"] == ["c", "a", "d", "e"]  # all the others, no self
    with pytest.raises(ValueError):
        nearest_views(cams, ["a"], -1)


def test_far_render_leaves_out_the_nearest_views(gt_ws):
    ws = Workspace(gt_ws)
    cams = registered_cameras(ws)
    names = sorted(cams)
    r = IBRRenderer(ws)
    cover = {m: (r(m, low_res_camera(cams[m], 2))[1] > 0).mean() for m in names}
    n = max(names, key=cover.get)  # tiny's 8 views are far apart: the best-covered one
    cam = low_res_camera(cams[n], 2)
    col, dep = r(n, cam)
    col_far, dep_far = r.excluding(nearest_views(cams, [n], 1))(n, cam)
    assert (dep > 0).mean() > 0.2
    assert (dep_far > 0).mean() <= (dep > 0).mean()     # fewer sources cover no more
    assert np.abs(col_far - col).mean() > 1e-3          # other sources, another image
    with pytest.raises(ValueError, match="every view is excluded"):
        r.excluding({n: [m for m in names if m != n]})(n, cam)
    col_again, _ = r(n, cam)                            # the original renderer is unchanged
    np.testing.assert_array_equal(col_again, col)


def test_stage_trains_on_far_renders_of_training_views(gt_ws):
    fast = ["--train.steps", "2", "--train.batch", "2", "--train.crop", "16", "--train.checkpoint-every", "2",
            "--train.threads", "1", "--no-progress", "--time-budget-s", "0"]
    assert main(["-q", "supersample", str(gt_ws), "--exclude-nearest", "2"] + fast) == 0
    rep = json.loads((gt_ws / "nn" / "train.json").read_text())
    assert rep["exclude_nearest"] == 2 and rep["far_pairs"] > 0
    assert rep["train_pairs"] == 2 * rep["far_pairs"]   # one far pair per leave-one-out pair
    assert [s for s, _ in rep["val_curve"]] == [2]      # validated at the last step
    assert not (gt_ws / "nn" / "cache").exists()
    # the trained net through `ibr render`, with the mirror-image self-ensemble
    out = gt_ws / "renders" / "cli_se"
    assert main(["render", str(gt_ws), "--heldout", "--supersample", "--self-ensemble",
                 "--frames", "2", "--out", str(out), "--no-progress"]) == 0
    tim = json.loads((out / "timings.json").read_text())
    assert tim["supersample"] and tim["self_ensemble"] and len(tim["frames"]) == 2
    assert main(["render", str(gt_ws), "--heldout", "--self-ensemble"]) == 2  # needs --supersample
    # auto: DSRNet only when the measured figures on its validation views say so
    from ibr_pipeline.nn.infer import prefer_dsrnet
    out = gt_ws / "renders" / "cli_auto"
    assert main(["render", str(gt_ws), "--heldout", "--supersample", "auto", "--frames", "1",
                 "--out", str(out), "--no-progress"]) == 0
    tim = json.loads((out / "timings.json").read_text())
    ch = tim["supersample_choice"]
    assert ch["views"] == rep["val_views"][:2] and ch["direct_ms"] > 0 and ch["dsrnet_ms"] > 0
    assert tim["supersample"] == ch["use"] == prefer_dsrnet(ch["direct_ms"], ch["dsrnet_ms"],
                                                            ch["direct_psnr"], ch["dsrnet_psnr"])[0]
    # the same views through DSRNet: what the stage's own validation measured (another code path)
    assert abs(ch["dsrnet_psnr"] - rep["validation"]["psnr"]) < 0.05, (ch, rep["validation"])
    # leaving out every other view is a bad value, named before anything is rendered
    assert main(["-q", "supersample", str(gt_ws), "--exclude-nearest", "7"] + fast) == 2


def test_standin_renderer_rejects_exclude_nearest(tiny_scene, tmp_path, capsys):
    ws = tmp_path / "ws"
    assert main(["init", str(ws), "--input", str(tiny_scene[0])]) == 0
    assert main(["supersample", str(ws), "--renderer", "standin", "--exclude-nearest", "3"]) == 2
    assert "exclude_nearest" in capsys.readouterr().err
    assert not (ws / "nn").exists()


def _inputs(rng, h=12, w=16):
    t = lambda *s: torch.from_numpy(rng.random(s, dtype=np.float32))  # noqa: E731
    flow = torch.from_numpy(rng.normal(0, 2, (1, 2, h, w)).astype(np.float32))
    return t(1, 3, h, w), t(1, 1, h, w) + 1, t(1, 3, h, w), t(1, 1, h, w) + 1, flow


def _mirror(cur, depth, prev, depth_prev, flow):
    f = lambda x: torch.flip(x, dims=[3])  # noqa: E731
    return f(cur), f(depth), f(prev), f(depth_prev), f(flow) * torch.tensor([-1.0, 1.0]).view(1, 2, 1, 1)


def test_self_ensemble_is_mirror_equivariant():
    torch.manual_seed(0)
    model = DSRNet(preset("cpu")).eval()
    with torch.no_grad():  # perturb the zero-initialised last layers so the net is not trivial
        for p in model.parameters():
            p.add_(0.05 * torch.randn_like(p))
    x = _inputs(np.random.default_rng(1))
    flip = lambda y: torch.flip(y, dims=[3])  # noqa: E731
    with torch.no_grad():
        plain, plain_m = model(*x)["image"], model(*_mirror(*x))["image"]
        ens, ens_m = run_network(model, *x, self_ensemble=True), run_network(
            model, *_mirror(*x), self_ensemble=True)
        assert torch.allclose(run_network(model, *x), plain)
    # the net alone is not mirror-equivariant, its self-ensemble is (to float rounding)
    assert (flip(plain_m) - plain).abs().max() > 1e-3
    assert (flip(ens_m) - ens).abs().max() < 1e-5
    assert torch.allclose(ens, 0.5 * (plain + flip(plain_m)), atol=1e-5)


def test_prefer_dsrnet_rule():
    from ibr_pipeline.nn.infer import prefer_dsrnet
    assert prefer_dsrnet(10.0, 50.0, 30.0, 30.1)[0]          # better, even if slower
    ok, why = prefer_dsrnet(10.0, 5.0, 30.0, 29.6)
    assert ok and "faster" in why                            # faster, within 0.5 dB
    ok, why = prefer_dsrnet(10.0, 5.0, 30.0, 29.0)
    assert not ok and "worse" in why                         # faster but 1 dB worse
    ok, why = prefer_dsrnet(5.0, 10.0, 30.0, 29.9)
    assert not ok and "slower" in why and "full resolution" in why
