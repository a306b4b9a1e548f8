"""The `ibr` CLI: help, status explanations, the ingest stage, and one-line errors on bad arguments
(bad input files and configs: tests/bad_input/)."""
import re
import subprocess
import sys

import numpy as np
import pytest

from ibr_pipeline.cli import main
from ibr_pipeline.io.colmap import write_colmap_model
from ibr_pipeline.io.images import write_depth_png, write_image
from ibr_pipeline.scene import Camera
from ibr_pipeline.stages import STAGES


def _snapshot(root):
    return {p: (p.stat().st_size, p.stat().st_mtime_ns) for p in root.rglob("*")} if root.exists() else {}


@pytest.fixture
def scene_input(tmp_path):
    """A 4-view COLMAP input folder with depth at half resolution."""
    root = tmp_path / "input"
    K = Camera.intrinsics_from_fov(40, 30, 60)
    cams = {f"{i}.png": Camera.look_at([i * 0.1, 0, 0], [0, 3, 0], [0, 0, 1], K, 40, 30) for i in range(4)}
    rng = np.random.default_rng(0)
    for name in cams:
        write_image(root / "images" / name, rng.random((30, 40, 3)))
        write_depth_png(root / "depth" / name, np.full((15, 20), 3.0))
    write_colmap_model(cams, root / "sparse" / "0")
    return root


@pytest.fixture
def workspace(tmp_path, scene_input):
    ws = tmp_path / "ws"
    assert main(["init", str(ws), "--input", str(scene_input)]) == 0
    return ws


def _fails_cleanly(argv, ws, capsys, *needles):
    before = _snapshot(ws)
    code = main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2, err
    errors = [line for line in err if "error" in line.lower()]
    assert len(errors) == 1 and err[-1].startswith("ibr: error: "), err  # one line, the last one
    for n in needles:
        assert n in err[-1], err[-1]
    assert _snapshot(ws) == before, "bad input must leave the workspace as it was"
    return err[-1]


def test_help_is_light_and_lists_every_stage():
    code = ("import sys; from ibr_pipeline.cli import build_parser; h = build_parser().format_help(); "
            "heavy = [m for m in ('torch', 'open3d', 'pycolmap', 'cv2', 'moderngl', 'distributed', "
            "'matplotlib', 'scipy', 'PIL') if m in sys.modules]; print(heavy); print(h)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.splitlines()[0] == "[]", "ibr --help must not import heavy libraries"
    for s in STAGES:
        assert s.name in out
    res = subprocess.run([sys.executable, "-m", "ibr_pipeline", "run", "--help"], capture_output=True, text=True)
    assert res.returncode == 0
    for flag in ("--force", "--dry-run", "--from", "--until", "--jobs", "--dask-scheduler", "--dask-local", "--set"):
        assert flag in res.stdout


def test_no_progress_silences_the_stages_own_bars(workspace, monkeypatch):
    """ingest's image check has its own tqdm bar; --no-progress must disable it too (each bar's
    state is recorded when it is created)."""
    import tqdm
    seen = []
    init = tqdm.tqdm.__init__

    def spy(self, *a, **k):
        init(self, *a, **k)
        seen.append((k.get("desc"), self.disable))
    monkeypatch.setattr(tqdm.tqdm, "__init__", spy)
    assert main(["ingest", str(workspace), "--force", "--no-progress"]) == 0
    assert ("ingest: checking images", True) in seen
    seen.clear()
    assert main(["ingest", str(workspace), "--force"]) == 0
    assert ("ingest: checking images", False) in seen


@pytest.mark.parametrize("stage", [s.name for s in STAGES])
def test_every_stage_help_prints(stage, capsys):
    """`ibr STAGE --help` lists the stage's config flags (a '%' in a field's help once crashed
    argparse's formatting for view_depth)."""
    with pytest.raises(SystemExit) as e:
        main([stage, "--help"])
    assert e.value.code == 0
    assert "--jobs" in capsys.readouterr().out


def test_run_ingest_status_and_reasons(workspace, scene_input, capsys):
    assert main(["status", str(workspace)]) == 0
    out = capsys.readouterr().out
    assert "ingest" in out and "never run" in out
    assert re.search(r"^global_mesh\s+(will run|blocked)", out, re.M)
    assert main(["run", str(workspace), "--until", "ingest", "--no-progress"]) == 0
    err = capsys.readouterr().err
    assert "4 images (4 with cameras, from colmap), 4 with depth" in err
    assert "stage" in err and "seconds" in err and "total" in err  # the timing table
    assert (workspace / "scene.json").is_file()
    assert main(["status", str(workspace)]) == 0
    assert re.search(r"^ingest\s+up to date", capsys.readouterr().out, re.M)
    write_image(scene_input / "images" / "2.png", np.zeros((30, 40, 3)))
    assert main(["status", str(workspace), "--set", "ingest.min_views=3"]) == 0
    out = capsys.readouterr().out
    assert "input changed: input/images/2.png" in out and "ingest.min_views 2 → 3" in out
    assert main(["ingest", str(workspace), "--dry-run"]) == 0
    assert "will run" in capsys.readouterr().out
    assert main(["ingest", str(workspace), "--no-progress"]) == 0
    assert main(["status", str(workspace), "--json"]) == 0
    assert '"state": "up to date"' in capsys.readouterr().out


def test_missing_workspace(tmp_path, capsys):
    _fails_cleanly(["status", str(tmp_path / "nope")], tmp_path, capsys, "workspace does not exist")
    assert not (tmp_path / "nope").exists()


def test_missing_input_folder_creates_nothing(tmp_path, capsys):
    _fails_cleanly(["run", str(tmp_path / "ws"), "--input", str(tmp_path / "none")], tmp_path, capsys,
                   "input folder does not exist")


def test_unknown_stage(workspace, capsys):
    _fails_cleanly(["run", str(workspace), "--from", "meshify"], workspace, capsys, "unknown stage 'meshify'")
    with pytest.raises(SystemExit) as e:
        main(["meshify", str(workspace)])
    assert e.value.code == 2  # argparse: invalid choice


def test_workspace_input_mismatch(workspace, tmp_path, capsys):
    other = tmp_path / "other"
    other.mkdir()
    _fails_cleanly(["run", str(workspace), "--input", str(other)], workspace, capsys, "already uses input")
