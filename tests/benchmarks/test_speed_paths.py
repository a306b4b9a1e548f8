"""`ibr bench speed` runs each timed stage inside the variant's source tree (cwd = that tree), so
every path it hands to those processes must be absolute: a relative `--out` once made the first
`ibr run` fail with "input folder does not exist"."""
from __future__ import annotations

import argparse
from pathlib import Path

from benchmarks import speed


def test_relative_out_reaches_the_stage_processes_as_absolute_paths(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    calls = []

    def fake_scene(root, views, a):
        p = Path(root) / f"scene_{views}"
        p.mkdir(parents=True, exist_ok=True)
        return p

    def fake_ibr(src, args):
        calls.append(args)
        if "--until" in args and "--from" not in args:  # the untimed preparation run
            Path(args[args.index("run") + 1]).mkdir(parents=True, exist_ok=True)
        return 1.0, 2.0

    monkeypatch.setattr(speed, "_scene", fake_scene)
    monkeypatch.setattr(speed, "_ibr", fake_ibr)
    p = argparse.ArgumentParser()
    speed.add_arguments(p)
    a = p.parse_args(["--views", "2", "--stages", "render_views", "--no-frames", "--out", "rel/out"])
    assert speed.main(a) == 0
    assert calls, "no stage process was started"
    for args in calls:
        for flag in ("run", "--input"):
            if flag in args:
                path = Path(args[args.index(flag) + 1])
                assert path.is_absolute(), args
                assert tmp_path in path.parents, args
    assert (tmp_path / "rel" / "out" / "speed.json").is_file()
