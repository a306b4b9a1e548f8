"""The workspace itself: read-only, full, busy, file-size limit; --dry-run; runs.jsonl; a bad model.

Read-only and full file systems are real ones where the test can make them (a read-only bind
mount and a tiny tmpfs need root: skipped elsewhere); the file-size limit (RLIMIT_FSIZE) works for
any user and takes the same path (a write that fails with an errno the user can fix).
"""
import contextlib
import json
import resource
import subprocess
import sys
import time

import pytest
from conftest import refused, refused_subprocess, tree

from ibr_pipeline.cli import main


@contextlib.contextmanager
def _mount(args, target):
    r = subprocess.run(["mount", *args, str(target)], capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount here ({r.stderr.strip()[:80]})")
    try:
        yield
    finally:
        subprocess.run(["umount", "-l", str(target)], capture_output=True)


def test_read_only_workspace(capsys, ws, input_dir):
    with _mount(["--bind", "-o", "ro", str(ws)], ws):
        refused(capsys, ["run", ws, "--no-progress"], input_dir, ws, str(ws), "read-only file system")


def test_full_disk_during_a_stage_write(capsys, tmp_path, input_dir):
    ws = tmp_path / "small"
    ws.mkdir()
    with _mount(["-t", "tmpfs", "-o", "size=4k", "tmpfs"], ws):
        (ws / "ibr.toml").write_text(f'[input]\npath = "{input_dir}"\n')  # fills the one page
        refused(capsys, ["run", ws, "--no-progress"], input_dir, ws, "scene.json", "no space left")


def test_full_disk_in_a_per_view_stage_keeps_finished_views(tmp_path):
    """A per-view stage that runs out of space mid-stage stops with WorkspaceError (exit 2 in the
    CLI); the views that finished keep their records and are not redone once there is space."""
    from toy_stages import STAGES, make_toy_workspace

    from ibr_pipeline.errors import WorkspaceError
    from ibr_pipeline.pipeline import load_configs, run
    from ibr_pipeline.workspace import Workspace
    root = tmp_path / "toy"
    root.mkdir()
    with _mount(["-t", "tmpfs", "-o", "size=96k", "tmpfs"], root):
        ws_root = make_toy_workspace(root, n_views=12)
        ws = Workspace(ws_root)
        configs = load_configs(STAGES, ws, {"upper": {"repeat": "1000"}})  # ~17 kB per view
        with pytest.raises(WorkspaceError, match="out.txt: cannot write: no space left"):
            run(STAGES, ws, configs, STAGES[:2], progress=False)
        done = sorted(p.stem for p in (ws_root / ".ibr" / "state" / "upper").glob("*.json"))
        assert 1 <= len(done) < 12
        for v in done:
            assert (ws_root / "views" / v / "out.txt").read_text().endswith("END\n")
        assert not list(ws_root.rglob("*ibrtmp*")), "the failed write left a temporary"
        subprocess.run(["mount", "-o", "remount,size=1m", str(root)], check=True)  # free space
        ran_before = len((ws_root / "ranlog.txt").read_text().split())
        results = run(STAGES, ws, configs, STAGES[:2], progress=False)
        assert results[1].result == "ran" and results[1].views_run == 12 - len(done)
        ran_after = (ws_root / "ranlog.txt").read_text().split()[ran_before:]
        assert not set(ran_after) & set(done), "finished views were redone"


def test_file_size_limit(input_dir, ws):
    def limit():
        resource.setrlimit(resource.RLIMIT_FSIZE, (512, 512))
    refused_subprocess(["run", ws, "--no-progress"], input_dir, ws, "scene.json", "file size limit",
                       preexec_fn=limit)


def test_second_run_is_refused_and_names_the_holder(capsys, ws, input_dir):
    from ibr_pipeline.workspace import Workspace
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time; from ibr_pipeline.workspace "
                               "import Workspace\nwith Workspace(sys.argv[1]).lock():\n print('held', "
                               "flush=True); time.sleep(60)", str(ws)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        line = refused(capsys, ["run", ws, "--no-progress"], input_dir, ws, "in use by",
                       f"pid {holder.pid}", "--wait")
        assert "ibr_pipeline.workspace" in line  # the holder's command line is shown
    finally:
        holder.kill()
        holder.wait()
    with Workspace(ws).lock():  # a killed holder leaves no stale lock
        pass


def test_wait_waits_for_the_holder(ws, input_dir):
    from ibr_pipeline.workspace import Workspace
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time; from ibr_pipeline.workspace "
                               "import Workspace\nwith Workspace(sys.argv[1]).lock():\n print('held', "
                               "flush=True); time.sleep(2)", str(ws)], stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "held"
    t0 = time.monotonic()
    with Workspace(ws).lock(wait=True):
        waited = time.monotonic() - t0
    assert waited > 1.0, "the lock was taken while the holder still held it (2 s)"
    holder.wait()


def test_dry_run_writes_nothing(capsys, tmp_path, input_dir, ws):
    new = tmp_path / "never_made"
    assert main(["run", str(new), "--input", str(input_dir), "--dry-run"]) == 0
    assert "ingest" in capsys.readouterr().out
    assert not new.exists(), "--dry-run created the workspace"
    before = tree(ws)
    assert main(["run", str(ws), "--dry-run"]) == 0
    assert tree(ws) == before


def test_runs_jsonl_records_the_resolved_config_and_command(capsys, ws):
    assert main(["run", str(ws), "--until", "ingest", "--no-progress", "--set", "ingest.min_views=3"]) == 0
    entry = json.loads((ws / ".ibr" / "runs.jsonl").read_text().splitlines()[-1])
    assert entry["command"] == ["run", str(ws), "--until", "ingest", "--no-progress", "--set",
                                "ingest.min_views=3"]
    assert entry["config"]["ingest"]["min_views"] == 3
    assert entry["config"]["ingest"]["check_pixels"] is True  # defaults too, not only what was set


@pytest.mark.parametrize("payload", [b"garbage" * 10, b"PK\x03\x04 not a torch archive\n\n", "pickle"])
def test_unreadable_model_file_is_one_line(tmp_path, payload):
    """A corrupt or hostile DSRNet / VGG file: one line naming it, torch's paragraphs (and their
    advice to load with weights_only=False) left out, and a pickled object never executed."""
    import torch

    from ibr_pipeline.errors import InputError
    from ibr_pipeline.nn.losses import VGGFeatures
    from ibr_pipeline.nn.model import load_model
    p = tmp_path / "model.pt"
    if payload == "pickle":
        torch.save({"a": torch.nn.Linear(2, 2)}, p)  # a module object: refused by weights_only
    else:
        p.write_bytes(payload)
    for loader in (load_model, VGGFeatures):
        with pytest.raises(InputError) as e:
            loader(p)
        msg = str(e.value)
        assert "\n" not in msg and str(p) in msg and "weights_only" not in msg, msg


def test_every_input_error_is_one_line():
    from ibr_pipeline.errors import ConfigError, InputError
    assert str(InputError("a\n  b\n\nc")) == "a b c"
    assert "\n" not in str(InputError("x" * 5000)) and len(str(InputError("x" * 5000))) <= 600
    import pickle
    e = pickle.loads(pickle.dumps(ConfigError("ingest.min_views", "must be >= 1")))
    assert str(e) == "invalid config ingest.min_views: must be >= 1" and e.field == "ingest.min_views"
