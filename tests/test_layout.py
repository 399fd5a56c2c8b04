"""The type checker sees the package as it is installed.

``[tool.setuptools.package-dir]`` maps the folders to ``flexforce.<name>``; mypy reads the same
layout from the symlink tree ``.mypy/flexforce`` (pyproject.toml, ``[tool.mypy]``).  A module added
to ``flexforce/`` without its link, or a folder mapped elsewhere, would silently go unchecked.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_mypy_tree_mirrors_the_package_dir_mapping():
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())
    mapping = config["tool"]["setuptools"]["package-dir"]
    tree = ROOT / ".mypy" / "flexforce"
    assert mapping["flexforce"] == "flexforce"
    for package, folder in mapping.items():
        if package == "flexforce":
            continue
        link = tree / package.split(".", 1)[1]
        assert link.is_symlink() and link.resolve() == (ROOT / folder).resolve(), package
    for module in (ROOT / "flexforce").glob("*.py"):
        link = tree / module.name
        assert link.is_symlink() and link.resolve() == module.resolve(), f"{link} -> {module} missing"
    assert {p.name for p in tree.iterdir()} == {p.name for p in (ROOT / "flexforce").glob("*.py")} | {
        package.split(".", 1)[1] for package in mapping if package != "flexforce"}
