"""A real subprocess killed with SIGKILL in the middle of a stage resumes without redoing finished
work, never leaves a truncated file under a real name, and ends with the outputs of an
uninterrupted run: a toy per-view stage, then `global_mesh`, `render_views` and `supersample` run
by `python -m ibr_pipeline run` on the `tiny` scene."""
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

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
    proc.communicate()
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


# --- SIGKILL in the middle of the real stages -------------------------------------------------
# Each test runs `python -m ibr_pipeline run WS --from STAGE --until STAGE` three times on copies of
# one prepared workspace (the `tiny` scene): uninterrupted (the reference), killed with SIGKILL
# mid-stage, and resumed. To make "mid-stage" a precise moment rather than a race against a stage
# that takes a second on `tiny`, the killed run gets a sitecustomize hook (HOOK, below) that sleeps
# between writing chosen files' temporaries and renaming them into place: the kill lands while a
# temporary of a chosen output exists and the files before it are under their real names. The hook
# changes no byte the stage writes; it also logs every file renamed into place (IBR_WRITE_LOG).
HOOK = '''
import os
if os.environ.get("IBR_SLOW_RENAME") or os.environ.get("IBR_WRITE_LOG"):
    import contextlib, fnmatch, itertools, time
    import ibr_pipeline.workspace as _w
    _real = _w.atomic_path
    # IBR_SLOW_RENAME = "GLOB:SECONDS[:SKIP]": sleep before renaming files matching GLOB, after SKIP
    _pat, _sec, _skip = ((os.environ.get("IBR_SLOW_RENAME") or ":0").split(":") + ["0", "0"])[:3]
    _seen = itertools.count()
    _log = os.environ.get("IBR_WRITE_LOG")

    @contextlib.contextmanager
    def atomic_path(target):
        with _real(target) as tmp:
            yield tmp
            if _pat and fnmatch.fnmatch(str(target), _pat) and next(_seen) >= int(_skip):
                time.sleep(float(_sec))   # temporary written, not yet renamed
        if _log:
            with open(_log, "a") as f:
                f.write(f"{target}\\n")

    _w.atomic_path = atomic_path   # before any module binds it with `from .workspace import`
'''

TMP = "*.ibrtmp-*"
# supersample: real IBR renderer, no time budget (a budget makes the step count depend on speed)
SUPERSAMPLE = ["--set", "supersample.time_budget_s=0", "--set", "supersample.train.steps=12",
               "--set", "supersample.train.batch=2", "--set", "supersample.train.crop=24",
               "--set", "supersample.train.checkpoint_every=2", "--set", "supersample.train.threads=1"]


@pytest.fixture(scope="module")
def prepared(tiny_scene, tmp_path_factory):
    """{"poses": workspace of `tiny` after the real ingest + poses, "reflection": one whose stages
    through reflection are ground truth, "hook": the folder of the sitecustomize hook}."""
    from ibr_pipeline.cli import main
    from ibr_pipeline.gt_workspace import write_gt_workspace

    root = tmp_path_factory.mktemp("kill")
    (root / "hook").mkdir()
    (root / "hook" / "sitecustomize.py").write_text(HOOK)
    assert main(["-q", "run", str(root / "poses"), "--input", str(tiny_scene[0]), "--until", "poses",
                 "--no-progress"]) == 0
    write_gt_workspace(tiny_scene[0], root / "reflection", "reflection", global_mesh="none")
    return {"poses": root / "poses", "reflection": root / "reflection", "hook": root / "hook"}


def _ibr_run(ws, stage, extra=(), hook=None, slow="", log=None):
    env = dict(os.environ)
    if hook is not None:
        env["PYTHONPATH"] = os.pathsep.join([str(hook), env.get("PYTHONPATH", "")])
        env["IBR_SLOW_RENAME"] = slow
        if log is not None:
            env["IBR_WRITE_LOG"] = str(log)
    cmd = [sys.executable, "-m", "ibr_pipeline", "-q", "run", str(ws), "--from", stage, "--until",
           stage, "--no-progress", *extra]
    return subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def _finish(proc, timeout=300):
    out, err = proc.communicate(timeout=timeout)
    assert proc.returncode == 0, err.decode()[-3000:]


def _kill_when(proc, condition, timeout=120):
    deadline = time.time() + timeout
    while not condition():
        if proc.poll() is not None:
            raise AssertionError("the stage ended before the kill point: "
                                 + proc.communicate()[1].decode()[-3000:])
        assert time.time() < deadline, "kill point never reached"
        time.sleep(0.005)
    os.kill(proc.pid, signal.SIGKILL)
    proc.communicate()   # reaps it and closes the pipes
    assert proc.returncode == -signal.SIGKILL


def _timeless(obj):
    """A JSON value without its wall-clock measurements (ms, seconds, timings, *_s, *_ms)."""
    if isinstance(obj, dict):
        return {k: _timeless(v) for k, v in obj.items()
                if not (k in ("ms", "seconds", "timings") or k.endswith(("_ms", "_s"))
                        or k.startswith("ms_"))}
    if isinstance(obj, list):
        return [_timeless(v) for v in obj]
    return obj


def _same(a: Path, b: Path, drop=()) -> str:
    """'bytes' when identical, 'timings' when only wall-clock fields of a JSON differ, '' else."""
    if a.read_bytes() == b.read_bytes():
        return "bytes"
    if a.suffix == ".json":
        ja, jb = json.loads(a.read_text()), json.loads(b.read_text())
        for k in drop:
            ja.pop(k, None), jb.pop(k, None)
        if _timeless(ja) == _timeless(jb):
            return "timings"
    return ""


def _readable(p: Path) -> None:
    """A file with no counterpart in the reference (a cache, a checkpoint) is complete: it loads."""
    if p.suffix in (".npz", ".npy"):
        import numpy as np
        z = np.load(p)
        if p.suffix == ".npz":
            [z[k] for k in z.files]
    elif p.suffix == ".pt":
        import torch
        torch.load(p, map_location="cpu", weights_only=True)
    elif p.suffix == ".json":
        json.loads(p.read_text())
    else:
        raise AssertionError(f"no reference and no reader for {p}")


def _records(ws):
    return {p: json.loads(p.read_text()) for p in (ws / ".ibr" / "state").rglob("*.json")}


def _check_killed(ws, ref, stage, dirs):
    """After the kill: the stage has no record; every other record's outputs match their sha256;
    every file under a real name in the stage's folders is complete (equal to the reference's, or
    loadable); the kill landed mid-write (a temporary exists); and the plan reruns the stage."""
    from ibr_pipeline.pipeline import scene_for, load_configs
    from ibr_pipeline.runner import HashCache, StageContext, plan_stage
    from ibr_pipeline.stages import STAGES, stage_by_name
    from ibr_pipeline.workspace import Workspace, file_sha256

    assert not (ws / ".ibr" / "state" / f"{stage}.json").exists()
    for path, rec in _records(ws).items():
        for key, meta in rec.get("outputs", {}).items():
            assert file_sha256(ws / key) == meta["sha256"], (path, key)
    assert any(list((ws / d).rglob(TMP)) for d in dirs), "the kill landed mid-write"
    for d in dirs:
        for p in (ws / d).rglob("*"):
            if not p.is_file() or p.match(TMP):
                continue
            twin = ref / p.relative_to(ws)
            if twin.is_file():
                assert _same(p, twin), f"{p.relative_to(ws)} differs from the uninterrupted run's"
            else:
                _readable(p)
    w = Workspace(ws)   # what `ibr run --from STAGE` plans now
    ctx = StageContext(w, stage, load_configs(STAGES, w, {})[stage], scene_for(w, stage))
    plan = plan_stage(stage_by_name(stage), ctx, HashCache(w.hash_cache_path), False, None)
    assert plan.state == "will run" and plan.reasons == ["never run"], plan.reasons


def _check_resumed(ws, ref, stage, drop=()) -> dict:
    """The resumed run left no temporary, recorded its outputs truthfully, and wrote what the
    uninterrupted run wrote: {output: 'bytes' | 'timings'} (how it matched)."""
    from ibr_pipeline.workspace import file_sha256

    assert not list(ws.rglob(TMP)), "temporaries of the killed run must be cleaned"
    rec = json.loads((ws / ".ibr" / "state" / f"{stage}.json").read_text())
    ref_rec = json.loads((ref / ".ibr" / "state" / f"{stage}.json").read_text())
    assert rec["status"] == "ok" and sorted(rec["outputs"]) == sorted(ref_rec["outputs"])
    how = {}
    for key, meta in rec["outputs"].items():
        assert file_sha256(ws / key) == meta["sha256"], key
        how[key] = _same(ws / key, ref / key, drop)
    differ = sorted(k for k, v in how.items() if not v)
    assert not differ, f"outputs differ from the uninterrupted run: {differ}"
    # only wall-clock fields may differ, and only in JSON reports
    assert all(v == "bytes" or k.endswith(".json") for k, v in how.items()), how
    return how


def _written(log: Path, ws: Path) -> list[str]:
    if not log.is_file():
        return []
    return [Path(p).relative_to(ws).as_posix() for p in log.read_text().split()]


def _three_copies(src, tmp_path):
    ref, ws = tmp_path / "ref", tmp_path / "ws"
    shutil.copytree(src, ref, symlinks=True)
    shutil.copytree(src, ws, symlinks=True)
    return ref, ws


def test_sigkill_during_global_mesh(prepared, tmp_path):
    """Killed after global/mesh.ply was renamed into place and while report.json is a temporary:
    the half-finished stage has no record, so the rerun redoes it and writes the same files."""
    ref, ws = _three_copies(prepared["poses"], tmp_path)
    _finish(_ibr_run(ref, "global_mesh"))
    proc = _ibr_run(ws, "global_mesh", hook=prepared["hook"], slow="*/global/report.json:30")
    _kill_when(proc, lambda: (ws / "global" / "mesh.ply").is_file()
               and list((ws / "global").glob(".report" + TMP)))
    assert not (ws / "global" / "report.json").exists()
    _check_killed(ws, ref, "global_mesh", ["global"])
    _finish(_ibr_run(ws, "global_mesh"))
    how = _check_resumed(ws, ref, "global_mesh")
    assert how["global/mesh.ply"] == "bytes"


def test_sigkill_during_render_views(prepared, tmp_path):
    """Killed while the third render set is being written (two sets complete under their real
    names). render_views is a whole-scene stage: the rerun renders every set again (it keeps no
    per-frame progress), and writes the same PNGs byte for byte."""
    ref, ws = _three_copies(prepared["reflection"], tmp_path)
    _finish(_ibr_run(ref, "render_views"))
    log = tmp_path / "killed.log"
    proc = _ibr_run(ws, "render_views", hook=prepared["hook"], slow="*/renders/*:0.1", log=log)
    _kill_when(proc, lambda: (ws / "renders" / "test_single" / "cameras.json").is_file()
               and list((ws / "renders").rglob(TMP)))
    done = _written(log, ws)
    assert 4 <= sum(k.endswith(".png") for k in done) < len(list((ref / "renders").rglob("*.png")))
    assert not (ws / "renders" / "tour" / "cameras.json").exists(), "the kill must land mid-stage"
    _check_killed(ws, ref, "render_views", ["renders"])
    _finish(_ibr_run(ws, "render_views"))
    how = _check_resumed(ws, ref, "render_views")
    assert all(v == "bytes" for k, v in how.items() if k.endswith(".png"))


def test_sigkill_during_supersample_resumes_renders_and_training(prepared, tmp_path):
    """Killed while the second training checkpoint is being written (the first is in place): the rerun renders no view
    again (nn/cache), resumes training at the checkpoint's step, and trains the same network as
    an uninterrupted run, byte for byte."""
    import torch

    ref, ws = _three_copies(prepared["reflection"], tmp_path)
    _finish(_ibr_run(ref, "supersample", SUPERSAMPLE))
    proc = _ibr_run(ws, "supersample", SUPERSAMPLE, hook=prepared["hook"],
                    slow="*/nn/checkpoint.pt:30:1", log=tmp_path / "killed.log")
    ck = ws / "nn" / "checkpoint.pt"
    _kill_when(proc, lambda: ck.is_file() and list((ws / "nn").glob(".checkpoint" + TMP)))
    assert not (ws / "nn" / "dsrnet.pt").exists()
    cached = sorted(p.name for p in (ws / "nn" / "cache").glob("*.npz"))
    assert len(cached) == 8, "every low-res render was cached before training"
    step = torch.load(ck, map_location="cpu", weights_only=True)["step"]
    assert 0 < step < 12
    _check_killed(ws, ref, "supersample", ["nn"])

    log = tmp_path / "resumed.log"
    _finish(_ibr_run(ws, "supersample", SUPERSAMPLE, hook=prepared["hook"], log=log))
    written = _written(log, ws)
    assert not [k for k in written if k.startswith("nn/cache/") and k.endswith(".npz")], \
        "cached renders were rendered again"
    assert written.count("nn/checkpoint.pt") == (12 - step) // 2, "finished steps were redone"
    rep = json.loads((ws / "nn" / "train.json").read_text())
    assert rep["resumed_from_step"] == step and rep["steps"] == 12
    assert json.loads((ref / "nn" / "train.json").read_text())["resumed_from_step"] == 0
    how = _check_resumed(ws, ref, "supersample", drop=("resumed_from_step",))
    assert how["nn/dsrnet.pt"] == "bytes" and how["nn/loss.png"] == "bytes", how
