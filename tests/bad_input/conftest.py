"""Shared by the bad-input suite: a small input folder, and the one assertion every case makes.

`refused(argv, ...)` runs the CLI and checks the README's promise: exit code 2 (1 for a stage
fault), one line `ibr: error: ...` naming the file or field, no traceback, the input folder
byte-identical, the workspace as it was (no file added, changed or removed, no temporary left).
"""
import hashlib
import subprocess
import sys

import numpy as np
import pytest

from ibr_pipeline.cli import main
from ibr_pipeline.io.colmap import write_colmap_model
from ibr_pipeline.io.images import write_depth_png, write_image
from ibr_pipeline.scene import Camera, cameras_to_json


def tree(root):
    """{relative path: sha256} of every file under root (empty when root does not exist)."""
    if not root.exists():
        return {}
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def cameras(n=4):
    K = Camera.intrinsics_from_fov(40, 30, 60)
    return {f"{i}.png": Camera.look_at([i * 0.1, 0, 0], [0, 3, 0], [0, 0, 1], K, 40, 30) for i in range(n)}


@pytest.fixture
def input_dir(tmp_path):
    """A 4-view input folder: images/ + cameras.json + depth/ (16-bit mm, half resolution)."""
    root = tmp_path / "input"
    rng = np.random.default_rng(0)
    for name in cameras():
        write_image(root / "images" / name, rng.random((30, 40, 3)))
        write_depth_png(root / "depth" / name, np.full((15, 20), 3.0))
    (root / "cameras.json").write_text(cameras_to_json(cameras()))
    return root


@pytest.fixture
def colmap_dir(tmp_path):
    """The same views as a COLMAP workspace (images/ + sparse/0 binary model), no depth."""
    root = tmp_path / "colmap"
    rng = np.random.default_rng(1)
    for name in cameras():
        write_image(root / "images" / name, rng.random((30, 40, 3)))
    write_colmap_model(cameras(), root / "sparse" / "0", text=False)
    return root


@pytest.fixture
def ws(tmp_path, input_dir):
    ws = tmp_path / "ws"
    assert main(["init", str(ws), "--input", str(input_dir)]) == 0
    return ws


def _check(code, err, expect_code, needles, before, after):
    lines = [line for line in err.strip().splitlines() if line.strip()]
    assert code == expect_code, err
    assert "Traceback" not in err, err
    assert lines and lines[-1].startswith("ibr: error: "), err
    assert sum(line.startswith("ibr: error: ") for line in lines) == 1, err
    for n in needles:
        assert n in lines[-1], lines[-1]
    for folder, (old, new) in {"input": (before[0], after[0]), "workspace": (before[1], after[1])}.items():
        assert new == old, f"the {folder} changed: " + str(sorted(set(new.items()) ^ set(old.items()))[:4])
    return lines[-1]


def refused(capsys, argv, input_root, ws_root, *needles, code=2):
    """Run `ibr ARGV` in this process and assert the promise; returns the error line."""
    before = (tree(input_root), tree(ws_root))
    rc = main([str(a) for a in argv])
    err = capsys.readouterr().err
    return _check(rc, err, code, needles, before, (tree(input_root), tree(ws_root)))


def refused_subprocess(argv, input_root, ws_root, *needles, code=2, **popen):
    """The same, with `python -m ibr_pipeline` in a child process (rlimits, other users, signals)."""
    before = (tree(input_root), tree(ws_root))
    p = subprocess.run([sys.executable, "-m", "ibr_pipeline", *map(str, argv)], capture_output=True,
                       text=True, timeout=300, **popen)
    return _check(p.returncode, p.stderr, code, needles, before, (tree(input_root), tree(ws_root)))
