"""The packages' import graph reads as layers: no cycles among modules, the core (`racklay`)
never imports the apps built on it (`transfer`, `annotate`), and no module imports another
module's private (`_underscore`) names. Read from the source with `ast`, so imports inside
functions count too: a lazy import hides a cycle from Python, not from this test."""
from __future__ import annotations

import ast
from pathlib import Path

from conftest import REPO as ROOT

PACKAGES = ("racklay", "transfer", "annotate")


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules() -> dict[str, Path]:
    return {module_name(p): p for pkg in PACKAGES for p in sorted((ROOT / pkg).rglob("*.py"))}


def imports(name: str, path: Path, known: set[str]) -> list[tuple[str, str, int]]:
    """(imported module, imported name or "", line) for every import of a project module in
    `path`. `from pkg import mod` counts as importing `pkg.mod` when that is a module."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(a.name, "", node.lineno) for a in node.names if a.name.split(".")[0] in PACKAGES]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            if mod.split(".")[0] not in PACKAGES:
                continue
            for a in node.names:
                sub = f"{mod}.{a.name}"
                out.append((sub, "", node.lineno) if sub in known else (mod, a.name, node.lineno))
    return out


def graph() -> tuple[dict[str, set[str]], list[tuple[str, str, str, int]]]:
    mods = modules()
    edges: dict[str, set[str]] = {m: set() for m in mods}
    named = []
    for m, p in mods.items():
        for target, name, line in imports(m, p, set(mods)):
            while target and target not in mods:      # `import racklay.synth.recipe` names a module
                target = target.rpartition(".")[0]
            if target and target != m:
                edges[m].add(target)
            named.append((m, target, name, line))
    return edges, named


def find_cycle(edges: dict[str, set[str]]) -> list[str] | None:
    """One cycle (as a closed path) if the graph has any, by depth-first search. A package's
    `__init__` importing its own submodules is part of the graph like any other import."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m: str):
        state[m] = 1
        stack.append(m)
        for n in sorted(edges.get(m, ())):
            if state.get(n) == 1:
                return stack[stack.index(n):] + [n]
            if n not in state and (c := visit(n)):
                return c
        stack.pop()
        state[m] = 2
        return None

    for m in sorted(edges):
        if m not in state and (c := visit(m)):
            return c
    return None


def test_the_graph_walker_sees_imports():
    edges, _ = graph()
    assert "racklay.onnx" in edges["racklay.predict"]           # from .onnx import ...
    assert "racklay.model" in edges["racklay.checkpoint"]
    assert "racklay.synth.recipe" in edges["transfer.demo"]      # an import inside a function
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None


def test_no_import_cycles():
    cycle = find_cycle(graph()[0])
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_core_does_not_import_the_apps():
    edges, _ = graph()
    bad = sorted(f"{m} imports {n}" for m, ns in edges.items() if m.startswith("racklay")
                 for n in ns if n.split(".")[0] != "racklay")
    assert not bad, "racklay must not depend on transfer/annotate: " + "; ".join(bad)


def test_no_private_names_from_other_modules():
    _, named = graph()
    bad = sorted(f"{m}:{line} imports {t}.{n}" for m, t, n, line in named
                 if n.startswith("_") and not n.startswith("__") and t != m)
    assert not bad, "private names imported across modules: " + "; ".join(bad)
