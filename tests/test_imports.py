"""The import graph of `bulbjax/`: no circles, imports only run downward through the layers, and
the rooms of an experiment (`ROOMS`) are entered through their faces.

Every module of the package is parsed with `ast` (nothing is imported): each `import` and
`from ... import` anywhere in it (at module level, in functions, under `TYPE_CHECKING`) is an
edge to the bulbjax module it names (`from pkg import name` names `pkg.name` when that is a
module, else `pkg` itself). Importing `a.b.c` also runs the `__init__` of `a` and `a.b`; those
implicit edges are left out, as a package's `__init__` only hands names on.

Layers, top to bottom (a module may import its own layer and the ones below, never above):
  8. the command line and the commands it drives: `bulbjax.cli`, `bulbjax.__main__`,
     `bulbjax.run_command` (`bulbjax run`), `bulbjax.reproduce.*` (the paper's plan of runs);
  7. the run: `bulbjax.run.*` (settings resolved, resume, the run loop, its folder, checkpoints,
     console, provenance, figures drawn in a run, the offline fit's driver);
  6. the report: `bulbjax.report.*` (records, report files, findings, figures of learners);
  5. the epoch: `bulbjax.epoch.*` (the jitted epoch and its parts, seed groups, compiled programs,
     the offline fit's programs);
  4. what an experiment is built from: `bulbjax.config` (ExperimentConfig, RunOptions, presets,
     config.json read back) and `bulbjax.offline_config` (OfflineConfig, built on it);
  3. what an experiment is made of: `bulbjax.learners.*`, `bulbjax.envs.*`, `bulbjax.interop.*`,
     `bulbjax.gym`, and the package root `bulbjax` (`bulbjax.make`);
  2. what those use: `bulbjax.data.*` (buffers, windows, synthetic data), `bulbjax.eval.*` (probes,
     state specs, object scores), `bulbjax.rl.*` (PPO);
  1. utilities: `bulbjax.assets.*` (model assets and their cache), `bulbjax.compile_cache`,
     `bulbjax.distributed` (multi-process settings).
A new module or package must be given a layer here (the test says which one has none).

Inside a layer, a folder of a package (`FOLDERS`: the multi-object scenes `bulbjax.envs.objects`,
the SPAIR learner `bulbjax.learners.spair`, the epoch's environment side `bulbjax.epoch.rollouts`) is entered from its package by the modules named for
it only, and imports none of the package's modules named as out of its reach (its siblings, the
package's registry and face), as its `__init__.py` says.
"""

from __future__ import annotations

import ast
import os
from typing import Iterable

import pytest

ROOT = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "bulbjax")

# module-name prefix -> layer (the longest matching prefix wins)
LAYERS: dict[str, int] = {
    "bulbjax.cli": 8, "bulbjax.__main__": 8, "bulbjax.run_command": 8, "bulbjax.env_commands": 8, "bulbjax.reproduce": 8,
    "bulbjax.run": 7, "bulbjax.report": 6, "bulbjax.epoch": 5, "bulbjax.config": 4, "bulbjax.offline_config": 4,
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
    run's face, the run loop the faces of the epoch and the report, and the epoch's modules
    import the device layer."""
    assert len(graph) > 40
    assert "bulbjax.run" in graph["bulbjax.cli"]  # a function-level import
    assert {"bulbjax.epoch", "bulbjax.report"} <= set(graph["bulbjax.run.loop"])
    assert "bulbjax.epoch.devices" in graph["bulbjax.epoch.loop"]
    assert "bulbjax.report.records" in graph["bulbjax.report.findings"]


def test_every_module_has_a_layer(graph):
    missing = [m for m in graph if layer(m) is None]
    assert not missing, f"modules without a layer in tests/test_imports.py LAYERS: {missing}"


def test_no_import_cycles(graph):
    found = cycles(graph)
    assert not found, "import cycles: " + "; ".join(" -> ".join(c) for c in found)


def test_imports_run_downward(graph):
    bad = upward(graph)
    assert not bad, "imports from a lower layer to a higher one:\n" + "\n".join(bad)


# the rooms of an experiment: each one's face (its `__init__.py`) is the door the others use
ROOMS = ("bulbjax.epoch", "bulbjax.report", "bulbjax.run")


def room(module: str) -> str | None:
    return next((r for r in ROOMS if module == r or module.startswith(r + ".")), None)


def behind_faces(graph: dict[str, dict[str, int]]) -> list[str]:
    """Every import of a file inside a room from outside that room, as 'a -> b, line n'."""
    return [f"{a} -> {b}, line {line}" for a, edges in sorted(graph.items()) for b, line in sorted(edges.items())
            if room(b) and b != room(b) and room(a) != room(b)]


def test_rooms_meet_at_their_faces(graph):
    """The epoch, the report and the run import one another, and the command line and
    `bulbjax.reproduce` import them, through their faces (`bulbjax.epoch`, ...), never through
    the files behind them (tests and benchmarks may open any file)."""
    bad = behind_faces(graph)
    assert not bad, "imports past a room's face:\n" + "\n".join(bad)


# a folder inside a package -> (the modules of that package, outside the folder, that may import
# it; the modules of that package it never imports)
FOLDERS: dict[str, tuple[set[str], set[str]]] = {
    "bulbjax.envs.objects": ({"bulbjax.envs.registry"},
                             {"bulbjax.envs", "bulbjax.envs.registry", "bulbjax.envs.pendulum",
                              "bulbjax.envs.locomotion"}),
    "bulbjax.epoch.rollouts": ({"bulbjax.epoch.loop", "bulbjax.epoch.offline"},
                               {"bulbjax.epoch", "bulbjax.epoch.loop", "bulbjax.epoch.offline",
                                "bulbjax.epoch.learning", "bulbjax.epoch.probing",
                                "bulbjax.epoch.programs", "bulbjax.epoch.groups",
                                "bulbjax.epoch.apart"}),
    "bulbjax.learners.spair": ({"bulbjax.learners"},
                               {"bulbjax.learners", "bulbjax.learners.registry", "bulbjax.learners.plugins",
                                "bulbjax.learners.vae", "bulbjax.learners.sequential",
                                "bulbjax.learners.contrastive"}),
}


def _inside(module: str, package: str) -> bool:
    return module == package or module.startswith(package + ".")


def folder_crossings(graph: dict[str, dict[str, int]]) -> list[str]:
    """Every import into a folder of `FOLDERS` from a module of its package not named as its
    entrance, and every import from the folder of a module of its package out of its reach,
    as 'a -> b, line n'."""
    out = []
    for folder, (entrances, never) in FOLDERS.items():
        package = folder.rpartition(".")[0]
        for a, edges in sorted(graph.items()):
            for b, line in sorted(edges.items()):
                into = _inside(b, folder) and not _inside(a, folder) and _inside(a, package)
                if (into and a not in entrances) or (_inside(a, folder) and b in never):
                    out.append(f"{a} -> {b}, line {line}")
    return out


def test_folders_keep_to_their_package(graph):
    """The multi-object scenes are imported in `bulbjax.envs` by the registry alone and import
    only the envs' core (no single-body domain, not the registry); SPAIR is imported in
    `bulbjax.learners` by the face alone and imports no other learner, nor the registry."""
    assert all(f in graph for f in FOLDERS), "a folder of FOLDERS is not in the package"
    bad = folder_crossings(graph)
    assert not bad, "imports across a folder's edge:\n" + "\n".join(bad)


def test_checks_catch_what_they_look_for():
    """The cycle finder, the layer check and the face check on made-up graphs: a three-module
    circle and an upward import are reported (and nothing else); a diamond is no circle; an
    import past a room's face from outside it is reported, one inside the room or of a face is not."""
    g = {"bulbjax.epoch.a": {"bulbjax.epoch.b": 1}, "bulbjax.epoch.b": {"bulbjax.epoch.c": 2},
         "bulbjax.epoch.c": {"bulbjax.epoch.a": 3, "bulbjax.data.x": 4},
         "bulbjax.data.x": {"bulbjax.epoch.d": 5}, "bulbjax.epoch.d": {},
         "bulbjax.cli": {"bulbjax.epoch.d": 6, "bulbjax.data.x": 7}}
    found = cycles(g)
    assert len(found) == 1
    three = found[0]
    assert len(three) == 4 and three[0] == three[-1] and set(three) == {"bulbjax.epoch.a", "bulbjax.epoch.b",
                                                      "bulbjax.epoch.c"}
    assert upward(g) == ["bulbjax.data.x (layer 2) -> bulbjax.epoch.d (layer 5), line 5"]
    assert cycles({"bulbjax.cli": {"bulbjax.data.x": 1, "bulbjax.rl.y": 2}, "bulbjax.data.x": {"bulbjax.rl.y": 3},
                   "bulbjax.rl.y": {}}) == []
    assert behind_faces({"bulbjax.cli": {"bulbjax.run": 1, "bulbjax.run.loop": 2},
                         "bulbjax.run.loop": {"bulbjax.run.rundir": 3, "bulbjax.epoch": 4, "bulbjax.epoch.loop": 5}}) \
        == ["bulbjax.cli -> bulbjax.run.loop, line 2", "bulbjax.run.loop -> bulbjax.epoch.loop, line 5"]
    assert folder_crossings({"bulbjax.envs.registry": {"bulbjax.envs.objects.incline": 1},
                             "bulbjax.envs.base": {"bulbjax.envs.objects.incline": 2},
                             "bulbjax.envs.objects.incline": {"bulbjax.envs.locomotion": 3, "bulbjax.envs.base": 4},
                             "bulbjax.epoch.probing": {"bulbjax.envs.objects.rearrange": 5}}) \
        == ["bulbjax.envs.base -> bulbjax.envs.objects.incline, line 2",
            "bulbjax.envs.objects.incline -> bulbjax.envs.locomotion, line 3"]
