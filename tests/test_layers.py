"""The package's layers (docs/DESIGN.md "Layers"): what may import what, and no import cycles.

Every `import` of the package is read from the source (also the ones inside functions: a lazy
import is still a dependency), so a module that reaches upward fails here, not in review."""
from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "ibr_pipeline"

# layer of each top-level module / subpackage of ibr_pipeline, lowest first
LAYERS = {
    "foundation": {"errors", "scene", "config", "layout", "workspace", "cache", "metrics", "flip_ldr",
                   "threads", "io"},
    "geometry": {"geometry"},
    "algorithms": {"render", "raytree", "nn"},
    "synthetic": {"synthetic"},
    "orchestration": {"runner", "executors", "pipeline", "stages", "gt_workspace", "report",
                      "report_sections", "report_figures",
                      "viewer"},
    "cli": {"cli", "commands", "__main__", "__init__"},
}
ORDER = list(LAYERS)
LAYER_OF = {name: layer for layer, names in LAYERS.items() for name in names}
# algorithm packages are siblings: none imports another (geometry is below all of them)
SIBLINGS_INDEPENDENT = {"algorithms"}
# the one module that reaches the top-level benchmarks/ package (`ibr bench NAME`)
BENCH_COMMAND = "ibr_pipeline.commands.bench"


def _modules() -> dict[str, Path]:
    mods = {}
    for p in PKG.rglob("*.py"):
        parts = list(p.relative_to(PKG.parent).with_suffix("").parts)
        if parts[-1] == "__init__" and len(parts) > 1:
            parts = parts[:-1]
        mods[".".join(parts)] = p
    return mods


def _imports(mods: dict[str, Path]) -> dict[str, set[str]]:
    """module -> the package modules it imports (anywhere in its source)."""
    edges: dict[str, set[str]] = defaultdict(set)
    for mod, path in mods.items():
        is_pkg = path.name == "__init__.py"
        for node in ast.walk(ast.parse(path.read_text())):
            targets = []
            if isinstance(node, ast.ImportFrom):
                if node.level:
                    base = mod.split(".") if is_pkg else mod.split(".")[:-1]
                    base = base[:len(base) - (node.level - 1)]
                    target = ".".join(base + ([node.module] if node.module else []))
                else:
                    target = node.module or ""
                # `from pkg import mod` depends on pkg.mod; `from mod import name` on mod
                targets = [f"{target}.{a.name}" if f"{target}.{a.name}" in mods else target
                           for a in node.names]
            elif isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            for t in targets:
                if t.split(".")[0] == "benchmarks":
                    edges[mod].add(t)
                while t and t not in mods:
                    t = t.rpartition(".")[0]
                if t and t != mod:
                    edges[mod].add(t)
    return edges


def _top(mod: str) -> str:
    parts = mod.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def test_every_module_has_a_layer():
    tops = {_top(m) for m in _modules()}
    assert tops <= set(LAYER_OF), f"modules without a layer in LAYERS: {sorted(tops - set(LAYER_OF))}"


def test_no_module_imports_a_higher_layer_or_a_sibling_algorithm():
    bad = []
    for mod, targets in _imports(_modules()).items():
        src = LAYER_OF[_top(mod)]
        for t in targets:
            if t.split(".")[0] == "benchmarks":
                if mod != BENCH_COMMAND:
                    bad.append(f"{mod} -> {t} (only {BENCH_COMMAND} imports benchmarks/)")
                continue
            dst = LAYER_OF[_top(t)]
            if ORDER.index(dst) > ORDER.index(src):
                bad.append(f"{mod} ({src}) -> {t} ({dst})")
            elif src == dst and src in SIBLINGS_INDEPENDENT and _top(mod) != _top(t):
                bad.append(f"{mod} -> {t} (sibling algorithm packages)")
    assert not bad, "layer violations:\n" + "\n".join(sorted(bad))


def test_no_import_cycles():
    edges = _imports(_modules())
    index, low, stack, on, cycles, counter = {}, {}, [], set(), [], [0]

    def visit(v):   # Tarjan's strongly connected components
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in edges.get(v, ()):
            if w.split(".")[0] != "ibr_pipeline":
                continue
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    for m in _modules():
        if m not in index:
            visit(m)
    assert not cycles, f"import cycles: {cycles}"


def test_the_rules_catch_a_back_edge(tmp_path, monkeypatch):
    """The checker itself: a geometry module importing a stage is reported."""
    mods = {"ibr_pipeline.geometry.x": tmp_path / "x.py", "ibr_pipeline.stages": tmp_path / "s.py"}
    mods["ibr_pipeline.geometry.x"].write_text("def f():\n    from ..stages import STAGES\n")
    mods["ibr_pipeline.stages"].write_text("")
    edges = _imports(mods)
    assert edges["ibr_pipeline.geometry.x"] == {"ibr_pipeline.stages"}
