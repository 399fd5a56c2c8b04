"""The layers the folders show (DESIGN.md, "Layout"; docs/architecture.md): every import points down.

Each module of each folder is parsed with :mod:`ast` (nothing is imported, so a lazy import inside a
function counts as much as one at the top, and so does an import under ``TYPE_CHECKING``: a type is
a dependency too) and every ``flexforce.*`` module it names must belong to its own layer or to one
it may depend on (:data:`ALLOWED`).  There are no exceptions.
"""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

from flexforce.factors.effects import ProblemView
from flexforce.smoother import Problem

ROOT = Path(__file__).resolve().parents[1]

FOLDERS = {"factors": "factors", "smoother": "smoother", "datasets": "datasets", "compare": "compare",
           "flexforce": "flexforce"}
"""Top-level package -> folder (pyproject's ``[tool.setuptools.package-dir]``: ``flexforce.<name>``)."""

LAYERS: dict[str, tuple[str, ...]] = {
    "ground": ("flexforce.errors", "flexforce.options", "flexforce.jit", "flexforce.processes"),
    "data": ("flexforce.datasets",),
    "io": ("flexforce.datasets.io",),
    "sim": ("flexforce.datasets.sim",),
    "physics": ("flexforce.factors",),
    "estimators": ("flexforce.smoother", "flexforce.compare.ekf"),
    "comparison": ("flexforce.compare",),
    "diagnostics": ("flexforce.compare.diagnostics",),
    "reports": ("flexforce.compare.reports",),
    "api": ("flexforce",),
    "cli": ("flexforce.cli",),
}
"""Layer -> the module prefixes it holds; a module belongs to the layer of its longest prefix
(``flexforce.datasets.io.bagio`` is I/O, ``flexforce.datasets.recording`` data)."""

ALLOWED: dict[str, set[str]] = {
    "ground": set(),
    "data": {"ground"},
    "io": {"data", "ground"},
    "sim": {"data", "ground"},
    "physics": {"data", "ground"},
    "estimators": {"physics", "data", "ground"},
    "comparison": {"estimators", "physics", "io", "data", "ground"},
    "diagnostics": {"comparison", "estimators", "physics", "io", "data", "ground"},
    "reports": {"diagnostics", "comparison", "estimators", "physics", "io", "data", "ground"},
    "api": {"reports", "diagnostics", "comparison", "estimators", "physics", "io", "sim", "data", "ground"},
    "cli": {"api", "reports", "diagnostics", "comparison", "estimators", "physics", "io", "sim", "data", "ground"},
}
"""Layer -> the other layers its modules may import (docs/architecture.md draws them).  The data
types and the robot model are at the ground; the physics above them; the estimators (smoothers
and the EKF) above the physics; I/O and the simulator beside the estimators, importing only the
data types and the robot model (the simulator shares no physics with the estimators, so that a
shared mistake cannot cancel out); the comparison, the diagnostics and the reports above the
estimators; the public API and the CLI on top.  Within the ground, :mod:`flexforce.errors` imports
nothing of the project and :mod:`flexforce.options` only the errors."""

GROUND_IMPORTS = {"flexforce.errors": set(), "flexforce.jit": set(), "flexforce.options": {"flexforce.errors"}}
"""What each ground module may import of the project."""


def _modules(folder: str) -> list[Path]:
    return sorted((ROOT / folder).rglob("*.py"))


def _imports(path: Path) -> set[str]:
    """The ``flexforce.*`` modules ``path`` imports (``from flexforce.x import y`` as ``flexforce.x``,
    ``from flexforce import x`` as ``flexforce.x``; relative imports, which the package does not use
    today, resolved against its package)."""
    rel = path.relative_to(ROOT)
    package = ["flexforce"] + ([] if rel.parts[0] == "flexforce" else [rel.parts[0]]) + list(rel.parts[1:-1])
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            out |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[:len(package) - node.level + 1]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            if module == "flexforce" or (node.level and not node.module):
                out |= {f"{module}.{alias.name}" for alias in node.names}
            else:
                out.add(module)
    return {m for m in out if m == "flexforce" or m.startswith("flexforce.")}


def _layer(module: str) -> str:
    """The layer of a module: the one of its longest prefix in :data:`LAYERS`."""
    best, layer = -1, ""
    for name, prefixes in LAYERS.items():
        for prefix in prefixes:
            if (module == prefix or module.startswith(prefix + ".")) and len(prefix) > best:
                best, layer = len(prefix), name
    assert layer, f"{module} belongs to no layer"
    return layer


def _module_name(path: Path) -> str:
    rel = path.relative_to(ROOT)
    parts = ["flexforce"] + ([] if rel.parts[0] == "flexforce" else [rel.parts[0]]) + list(rel.parts[1:])
    parts[-1] = parts[-1].removesuffix(".py")
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _violations() -> dict[tuple[str, str], str]:
    """``(module, imported module) -> what is wrong`` over every module of the package."""
    out = {}
    for folder in FOLDERS.values():
        for path in _modules(folder):
            rel = path.relative_to(ROOT).as_posix()
            name = _module_name(path)
            layer = _layer(name)
            for target in sorted(_imports(path)):
                to = _layer(target)
                if name in GROUND_IMPORTS:
                    if target not in GROUND_IMPORTS[name]:
                        allowed = sorted(GROUND_IMPORTS[name]) or "nothing"
                        out[(rel, target)] = f"{name} imports only {allowed} of the project"
                elif to != layer and to not in ALLOWED[layer]:
                    out[(rel, target)] = f"{layer} may import {sorted(ALLOWED[layer])}, not {to}"
    return out


def test_the_parser_sees_the_imports_it_must_check():
    """The checker itself: imports at the top, inside a function and under ``TYPE_CHECKING`` are seen."""
    found = _imports(ROOT / "smoother" / "problem.py")
    assert {"flexforce.errors", "flexforce.factors", "flexforce.factors.effects",
            "flexforce.datasets.recording"} <= found, found  # the last one under TYPE_CHECKING
    assert "flexforce.datasets.robot" in _imports(ROOT / "factors" / "model.py")  # inside a method
    assert _layer("flexforce.factors.core") == "physics" and _layer("flexforce.errors") == "ground"
    assert _layer("flexforce.datasets.io.bagio") == "io" and _layer("flexforce.datasets.recording") == "data"
    assert _layer("flexforce.compare.ekf.filter") == "estimators" and _layer("flexforce.cli") == "cli"


def test_every_import_points_down_the_layers():
    bad = _violations()
    assert not bad, "upward imports:\n" + "\n".join(f"  {m} imports {t}: {why}" for (m, t), why in bad.items())


def test_every_module_belongs_to_a_layer():
    for folder in FOLDERS.values():
        for path in _modules(folder):
            _layer(_module_name(path))


def test_the_effect_protocol_names_no_estimator():
    """The effects' protocol lives in factors/ and imports nothing above it."""
    for path in sorted((ROOT / "factors" / "effects").glob("*.py")):
        effects = _imports(path)
        assert {_layer(m) for m in effects} <= {"physics", "data", "ground"}, (path.name, effects)


def _problem_is_a_view(problem: Problem) -> ProblemView:
    """mypy checks this (tests/ is in [tool.mypy] files): the smoother's Problem satisfies the view."""
    return problem


def test_the_smoothers_problem_has_every_member_of_the_view():
    members = {name for name in vars(ProblemView) if not name.startswith("_")}
    have = {f.name for f in dataclasses.fields(Problem)} | set(dir(Problem))
    assert members and members <= have, members - have
