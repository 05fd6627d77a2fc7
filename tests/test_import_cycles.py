"""No import cycles: between modules (function-level imports included) and between packages. Shared
pieces live in the module that owns them, below both users (issue 17). Imports under ``if TYPE_CHECKING``
are annotations only and are not counted."""

from __future__ import annotations

import ast
from pathlib import Path

from tests.support.procs import REPO

ROOT = REPO
PACKAGES = ("protocol", "edge_camera", "robot_agent", "mapper", "planner", "deploy", "sim", "bench")


def _modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for f in (ROOT / pkg).rglob("*.py"):
            name = ".".join(f.relative_to(ROOT).with_suffix("").parts)
            out[name.removesuffix(".__init__")] = f
    return out


def _runtime_imports(tree: ast.AST) -> list[str]:
    """Absolute imports that run (``from a.b import c`` names ``a.b`` and ``a.b.c``), skipping
    ``if TYPE_CHECKING:`` blocks."""
    found: list[str] = []
    stack = [tree]
    while stack:
        node = stack.pop()
        if isinstance(node, ast.If) and isinstance(node.test, ast.Name) and node.test.id == "TYPE_CHECKING":
            stack.extend(node.orelse)
            continue
        if isinstance(node, ast.Import):
            found += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found += [node.module, *(f"{node.module}.{a.name}" for a in node.names)]
        stack.extend(ast.iter_child_nodes(node))
    return found


def import_graph() -> dict[str, set[str]]:
    mods = _modules()
    return {m: {t for t in _runtime_imports(ast.parse(f.read_text())) if t in mods and t != m}
            for m, f in mods.items()}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one member (iterative Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    out: list[list[str]] = []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    x = stack.pop()
                    on_stack.discard(x)
                    comp.append(x)
                    if x == v:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))
    return out


def test_cycle_finder_finds_a_cycle_and_accepts_a_chain() -> None:
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": {"c"}, "c": set()}) == []


def test_type_checking_imports_do_not_count() -> None:
    tree = ast.parse("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import x.y\nelse:\n    import z\n"
                     "def f():\n    from a.b import c\n")
    assert sorted(_runtime_imports(tree)) == ["a.b", "a.b.c", "typing", "typing.TYPE_CHECKING", "z"]


def test_no_module_imports_itself_through_others() -> None:
    assert cycles(import_graph()) == []


def test_no_two_packages_import_each_other() -> None:
    graph = import_graph()
    uses = {(m.split(".")[0], t.split(".")[0]) for m, ts in graph.items() for t in ts}
    both_ways = sorted({tuple(sorted(p)) for p in uses if p[0] != p[1] and (p[1], p[0]) in uses})
    assert both_ways == [], [(m, t) for m, ts in graph.items() for t in ts
                             if tuple(sorted((m.split(".")[0], t.split(".")[0]))) in both_ways]
