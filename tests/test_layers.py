"""The package's shape: no module imports another that (through any chain) imports it back,
and the layers of pyproject.toml's import-linter contract hold (what ``lint-imports`` checks in
CI, asserted here too so that the test command catches an upward import)."""

from __future__ import annotations

import tomllib
from pathlib import Path

import grimp

PYPROJECT = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())
LAYERS = PYPROJECT["tool"]["importlinter"]["contracts"][0]["layers"]


def import_graph() -> grimp.ImportGraph:
    return grimp.build_graph("td3_jax", exclude_type_checking_imports=True)


def cycles(graph: grimp.ImportGraph) -> list[set[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[set[str]] = []

    def visit(module: str) -> None:
        index[module] = low[module] = len(index)
        stack.append(module)
        for other in sorted(graph.find_modules_directly_imported_by(module)):
            if other not in index:
                visit(other)
                low[module] = min(low[module], low[other])
            elif other in stack:
                low[module] = min(low[module], index[other])
        if low[module] == index[module]:
            component = set()
            while True:
                other = stack.pop()
                component.add(other)
                if other == module:
                    break
            if len(component) > 1:
                found.append(component)

    for module in sorted(graph.modules):
        if module not in index:
            visit(module)
    return found


def test_cycle_finder_finds_a_planted_cycle():
    graph = grimp.ImportGraph()
    for name in ("p", "p.a", "p.b", "p.c"):
        graph.add_module(name)
    graph.add_import(importer="p.a", imported="p.b")
    graph.add_import(importer="p.b", imported="p.a")
    graph.add_import(importer="p.c", imported="p.a")
    assert cycles(graph) == [{"p.a", "p.b"}]


def test_no_module_imports_itself_back():
    assert cycles(import_graph()) == []


def test_no_layer_imports_a_layer_above_it():
    graph = import_graph()
    for lower_index, lower in enumerate(LAYERS):
        for higher in LAYERS[:lower_index]:
            chains = graph.find_shortest_chains(importer=lower, imported=higher)
            assert not chains, f"{lower} imports {higher}: {sorted(chains)[:3]}"


def test_every_module_belongs_to_a_layer():
    """A module outside every layer would escape the contract (the package face and
    ``__main__`` only)."""
    outside = {m for m in import_graph().modules
               if not any(m == layer or m.startswith(layer + ".") for layer in LAYERS)}  # fmt: skip
    assert outside == {"td3_jax", "td3_jax.__main__"}
