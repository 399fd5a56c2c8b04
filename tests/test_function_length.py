"""No function of the package outside the compiled kernels is longer than 120 lines.

Each module of each package folder is parsed with :mod:`ast`; a function (or method, nested ones
included) decorated with ``njit`` is a compiled kernel, written as loops on purpose, and is left
out.  A longer function is split into named parts.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = ("flexforce", "smoother", "factors", "datasets", "compare")
MAX_LINES = 120


def _compiled(node: ast.FunctionDef | ast.AsyncFunctionDef) -> bool:
    for deco in node.decorator_list:
        target = deco.func if isinstance(deco, ast.Call) else deco
        name = target.attr if isinstance(target, ast.Attribute) else getattr(target, "id", "")
        if name == "njit":
            return True
    return False


def test_no_function_outside_the_kernels_is_longer_than_120_lines():
    long = []
    for folder in FOLDERS:
        for path in sorted((ROOT / folder).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and not _compiled(node):
                    lines = (node.end_lineno or node.lineno) - node.lineno + 1
                    if lines > MAX_LINES:
                        long.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name} ({lines} lines)")
    assert not long, "functions longer than 120 lines: " + "; ".join(long)


def test_the_check_sees_the_kernels():
    """The kernels are recognised as such (the check would pass vacuously on a wrong decorator name)."""
    tree = ast.parse((ROOT / "smoother" / "window_kernel.py").read_text(encoding="utf-8"))
    kernels = [n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef) and _compiled(n)]
    assert any(n.name == "window_system" for n in kernels)
