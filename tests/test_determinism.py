"""Deterministic outputs (issue #27): identical inputs give byte-identical files in every stage.

The whole pipeline runs twice on the `tiny` scene into two workspaces, each run in its own process
with its own PYTHONHASHSEED (a set of strings iterates in a different order in each: one such
order once moved the normalised scene frame, geometry/scale.py) and the second with two worker
processes (`--jobs 2`: results must not depend on the executor). Every file of the two workspaces
must be byte-identical, except the few that hold wall-clock times, listed below with the reason.

Then the symptom that started it: `global/mesh.ply` came out in open3d's thread-dependent
marching-cubes order, so `ibr run --force --from global_mesh --until global_mesh` rewrote it with
other bytes and every later stage became stale. Each stage is forced again on a copy of the
workspace and `ibr status` must find every stage up to date.
"""
import fnmatch
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from ibr_pipeline.cli import main
from ibr_pipeline.stages import STAGES

# Small and fast, and nothing that depends on the clock or the machine's load:
# * time_budget_s = 0: a wall-clock budget that binds ends DSRNet training (and fits its
#   learning-rate schedule) at a step that depends on the machine's speed, by design
#   (nn/train.py); 4 steps never reach it, 0 says so explicitly.
# * train.threads = 1: the trained weights depend on torch's CPU thread count (its reductions are
#   split per thread), and threads = 0 ("auto", nn/model.cpu_threads) takes the cores other
#   processes leave idle, so two runs on one machine could differ by the load alone.
CONFIG = """
[supersample]
time_budget_s = 0

[supersample.train]
steps = 4
batch = 2
crop = 24
checkpoint_every = 2
threads = 1
"""

# Whole files left out of the comparison, and why.
EXCLUDED = {
    ".ibr/state/*.json": "runner records: wall seconds and a finished-at timestamp (and the hashes "
                         "of the timing files below)",
    ".ibr/state/*/*.json": "per-view runner records: the same",
    ".ibr/runs.jsonl": "one line per `ibr run`: finished-at timestamp, seconds per stage",
    ".ibr/hashes.json": "the runner's hash cache: keyed by absolute path, holds file mtimes",
    ".ibr/logs/*": "tracebacks of failed views (none expected)",
}

# Reports compared field by field with these wall-clock fields removed (dotted paths, * = any key
# or list index). Every other field of these files must be identical.
TIMING_FIELDS = {
    "global/poses.json": ["timings"],                                 # poses_s, total_s
    "global/report.json": ["timings", "fusion.ms_per_frame"],
    "views/*/depth_report.json": ["ms", "cpu_ms", "timings_ms"],
    "views/*/mesh_report.json": ["ms", "cpu_ms"],
    # `processes`: how many render workers the frame times were taken beside (--jobs)
    "renders/*/timings.json": ["median_ms", "frames.*.ms", "frames.*.select_ms",
                               "frames.*.gl_ms", "frames.*.post_ms", "processes"],
    "nn/train.json": ["seconds"],                                     # render, train, total
    "eval/metrics.json": ["summary.naive_ms"],
}


def _ibr(args: list[str], hash_seed: int) -> None:
    """`ibr ARGS` in a fresh process with the given PYTHONHASHSEED."""
    env = dict(os.environ, PYTHONHASHSEED=str(hash_seed))
    res = subprocess.run([sys.executable, "-m", "ibr_pipeline", "-q"] + args, env=env,
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-4000:]


def _make_ws(ws: Path, src: Path, config: str = CONFIG) -> Path:
    assert main(["init", str(ws), "--input", str(src)]) == 0
    with open(ws / "ibr.toml", "a") as f:
        f.write(config)
    return ws


def _files(root: Path) -> set[str]:
    return {p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file()}


def _excluded(key: str) -> bool:
    return any(fnmatch.fnmatchcase(key, pat) for pat in EXCLUDED)


def _strip(obj, path: list[str]) -> bool:
    """Remove the dotted `path` from `obj` in place; whether anything was removed."""
    head, rest = path[0], path[1:]
    if isinstance(obj, dict):
        keys = list(obj) if head == "*" else [head] if head in obj else []
    elif isinstance(obj, list):
        keys = range(len(obj)) if head == "*" else []
    else:
        return False
    hit = False
    for k in reversed(list(keys)) if not rest else keys:
        if rest:
            hit |= _strip(obj[k], rest)
        else:
            del obj[k]
            hit = True
    return hit


def compare_workspaces(a: Path, b: Path) -> tuple[list[str], int]:
    """(differences, files compared) between two workspaces, per the rules above."""
    fa, fb = _files(a), _files(b)
    diffs = [f"only in {a.name}: {k}" for k in sorted(fa - fb) if not _excluded(k)]
    diffs += [f"only in {b.name}: {k}" for k in sorted(fb - fa) if not _excluded(k)]
    used: set[tuple[str, str]] = set()
    matched: set[str] = set()
    n = 0
    for key in sorted(fa & fb):
        if _excluded(key):
            continue
        n += 1
        ba, bb = (a / key).read_bytes(), (b / key).read_bytes()
        pats = [p for p in TIMING_FIELDS if fnmatch.fnmatchcase(key, p)]
        if not pats:
            if ba != bb:
                diffs.append(f"bytes differ: {key}")
            continue
        ja, jb = json.loads(ba), json.loads(bb)
        matched.update(pats)
        for pat in pats:
            for field in TIMING_FIELDS[pat]:
                if _strip(ja, field.split(".")):
                    used.add((pat, field))
                _strip(jb, field.split("."))
        # compared as canonical text: NaN (a metric of an empty mask) equals itself there
        if json.dumps(ja, sort_keys=True) != json.dumps(jb, sort_keys=True):
            diffs.append(f"differs beyond its timing fields: {key}")
    # an exclusion that no longer matches anything is dropped from the list, not kept "just in case"
    stale = [f"{p}: {f}" for p in matched for f in TIMING_FIELDS[p] if (p, f) not in used]
    assert not stale, f"timing exclusions that matched nothing (remove them): {stale}"
    return diffs, n


@pytest.fixture(scope="module")
def two_runs(tiny_scene, tmp_path_factory):
    """The full pipeline on `tiny`, twice: (workspace A, workspace B)."""
    root = tmp_path_factory.mktemp("determinism")
    a = _make_ws(root / "a", tiny_scene[0])
    b = _make_ws(root / "b", tiny_scene[0])
    _ibr(["run", str(a), "--no-progress"], hash_seed=1)
    _ibr(["run", str(b), "--no-progress", "--jobs", "2"], hash_seed=2)
    return a, b


def test_every_stage_writes_identical_bytes(two_runs):
    a, b = two_runs
    diffs, n = compare_workspaces(a, b)
    assert not diffs, "\n".join(diffs)
    # every stage ran and wrote its files: the comparison covered all of them
    for key in ("scene.json", "global/cameras.json", "global/mesh.ply", "views/0000.png/depth.npy",
                "views/0000.png/mesh.ply", "views/0004.png/M1.ply", "reflection/planes.json",
                "renders/test/0000.png", "nn/dsrnet.pt", "eval/metrics.json", "eval/fly.mp4"):
        assert (a / key).is_file(), key
    assert n > 100


# A forced rerun of a stage must leave every stage up to date. Two stages still fail, because a
# later stage reads (and so fingerprints) a file in which they also record wall-clock times; the
# fix is outside this test's files (moving the timings to files no stage reads) and is described
# in issue #27. strict: the test fails once they are fixed, so the marks get removed.
KNOWN_TIMING_INPUTS = {
    "poses": "global/poses.json holds timings.poses_s/total_s and is an input of global_mesh "
             "and render_views",
    "render_views": "renders/<set>/timings.json holds per-frame ms and is an input of evaluate "
                    "(for its source and holes fields)",
}


@pytest.mark.parametrize("stage", [
    pytest.param(s.name, marks=pytest.mark.xfail(strict=True, raises=AssertionError,
                                              reason=KNOWN_TIMING_INPUTS[s.name]))
    if s.name in KNOWN_TIMING_INPUTS else s.name for s in STAGES])
def test_forced_rerun_leaves_every_stage_up_to_date(two_runs, tmp_path, capsys, stage):
    ws = tmp_path / "ws"
    shutil.copytree(two_runs[0], ws)
    before = (ws / "global" / "mesh.ply").read_bytes()
    assert main(["-q", "run", str(ws), "--from", stage, "--until", stage, "--force",
                 "--no-progress"]) == 0
    capsys.readouterr()
    assert main(["status", str(ws), "--json"]) == 0
    plans = json.loads(capsys.readouterr().out)
    stale = [f"{p['stage']}: {p['state']} ({p['reason']})" for p in plans if p["state"] != "up to date"]
    assert [p["stage"] for p in plans] == [s.name for s in STAGES]
    assert not stale, "\n".join(stale)
    assert (ws / "global" / "mesh.ply").read_bytes() == before


def _rgb_only(src: Path, dst: Path) -> Path:
    """A copy of the capture with only images and cameras.json (no depth frames, no COLMAP model):
    posed images without a metric scale, so the poses stage measures a normalised scene frame by
    triangulating SIFT matches (geometry/scale.py) and global_mesh runs MVS."""
    dst.mkdir()
    shutil.copytree(src / "images", dst / "images")
    for f in ("cameras.json", "reflectors.json"):
        shutil.copy(src / f, dst / f)
    if (src / "gt").is_dir():
        shutil.copytree(src / "gt", dst / "gt")
    return dst


def test_normalised_scene_frame_does_not_depend_on_the_hash_seed(sample_scene, tmp_path):
    """The views of triangulate_given were iterated in a set's order: the mean of the camera
    centres, hence the normalised scale and every later file, changed with PYTHONHASHSEED."""
    src = _rgb_only(sample_scene, tmp_path / "rgb")
    wss = [_make_ws(tmp_path / f"ws{i}", src, "") for i in range(2)]
    for i, ws in enumerate(wss):
        _ibr(["run", str(ws), "--until", "poses", "--no-progress"], hash_seed=11 + i)
    assert json.loads((wss[0] / "global" / "poses.json").read_text())["units"] == "normalised"
    diffs, n = compare_workspaces(*wss)
    assert not diffs, "\n".join(diffs)
    assert n >= 5


@pytest.mark.slow
def test_rgb_only_capture_gives_identical_bytes(sample_scene, tmp_path):
    """The other path through the pipeline, on sample_data without depth frames: SIFT scale,
    PatchMatch MVS and its fusion, MVS-completed per-view depth, and every later stage (about
    1.5 min per run on 2 cores)."""
    src = _rgb_only(sample_scene, tmp_path / "rgb")
    wss = [_make_ws(tmp_path / f"ws{i}", src) for i in range(2)]
    _ibr(["run", str(wss[0]), "--no-progress"], hash_seed=21)
    _ibr(["run", str(wss[1]), "--no-progress", "--jobs", "2"], hash_seed=22)
    assert json.loads((wss[0] / "global" / "report.json").read_text())["dense"] == "mvs"
    diffs, n = compare_workspaces(*wss)
    assert not diffs, "\n".join(diffs)
