"""The packages' import graph reads as layers: no cycles among modules, the core (`racklay`)
never imports the apps built on it (`transfer`, `annotate`), and no module imports another
module's private (`_underscore`) names. Read from the source with `ast`, so imports inside
functions count too: a lazy import hides a cycle from Python, not from this test. The graph
reader is the one that draws docs/img/modules.png (bench/figures/module_graph.py)."""
from __future__ import annotations

from bench.figures.module_graph import find_cycle, graph


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


def test_commands_do_not_import_the_command_line_back():
    """racklay/cli.py loads the command modules by name; they take option types from
    racklay.config and CLIError from racklay.commands, never from the module that loads them."""
    edges, _ = graph()
    bad = sorted(m for m, ns in edges.items() if ".commands" in m and "racklay.cli" in ns)
    assert not bad, "command modules importing racklay.cli: " + ", ".join(bad)
