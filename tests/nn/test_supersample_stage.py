"""Stage `supersample` through the CLI/runner, SuperSampler, and bad input.

The stage's real low-res renderer is issue #7's IBR model; these tests use `--renderer standin`
(synthetic GT with IBR-like artefacts), because the stage must be testable without #7."""
import json
import shutil

import numpy as np
import pytest

from ibr_pipeline.cli import main
from ibr_pipeline.errors import InputError
from ibr_pipeline.nn.infer import SuperSampler
from ibr_pipeline.scene import cameras_from_json
from ibr_pipeline.workspace import Workspace

FAST = ["--renderer", "standin", "--steps", "4", "--batch", "2", "--crop", "24",
        "--checkpoint-every", "2", "--threads", "1", "--no-progress"]


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
    from ibr_pipeline.nn.data import StandInRenderer
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
    with pytest.raises(InputError, match="depth"):
        sampler(color, depth[:, :10], lr_cam)
    with pytest.raises(InputError, match="NaN"):
        sampler(np.full_like(color, np.nan), depth, lr_cam)


def test_bad_config_and_missing_inputs_write_nothing(ws, capsys):
    assert main(["supersample", str(ws), "--steps", "0", "--no-progress"]) == 2
    assert "supersample.steps" in capsys.readouterr().err
    assert main(["supersample", str(ws), "--preset", "huge", "--no-progress"]) == 2
    assert main(["supersample", str(ws), "--vgg-weights", "nope.pt"] + FAST) == 2
    assert "vgg_weights" in capsys.readouterr().err
    assert not (ws / "nn" / "dsrnet.pt").exists()


def test_real_renderer_needs_view_meshes(ws):
    """With the default renderer (issue #7's IBR model) the stage needs the per-view meshes and
    edges: without them it is blocked (missing input) and writes nothing."""
    rc = main(["supersample", str(ws), "--steps", "2", "--no-progress"])
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
    assert main(["supersample", str(ws), "--capture-fraction", "0.5", "--warmup-steps", "2"]
                + FAST) == 0
    rep = json.loads((ws / "nn" / "train.json").read_text())
    assert rep["capture_fraction"] == 0.5 and rep["capture_pairs"] == rep["train_pairs"] > 0
    assert rep["val_views"] and not set(rep["val_views"]) & set(rep["train_views"])
    assert rep["validation"]["psnr"] > 15


def test_resume_cache_ignores_run_only_options(tmp_path):
    """A killed run restarted with another thread count or time budget keeps its renders and
    checkpoint (the resume digest leaves those options out); a training option changes it."""
    from types import SimpleNamespace

    from ibr_pipeline.stages.supersample import SupersampleConfig, _digest

    fake_ws = SimpleNamespace(exists=lambda key: False, path=lambda key: tmp_path / key)
    digest = lambda **kw: _digest(SimpleNamespace(config=SupersampleConfig(**kw), ws=fake_ws))  # noqa: E731
    base = digest()
    assert digest(threads=2, time_budget_s=1200.0, progress=False, checkpoint_every=50) == base
    assert digest(steps=7000) != base and digest(use_mvr=False) != base
