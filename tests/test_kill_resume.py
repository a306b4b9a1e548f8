"""A real subprocess killed with SIGKILL in the middle of a per-view stage resumes without redoing
finished views, and never leaves a truncated file under a real name."""
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from toy_stages import STAGES, make_toy_workspace

from ibr_pipeline.pipeline import load_configs, run, status
from ibr_pipeline.workspace import Workspace

TOY = Path(__file__).parent / "toy_stages.py"


def test_sigkill_mid_stage_then_resume(tmp_path):
    ws_root = make_toy_workspace(tmp_path, n_views=12)
    state = ws_root / ".ibr" / "state" / "upper"
    proc = subprocess.Popen([sys.executable, str(TOY), str(ws_root), "0.25"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    deadline = time.time() + 60
    # wait until 4 views are done AND the next one is half-way through writing its output
    while time.time() < deadline:
        if (state.is_dir() and len(list(state.glob("*.json"))) >= 4
                and list(ws_root.glob("views/*/*ibrtmp*"))):
            break
        assert proc.poll() is None, proc.stderr.read().decode()
        time.sleep(0.01)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL

    done_before = {p.stem for p in state.glob("*.json")}
    assert 4 <= len(done_before) < 12, "the kill must land mid-stage"
    ran_before = (ws_root / "ranlog.txt").read_text().split()
    assert list(ws_root.glob("views/*/*ibrtmp*")), "the kill landed mid-write"
    # every file under a real name is complete; the interrupted write left only a temporary
    for out in ws_root.glob("views/*/out.txt"):
        assert out.read_text().endswith("END\n"), out
    assert all(out.parent.name in done_before for out in ws_root.glob("views/*/out.txt"))

    ws = Workspace(ws_root)
    configs = load_configs(STAGES, ws, {"upper": {"sleep": "0.25"}})
    plan = {p.stage.name: p for p in status(STAGES, ws, configs)}["upper"]
    assert sorted(plan.views_todo) == sorted(set(f"v{i:02d}" for i in range(12)) - done_before)

    results = run(STAGES, ws, configs, STAGES[:2], progress=False)
    assert results[1].views_run == 12 - len(done_before)
    ran_after = (ws_root / "ranlog.txt").read_text().split()[len(ran_before):]
    assert not set(ran_after) & done_before, "finished views were redone"
    assert sorted(ran_after) == sorted(set(f"v{i:02d}" for i in range(12)) - done_before)
    for i in range(12):
        assert (ws_root / "views" / f"v{i:02d}" / "out.txt").read_text().endswith("END\n")
    assert not list(ws_root.rglob("*ibrtmp*")), "temporaries of the killed run must be cleaned"
