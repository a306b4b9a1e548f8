"""`ibr bench NAME`: the benchmark table, its help, and one-line errors."""
from __future__ import annotations

import argparse
import importlib
import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks import BENCHMARKS, benchmark_by_name
from ibr_pipeline.cli import main

NAMES = [b.name for b in BENCHMARKS]
REPO = Path(__file__).resolve().parents[2]


def _exit_code(argv) -> int:
    try:
        return main(argv)
    except SystemExit as e:
        return e.code


def test_the_table_names_every_benchmark_once_in_order():
    assert NAMES == ["pipeline", "global_mesh", "view_depth", "reflection", "render", "dsrnet",
                     "raytree", "real", "speed", "viewer", "synth"]
    assert benchmark_by_name("raytree").module == "benchmarks.raytree"
    with pytest.raises(KeyError):
        benchmark_by_name("nosuch")
    for b in BENCHMARKS:
        assert b.help and "\n" not in b.help, b.name
        mod = importlib.import_module(b.module)
        assert callable(mod.add_arguments) and callable(mod.main), b.name
        assert mod.__doc__, f"{b.module}: its docstring is the description of its --help"
        assert "__main__" not in Path(mod.__file__).read_text(), f"{b.module}: run it as ibr bench"


@pytest.mark.parametrize("name", NAMES)
def test_every_benchmark_help_prints_its_flags(name, capsys):
    assert _exit_code(["bench", name, "--help"]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"usage: ibr bench {name}")
    p = argparse.ArgumentParser()
    importlib.import_module(benchmark_by_name(name).module).add_arguments(p)
    for action in p._actions:
        if not isinstance(action, argparse._HelpAction):
            assert action.help, f"{name}: {action.dest} has no help"
            if action.option_strings:
                assert action.option_strings[0] in out, f"{name}: {action.dest} not in --help"


def test_bench_help_lists_every_benchmark(capsys):
    assert _exit_code(["bench", "--help"]) == 0
    out = capsys.readouterr().out
    for b in BENCHMARKS:
        assert any(line.split() and line.split()[0] == b.name and b.help.split()[0] in line
                   for line in out.splitlines()), b.name


def test_unknown_benchmark_is_one_line_naming_the_known_ones(capsys):
    assert _exit_code(["bench", "nosuch"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nosuch" in err[0]
    assert all(name in err[0] for name in NAMES)


def test_bench_help_imports_no_heavy_library():
    code = ("import sys; from ibr_pipeline.cli import main\n"
            "try:\n    main(['bench', '--help'])\nexcept SystemExit:\n    pass\n"
            "print([m for m in ('torch', 'open3d', 'pycolmap', 'cv2', 'moderngl', 'matplotlib') "
            "if m in sys.modules])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=REPO)
    assert out.stdout.strip().splitlines()[-1] == "[]"


def test_benchmarks_use_only_the_public_api():
    """No benchmark imports a `_name` or reads a `._member` (of ibr_pipeline or anything else):
    what they measure goes through the API a user has."""
    import ast

    def private(name: str) -> bool:
        return name.startswith("_") and not name.startswith("__")

    bad = []
    for path in sorted((REPO / "benchmarks").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                parts = (node.module or "").split(".") + [a.name for a in node.names]
                bad += [f"{path.name}:{node.lineno} imports {p}" for p in parts if private(p)]
            elif isinstance(node, ast.Import):
                bad += [f"{path.name}:{node.lineno} imports {a.name}" for a in node.names
                        if any(private(p) for p in a.name.split("."))]
            elif isinstance(node, ast.Attribute) and private(node.attr):
                bad.append(f"{path.name}:{node.lineno} reads .{node.attr}")
    assert not bad, "\n".join(bad)
