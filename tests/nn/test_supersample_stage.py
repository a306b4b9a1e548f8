"""Stage `supersample` through the CLI/runner, SuperSampler, and bad input.

The stage's real low-res renderer is the render_views IBR model; these tests use `--renderer
standin` (synthetic GT with IBR-like artefacts), so the stage is tested without the stages before
it."""
import json
import shutil

import numpy as np
import pytest

from ibr_pipeline.cli import main
from ibr_pipeline.errors import InputError
from ibr_pipeline.nn.infer import SuperSampler
from ibr_pipeline.scene import cameras_from_json
from ibr_pipeline.workspace import Workspace

FAST = ["--renderer", "standin", "--train.steps", "4", "--train.batch", "2", "--train.crop", "24",
        "--train.checkpoint-every", "2", "--train.threads", "1", "--no-progress"]


@pytest.fixture
def ws(tiny_scene, tmp_path):
    """A workspace of `tiny` after ingest, with the exact poses as `global/cameras.json`."""
    src = tiny_scene[0]
    ws = tmp_path / "ws"
    assert main(["init", str(ws), "--input", str(src)]) == 0
    assert main(["ingest", str(ws), "--no-progress"]) == 0
    (ws / "global").mkdir()
    shutil.copy(src / "cameras.json", ws / "global" / "cameras.json")
    return ws


def test_stage_runs_and_sampler_uses_it(ws, tiny_scene):
    assert main(["supersample", str(ws)] + FAST) == 0
    for f in ("dsrnet.pt", "train.json", "loss.png"):
        assert (ws / "nn" / f).is_file()
    assert not (ws / "nn" / "checkpoint.pt").exists() and not (ws / "nn" / "cache").exists()
    rep = json.loads((ws / "nn" / "train.json").read_text())
    assert rep["steps"] == 4 and rep["val_views"] and not set(rep["val_views"]) & set(rep["train_views"])
    assert rep["validation"]["psnr"] > 15
    # up to date: a second run does nothing
    assert main(["supersample", str(ws)] + FAST) == 0
    # SuperSampler: API of docs/PIPELINE.md
    from ibr_pipeline.io.images import read_image
    from ibr_pipeline.render.low_res import StandInRenderer
    cams = cameras_from_json(tiny_scene[0] / "cameras.json")
    r = StandInRenderer(tiny_scene[0])
    sampler = SuperSampler.load(Workspace(ws), device="cpu")
    sampler.reset()
    for name in ("0001.png", "0002.png"):
        lr_cam = cams[name].resized(80, 60)
        color, depth = r(name, lr_cam)
        hr = sampler(color, depth, lr_cam)
        assert hr.shape == (120, 160, 3) and hr.dtype == np.float32
        assert 0 <= hr.min() and hr.max() <= 1
        gt = read_image(tiny_scene[0] / "images" / name)
        assert np.abs(hr - gt).mean() < 0.1
    with pytest.raises(ValueError, match="depth"):
        sampler(color, depth[:, :10], lr_cam)
    with pytest.raises(ValueError, match="NaN"):
        sampler(np.full_like(color, np.nan), depth, lr_cam)


def test_bad_config_and_missing_inputs_write_nothing(ws, capsys):
    assert main(["supersample", str(ws), "--train.steps", "0", "--no-progress"]) == 2
    assert "supersample.train.steps" in capsys.readouterr().err
    assert main(["supersample", str(ws), "--preset", "huge", "--no-progress"]) == 2
    assert main(["supersample", str(ws), "--train.vgg-weights", "nope.pt"] + FAST) == 2
    assert "vgg_weights" in capsys.readouterr().err
    assert not (ws / "nn" / "dsrnet.pt").exists()


def test_real_renderer_needs_view_meshes(ws):
    """With the default renderer (the render_views IBR model) the stage needs the per-view meshes and
    edges: without them it is blocked (missing input) and writes nothing."""
    rc = main(["supersample", str(ws), "--train.steps", "2", "--no-progress"])
    assert rc != 0
    assert not (ws / "nn" / "dsrnet.pt").exists()


def test_sampler_missing_model(tmp_path):
    with pytest.raises(InputError, match="no trained DSRNet"):
        SuperSampler.load(Workspace(tmp_path))
    (tmp_path / "nn").mkdir()
    (tmp_path / "nn" / "dsrnet.pt").write_bytes(b"garbage")
    with pytest.raises(InputError, match="cannot read"):
        SuperSampler.load(Workspace(tmp_path))


def test_help_lists_the_config():
    with pytest.raises(SystemExit) as e:
        main(["supersample", "--help"])
    assert e.value.code == 0


def test_stage_mixes_capture_pairs_of_training_views_only(ws):
    assert main(["supersample", str(ws), "--train.capture-fraction", "0.5", "--train.warmup-steps", "2"]
                + FAST) == 0
    rep = json.loads((ws / "nn" / "train.json").read_text())
    assert rep["capture_fraction"] == 0.5 and rep["capture_pairs"] == rep["train_pairs"] > 0
    assert rep["val_views"] and not set(rep["val_views"]) & set(rep["train_views"])
    assert rep["validation"]["psnr"] > 15


def test_fingerprint_leaves_out_run_only_options():
    """Options marked affects_output=False (threads, device, progress) neither rerun the stage nor
    invalidate its resumable renders and checkpoint (both are kept under the runner's
    fingerprint); a training option, a model option or an input does."""
    from ibr_pipeline.nn.train import TrainOptions
    from ibr_pipeline.runner import fingerprint
    from ibr_pipeline.stages.supersample import STAGE, SupersampleConfig

    def fp(inputs=None, **kw):
        return fingerprint(STAGE, SupersampleConfig(**kw), inputs or {"a.png": "1"})
    base = fp()
    assert fp(train=TrainOptions(threads=2, progress=False, device="cpu")) == base
    assert fp(train=TrainOptions(steps=7000)) != base and fp(use_mvr=False) != base
    assert fp(time_budget_s=1200.0) != base   # the budget decides how far training gets
    assert fp({"a.png": "2"}) != base

