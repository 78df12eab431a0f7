"""The package's import graph: no cycles, and each layer imports only the layers below it.

Every ``import`` statement counts, also those inside functions (a lazy import
still ties the two modules together); imports under ``if TYPE_CHECKING:`` and
code held in strings (the compiled kernels' child processes) do not.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"
PKG = SRC / "skelid"


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(SRC).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for p in PKG.rglob("*.py")}


def _is_type_checking(node: ast.If) -> bool:
    t = node.test
    return (isinstance(t, ast.Name) and t.id == "TYPE_CHECKING") or (
        isinstance(t, ast.Attribute) and t.attr == "TYPE_CHECKING")


def _imports(tree: ast.AST):
    """Every Import / ImportFrom node outside ``if TYPE_CHECKING:`` blocks."""
    stack = [tree]
    while stack:
        node = stack.pop()
        if isinstance(node, ast.If) and _is_type_checking(node):
            stack.extend(node.orelse)
            continue
        if isinstance(node, ast.Import | ast.ImportFrom):
            yield node
        stack.extend(ast.iter_child_nodes(node))


def _resolve(name: str, node, mods: dict[str, Path]) -> set[str]:
    """The skelid modules an import statement in module ``name`` loads (package inits implied by a
    submodule import are left out: every module would otherwise import ``skelid`` itself)."""
    out = set()
    if isinstance(node, ast.Import):
        for a in node.names:
            if a.name in mods:
                out.add(a.name)
        return out
    base = node.module or ""
    if node.level:
        pkg = name if mods[name].name == "__init__.py" else name.rpartition(".")[0]
        for _ in range(node.level - 1):
            pkg = pkg.rpartition(".")[0]
        base = f"{pkg}.{base}" if base else pkg
    if not base.startswith("skelid"):
        return out
    for a in node.names:
        sub = f"{base}.{a.name}"
        if sub in mods:
            out.add(sub)
        elif base in mods:
            out.add(base)
    return out


def import_graph() -> dict[str, set[str]]:
    mods = _modules()
    graph = {}
    for name, path in mods.items():
        tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
        graph[name] = set().union(*(_resolve(name, n, mods) for n in _imports(tree))) - {name}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index, low, on, stack, out = {}, {}, set(), [], []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph.get(v, ())):
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
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_the_graph_sees_lazy_imports():
    g = import_graph()
    assert "skelid.io.results" in g["skelid.cli"]  # imported inside a command function only
    assert "skelid.estimators.fit._lm_kernel" in g["skelid.estimators.fit.pose"]


def test_cycles_finds_a_cycle():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycle():
    found = cycles(import_graph())
    assert not found, "import cycles: " + "; ".join(" <-> ".join(c) for c in found)


ESTIMATORS = ("skelid.estimators.marker", "skelid.estimators.multitrial", "skelid.estimators.sampler",
              "skelid.estimators.paper", "skelid.estimators")
LAYERS = {
    # a stage never imports the estimators that assemble it
    "skelid.estimators.fit": ESTIMATORS + ("skelid.estimators.uncertainty", "skelid.estimators.checks",
                                           "skelid.estimators.online"),
    "skelid.estimators.uncertainty": ESTIMATORS + ("skelid.estimators.online",),
    "skelid.estimators.checks": ESTIMATORS + ("skelid.estimators.online",),
    "skelid.estimators.online": ESTIMATORS,
    # the model knows nothing of how it is fitted, read or shown
    "skelid.model": ("skelid.estimators", "skelid.io.results", "skelid.cli", "skelid.report", "skelid.live"),
}


@pytest.mark.parametrize("layer", sorted(LAYERS))
def test_layers_import_downwards_only(layer):
    g = import_graph()
    bad = []
    for mod, targets in g.items():
        if mod != layer and not mod.startswith(layer + "."):
            continue
        for t in targets:
            for banned in LAYERS[layer]:
                # the package ``skelid.estimators`` itself (its ``__init__``) is banned, not all below it
                under = banned != "skelid.estimators" and t.startswith(banned + ".")
                if (t == banned or under) and not (t == layer or t.startswith(layer + ".")):
                    bad.append(f"{mod} -> {t}")
    assert not bad, "imports against the layering: " + ", ".join(sorted(bad))
