"""The import graph of `bulbjax/`: no circles, and imports only run downward through the layers.

Every module of the package is parsed with `ast` (nothing is imported): each `import` and
`from ... import` anywhere in it (at module level, in functions, under `TYPE_CHECKING`) is an
edge to the bulbjax module it names (`from pkg import name` names `pkg.name` when that is a
module, else `pkg` itself). Importing `a.b.c` also runs the `__init__` of `a` and `a.b`; those
implicit edges are left out, as a package's `__init__` only hands names on.

Layers, top to bottom (a module may import its own layer and the ones below, never above):
  5. the command line and the commands it drives: `bulbjax.cli`, `bulbjax.__main__`,
     `bulbjax.run_command` (`bulbjax run`), `bulbjax.reproduce.*` (the paper's plan of runs);
  4. experiments: `bulbjax.experiment.*` (config and its resolution, the epoch's parts, runs,
     reports);
  3. what an experiment is made of: `bulbjax.learners.*`, `bulbjax.envs.*`, `bulbjax.interop.*`,
     `bulbjax.gym`, and the package root `bulbjax` (`bulbjax.make`);
  2. what those use: `bulbjax.data.*` (buffers, windows, synthetic data), `bulbjax.eval.*` (probes,
     state specs, object scores), `bulbjax.rl.*` (PPO);
  1. utilities: `bulbjax.assets.*` (model assets and their cache), `bulbjax.compile_cache`,
     `bulbjax.distributed` (multi-process settings).
A new module or package must be given a layer here (the test says which one has none).
"""

from __future__ import annotations

import ast
import os
from typing import Iterable

import pytest

ROOT = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "bulbjax")

# module-name prefix -> layer (the longest matching prefix wins)
LAYERS: dict[str, int] = {
    "bulbjax.cli": 5, "bulbjax.__main__": 5, "bulbjax.run_command": 5, "bulbjax.reproduce": 5,
    "bulbjax.experiment": 4,
    "bulbjax.learners": 3, "bulbjax.envs": 3, "bulbjax.interop": 3, "bulbjax.gym": 3, "bulbjax": 3,
    "bulbjax.data": 2, "bulbjax.eval": 2, "bulbjax.rl": 2,
    "bulbjax.assets": 1, "bulbjax.compile_cache": 1, "bulbjax.distributed": 1,
}


def modules(root: str = ROOT) -> dict[str, str]:
    """Every module of the package under `root`: dotted name -> file path (packages by their
    `__init__.py`, named as the package)."""
    out = {}
    base = os.path.dirname(root)
    for d, _, files in os.walk(root):
        for f in files:
            if f.endswith(".py"):
                path = os.path.join(d, f)
                parts = os.path.relpath(path, base)[:-3].split(os.sep)
                if parts[-1] == "__init__":
                    parts = parts[:-1]
                out[".".join(parts)] = path
    return out


def _imported(tree: ast.AST, name: str, is_package: bool) -> Iterable[tuple[str, int]]:
    """(dotted target, line) of every import statement in `tree`, relative ones resolved."""
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield a.name, node.lineno
        elif isinstance(node, ast.ImportFrom):
            pkg = node.module or ""
            if node.level:
                here = name.split(".") if is_package else name.split(".")[:-1]
                up = here[: len(here) - (node.level - 1)]
                pkg = ".".join(up + ([node.module] if node.module else []))
            for a in node.names:
                yield f"{pkg}.{a.name}", node.lineno


def import_graph(root: str = ROOT) -> dict[str, dict[str, int]]:
    """module -> {bulbjax module it imports: line of the (first) import}."""
    mods = modules(root)
    graph: dict[str, dict[str, int]] = {}
    for name, path in mods.items():
        with open(path) as f:
            tree = ast.parse(f.read(), path)
        edges: dict[str, int] = {}
        for target, line in _imported(tree, name, path.endswith("__init__.py")):
            while target and target not in mods:  # `from pkg import name`: pkg.name or pkg
                target = target.rpartition(".")[0]
            if target and target != name:
                edges.setdefault(target, line)
        graph[name] = edges
    return graph


def cycles(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each as one cycle
    through its members (a module importing itself is not counted)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    comps: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, {}):
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
                comps.append(_cycle_through(graph, set(comp)))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return comps


def _cycle_through(graph: dict[str, dict[str, int]], comp: set[str]) -> list[str]:
    """One import cycle inside a strongly connected component: a -> b -> ... -> a."""
    start = min(comp)
    prev = {start: None}
    todo = [start]
    while todo:  # breadth-first back to `start`
        v = todo.pop(0)
        for w in sorted(graph[v]):
            if w == start:
                path = [v]
                while prev[path[-1]] is not None:
                    path.append(prev[path[-1]])
                return path[::-1] + [start]
            if w in comp and w not in prev:
                prev[w] = v
                todo.append(w)
    return sorted(comp)


def layer(module: str) -> int | None:
    best = max((p for p in LAYERS if module == p or module.startswith(p + ".")), key=len, default=None)
    return None if best is None else LAYERS[best]


def upward(graph: dict[str, dict[str, int]]) -> list[str]:
    """Every import from a lower layer to a higher one, as 'a (layer) -> b (layer), line n'."""
    out = []
    for a, edges in sorted(graph.items()):
        for b, line in sorted(edges.items()):
            la, lb = layer(a), layer(b)
            if la is not None and lb is not None and lb > la:
                out.append(f"{a} (layer {la}) -> {b} (layer {lb}), line {line}")
    return out


@pytest.fixture(scope="module")
def graph() -> dict[str, dict[str, int]]:
    return import_graph()


def test_graph_sees_the_package(graph):
    """The graph is the package's (so the checks below look at something): the CLI imports the
    run loop, and the epoch's modules import the device layer."""
    assert len(graph) > 40
    assert "bulbjax.experiment.resolve" in graph["bulbjax.cli"]  # a function-level import
    assert "bulbjax.experiment.devices" in graph["bulbjax.experiment.loop"]
    assert "bulbjax.experiment.records" in graph["bulbjax.experiment.findings"]


def test_every_module_has_a_layer(graph):
    missing = [m for m in graph if layer(m) is None]
    assert not missing, f"modules without a layer in tests/test_imports.py LAYERS: {missing}"


def test_no_import_cycles(graph):
    found = cycles(graph)
    assert not found, "import cycles: " + "; ".join(" -> ".join(c) for c in found)


def test_imports_run_downward(graph):
    bad = upward(graph)
    assert not bad, "imports from a lower layer to a higher one:\n" + "\n".join(bad)


def test_checks_catch_what_they_look_for():
    """The cycle finder and the layer check on a made-up graph: a three-module circle and an
    upward import are reported (and nothing else); a diamond is no circle."""
    g = {"bulbjax.experiment.a": {"bulbjax.experiment.b": 1}, "bulbjax.experiment.b": {"bulbjax.experiment.c": 2},
         "bulbjax.experiment.c": {"bulbjax.experiment.a": 3, "bulbjax.data.x": 4},
         "bulbjax.data.x": {"bulbjax.experiment.d": 5}, "bulbjax.experiment.d": {},
         "bulbjax.cli": {"bulbjax.experiment.d": 6, "bulbjax.data.x": 7}}
    found = cycles(g)
    assert len(found) == 1
    three = found[0]
    assert len(three) == 4 and three[0] == three[-1] and set(three) == {"bulbjax.experiment.a", "bulbjax.experiment.b",
                                                      "bulbjax.experiment.c"}
    assert upward(g) == ["bulbjax.data.x (layer 2) -> bulbjax.experiment.d (layer 4), line 5"]
    assert cycles({"bulbjax.cli": {"bulbjax.data.x": 1, "bulbjax.rl.y": 2}, "bulbjax.data.x": {"bulbjax.rl.y": 3},
                   "bulbjax.rl.y": {}}) == []
