"""The layers the folders show (DESIGN.md, "Layout"): every import of the package points down.

physics (``factors/``) <- estimators (``smoother/``) <- comparison and diagnostics (``compare/``),
with the data (``datasets/``) beside the estimators and the CLI on top.  Each module of each
folder is parsed with :mod:`ast` (nothing is imported, so a lazy import inside a function counts
as much as one at the top, and so does an import under ``TYPE_CHECKING``: a type is a dependency
too) and every ``flexforce.*`` module it names must belong to a layer it may depend on.  The few
existing exceptions are listed in :data:`EXCEPTIONS` with their reason; an exception that no
longer occurs fails the test, so the list only shrinks.
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
"""Layer name -> folder (pyproject's ``[tool.setuptools.package-dir]``: ``flexforce.<layer>``)."""

ALLOWED = {
    "factors": {"factors", "errors", "options"},
    "smoother": {"smoother", "factors", "datasets", "errors", "options"},
    "datasets": {"datasets", "factors", "errors", "options"},
    "compare": {"compare", "smoother", "factors", "datasets", "errors", "options"},
}
"""Layer -> the layers its modules may import (``errors``: :mod:`flexforce.errors`, the one base
exception and one per layer; ``options``: :mod:`flexforce.options`, the checks of the config
dataclasses, which imports only ``errors``: both importable from everywhere)."""

SIMULATOR = ("datasets/simulator.py", "datasets/effects.py", "datasets/scenario.py")
"""The simulator, its scenarios and its hidden effects (the ground truth): independent of the
estimators' physics, so that a shared mistake cannot cancel out (nothing of factors, smoother,
compare)."""

EXCEPTIONS = {
    ("factors/model.py", "flexforce.datasets.robot"):
        "ModelConfig.from_recording builds the contact parameters from the robot's config "
        "(RobotConfig, RobotModel), lazily; it goes with the config dataclasses "
        "which take the robot's parameters as arguments",
    ("compare/runner.py", "flexforce.estimators"):
        "the comparison runs every estimator through the one entry point run_estimator (name -> EKF, "
        "batch, fixed-lag), which sits in flexforce/ above compare/ because it imports compare's EKF; "
        "it resolves once the EKF has its own subpackage below the comparison",
}
"""``(module, imported module) -> reason``: the upward imports that exist today."""


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
    """``flexforce.factors.core`` -> ``factors``; ``flexforce.errors`` -> ``errors``."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "flexforce"


def _violations() -> dict[tuple[str, str], str]:
    """``(module, imported module) -> what is wrong`` over every module of the package."""
    out = {}
    for layer, folder in FOLDERS.items():
        for path in _modules(folder):
            rel = path.relative_to(ROOT).as_posix()
            for target in sorted(_imports(path)):
                to = _layer(target)
                if to == "cli" and rel != "flexforce/cli.py":
                    out[(rel, target)] = "nothing imports the CLI"
                elif rel in SIMULATOR and to in {"factors", "smoother", "compare"}:
                    out[(rel, target)] = "the simulator imports nothing of factors, smoother or compare"
                elif layer in ALLOWED and to not in ALLOWED[layer]:
                    out[(rel, target)] = f"{layer} may import {sorted(ALLOWED[layer])}, not {to}"
                elif rel == "flexforce/errors.py":
                    out[(rel, target)] = "the errors module imports nothing of the project"
                elif rel == "flexforce/options.py" and to != "errors":
                    out[(rel, target)] = "the options module imports only the errors"
    return out


def test_the_parser_sees_the_imports_it_must_check():
    """The checker itself: imports at the top, inside a function and under ``TYPE_CHECKING`` are seen."""
    found = _imports(ROOT / "smoother" / "problem.py")
    assert {"flexforce.errors", "flexforce.factors", "flexforce.factors.effects",
            "flexforce.datasets.recording"} <= found, found  # the last one under TYPE_CHECKING
    assert "flexforce.datasets.robot" in _imports(ROOT / "factors" / "model.py")  # inside a method
    assert _layer("flexforce.factors.core") == "factors" and _layer("flexforce.errors") == "errors"


def test_every_import_points_down_the_layers():
    bad = {key: why for key, why in _violations().items() if key not in EXCEPTIONS}
    assert not bad, "upward imports:\n" + "\n".join(f"  {m} imports {t}: {why}" for (m, t), why in bad.items())


def test_the_recorded_exceptions_still_exist():
    """An exception that was resolved is taken off the list (it only shrinks)."""
    stale = set(EXCEPTIONS) - set(_violations())
    assert not stale, f"resolved, remove from EXCEPTIONS: {sorted(stale)}"


def test_the_effect_protocol_names_no_estimator():
    """The effects' protocol lives in factors/ and imports nothing above it."""
    effects = _imports(ROOT / "factors" / "effects.py")
    assert {_layer(m) for m in effects} <= {"factors", "errors"}, effects


def _problem_is_a_view(problem: Problem) -> ProblemView:
    """mypy checks this (tests/ is in [tool.mypy] files): the smoother's Problem satisfies the view."""
    return problem


def test_the_smoothers_problem_has_every_member_of_the_view():
    members = {name for name in vars(ProblemView) if not name.startswith("_")}
    have = {f.name for f in dataclasses.fields(Problem)} | set(dir(Problem))
    assert members and members <= have, members - have
