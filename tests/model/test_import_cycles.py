"""No module of skelid.model imports, even lazily, a module that imports it back."""

from __future__ import annotations

import ast
from pathlib import Path

import skelid

SRC = Path(skelid.__file__).resolve().parent


def _module_name(path: Path) -> str:
    parts = path.relative_to(SRC.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path, modules: set) -> set:
    """The skelid modules ``path`` imports anywhere in it (inside functions too); a package's own
    ``__init__`` is not counted for ``from package import submodule``."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name in modules}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            subs = {f"{node.module}.{a.name}" for a in node.names} & modules
            out |= subs or ({node.module} & modules)
    return out


def _graph() -> dict:
    files = {_module_name(p): p for p in SRC.rglob("*.py")}
    modules = set(files)
    return {m: _imports(p, modules) - {m} for m, p in files.items()}


def _reaches(graph: dict, start: str, goal: str) -> list | None:
    """A chain of imports from ``start`` to ``goal``, or None."""
    seen, stack = {start}, [(start, [start])]
    while stack:
        m, path = stack.pop()
        for n in sorted(graph.get(m, ())):
            if n == goal:
                return path + [n]
            if n not in seen:
                seen.add(n)
                stack.append((n, path + [n]))
    return None


def test_no_import_cycle_through_a_model_module():
    graph = _graph()
    model_modules = sorted(m for m in graph if m.startswith("skelid.model."))
    assert "skelid.model.description" in model_modules and "skelid.model._fk_kernel" in model_modules
    cycles = [chain for m in model_modules for n in sorted(graph[m]) if (chain := _reaches(graph, n, m))]
    assert not cycles, "import cycles: " + "; ".join(" -> ".join(c) for c in cycles)


def test_the_cycle_finder_finds_a_cycle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert _reaches(graph, "b", "a") == ["b", "c", "a"]
    assert _reaches(graph, "a", "d") is None
