"""`ibr synth` argparse hooks (its generation benchmark: tests/benchmarks/test_synth_bench.py)."""
from __future__ import annotations

import argparse
import subprocess
import sys

import pytest

from ibr_pipeline.errors import InputError
from ibr_pipeline.commands import synth as cli


def _parse(argv, add=cli.add_synth_arguments):
    p = argparse.ArgumentParser()
    add(p)
    return p.parse_args(argv)


def test_cli_module_import_is_light():
    code = ("import sys, ibr_pipeline.commands.synth; "
            "print([m for m in ('open3d', 'pycolmap', 'torch', 'numpy') if m in sys.modules])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_every_flag_has_help():
    p = argparse.ArgumentParser()
    cli.add_synth_arguments(p)
    for action in p._actions:
        if not isinstance(action, argparse._HelpAction):
            assert action.help, action.dest


@pytest.mark.parametrize("argv, flag", [
    (["tiny", "OUT", "--width", "0"], "--width"),
    (["tiny", "OUT", "--height", "-3"], "--height"),
    (["tiny", "OUT", "--views", "1"], "--views"),
    (["tiny", "OUT", "--depth-scale", "2"], "--depth-scale"),
    (["tiny", "OUT", "--jobs", "0"], "--jobs"),
])
def test_bad_arguments_name_the_flag(argv, flag, tmp_path):
    args = _parse([argv[0], str(tmp_path / "out")] + argv[2:])
    with pytest.raises(InputError, match=flag):
        cli.synth_main(args)
    assert not (tmp_path / "out").exists()  # validated before anything is written


def test_unknown_scene():
    with pytest.raises(SystemExit):
        _parse(["nope", "OUT"])
    with pytest.raises(InputError, match="NAME"):
        cli.synth_main(argparse.Namespace(name="nope", out="OUT"))


def test_synth_main(tmp_path):
    args = _parse(["tiny", str(tmp_path / "t"), "--views", "3", "--test-views", "1",
                   "--flythrough", "0", "--width", "64", "--height", "48", "--no-gt-layers",
                   "--no-progress"])
    assert cli.synth_main(args) == 0
    assert len(list((tmp_path / "t" / "images").glob("*.png"))) == 3
    assert not (tmp_path / "t" / "gt" / "I0").exists()
