"""Every function of the package is at most moderately branched (cyclomatic complexity <= 20, radon's C);
only the compiled kernels, whose flat loop nests are for numba's speed and say so, are exempt."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

radon = pytest.importorskip("radon.complexity", reason="radon is in the [test] extra")

SRC = Path(__file__).resolve().parents[1] / "src" / "skelid"
LIMIT = 20


def _blocks():
    for path in sorted(SRC.rglob("*.py")):
        text = path.read_text(encoding="utf-8")
        for block in radon.cc_visit(text):
            yield path, text, block


def test_no_function_is_more_branched_than_the_limit_except_the_compiled_kernels():
    over = []
    for path, text, block in _blocks():
        if block.complexity <= LIMIT:
            continue
        doc = ""
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.FunctionDef) and node.name == block.name and node.lineno == block.lineno:
                doc = ast.get_docstring(node) or ""
        if path.name.endswith("_kernel.py") and "flat" in doc:
            continue
        over.append(f"{path.relative_to(SRC)}:{block.lineno} {block.name} ({block.complexity})")
    assert not over, "split these functions (or, for a compiled kernel, say why it is flat): " + ", ".join(over)


def test_the_check_sees_a_branched_function():
    branchy = "def f(x):\n" + "".join(f"    if x == {i}:\n        return {i}\n" for i in range(25)) + "    return -1\n"
    assert max(b.complexity for b in radon.cc_visit(branchy)) > LIMIT
