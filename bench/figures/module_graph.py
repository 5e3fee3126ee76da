"""The import graph of racklay, transfer and annotate, read from the source with `ast` (imports
inside functions count too), and its picture, docs/img/modules.png: the modules in layers, each
importing only from the layers below it. tests/test_import_graph.py checks the same graph (no
cycles, the core never imports the apps).

    .venv/bin/python -m bench.figures.module_graph [--out docs/img/modules.png]
"""
from __future__ import annotations

import argparse
import ast
import io
from pathlib import Path

from bench.common import REPO

PACKAGES = ("racklay", "transfer", "annotate")

def module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules() -> dict[str, Path]:
    return {module_name(p): p for pkg in PACKAGES for p in sorted((REPO / pkg).rglob("*.py"))}


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


#: sub-packages drawn as one box (their modules are many and alike: one per command, WareSynth's stages)
GROUPS = ("racklay.commands", "transfer.commands", "annotate.commands", "racklay.synth")
COLOURS = {"racklay": "#dbe9f6", "racklay.synth": "#e3f1dc", "transfer": "#fbe5cf", "annotate": "#efe0f3"}


def grouped(edges: dict[str, set[str]]) -> dict[str, set[str]]:
    """The graph with GROUPS collapsed to one node each and package __init__s left out."""
    def node(m: str) -> str:
        return next((g for g in GROUPS if m == g or m.startswith(g + ".")), m)

    out: dict[str, set[str]] = {}
    for m, ns in edges.items():
        if m in PACKAGES or m.endswith(".__main__"):
            continue
        a = node(m)
        out.setdefault(a, set()).update(node(n) for n in ns if n not in PACKAGES and node(n) != a)
    return out


def layers(edges: dict[str, set[str]]) -> dict[str, int]:
    """Layer of each module: 0 for one that imports none of the others, else 1 + its deepest import."""
    depth: dict[str, int] = {}

    def d(m: str, seen=()) -> int:
        if m not in depth:
            ns = [n for n in edges.get(m, ()) if n not in seen]
            depth[m] = 1 + max((d(n, seen + (m,)) for n in ns), default=-1)
        return depth[m]

    for m in edges:
        d(m)
    return depth


def draw(out: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch
    from PIL import Image

    from racklay.atomic import atomic_write_bytes

    edges = grouped(graph()[0])
    layer = layers(edges)
    rows: dict[int, list[str]] = {}
    for m in sorted(edges, key=lambda m: (m.split(".")[0] != "racklay", m)):
        rows.setdefault(layer[m], []).append(m)
    wide = max(len(v) for v in rows.values())
    pos = {m: ((i + 0.5) * wide / len(ms), y) for y, ms in rows.items() for i, m in enumerate(ms)}
    fig, ax = plt.subplots(figsize=(1.55 * wide + 1, 0.85 * len(rows) + 1.2))
    for m, ns in edges.items():
        for n in ns:
            (x0, y0), (x1, y1) = pos[m], pos[n]
            ax.annotate("", xy=(x1, y1 + 0.18), xytext=(x0, y0 - 0.18),
                        arrowprops=dict(arrowstyle="->", color="#8a96a3", lw=0.45, alpha=0.45))
    for m, (x, y) in pos.items():
        colour = COLOURS.get(m if m in COLOURS else m.split(".")[0], "#eeeeee")
        ax.text(x, y, m + (".*" if m in GROUPS else ""), ha="center", va="center", fontsize=7.5,
                bbox=dict(boxstyle="round,pad=0.3", fc=colour, ec="#6b7785", lw=0.6))
    ax.set_xlim(-0.2, wide + 0.2)
    ax.set_ylim(-0.6, max(rows) + 0.9)
    ax.axis("off")
    ax.legend(handles=[Patch(fc=c, ec="#6b7785", label=k) for k, c in COLOURS.items()], loc="upper left",
              fontsize=8, ncol=4, frameon=False)
    ax.set_title("Import graph: each module imports only from rows below it (arrow: importer -> imported). "
                 "Generated by bench/figures/module_graph.py", fontsize=9)
    fig.subplots_adjust(left=0.01, right=0.99, bottom=0.01, top=0.94)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    small = io.BytesIO()   # 64 colours: a third of the bytes, the same picture
    Image.open(buf).convert("RGB").quantize(64).save(small, format="PNG", optimize=True)
    atomic_write_bytes(out, small.getvalue())
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "img" / "modules.png", help="output image")
    args = ap.parse_args(argv)
    edges = graph()[0]
    print(f"{len(edges)} modules, {sum(map(len, edges.values()))} imports; cycle: {find_cycle(edges)}")
    print(f"wrote {draw(args.out)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
