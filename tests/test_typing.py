"""flexforce as static tools see it from a user's project: typed (py.typed), every folder of the
source tree in the distribution, and mypy resolving ``flexforce.<name>`` from the installed (or strict
editable) copy outside the repository, where the folders' remapping is not at hand."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import tomllib
from pathlib import Path

import flexforce

ROOT = Path(__file__).resolve().parents[1]

REINSTALL = 'pip install -e ".[test]" --config-settings editable_mode=strict'
"""The install that static tools can follow (setuptools' default editable mode is an import hook)."""


def _package_dirs() -> dict[str, Path]:
    """Every package of the source tree (a folder with an ``__init__.py`` under a mapped folder) ->
    its folder, named as it imports (pyproject's ``[tool.setuptools.package-dir]``)."""
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    out = {}
    for name, folder in config["package-dir"].items():
        for init in sorted((ROOT / folder).rglob("__init__.py")):
            rel = init.parent.relative_to(ROOT / folder).parts
            out[".".join((name, *rel))] = init.parent
    return out


def test_every_package_of_the_source_tree_is_distributed():
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    missing = sorted(set(_package_dirs()) - set(config["packages"]))
    assert not missing, f"packages not in pyproject.toml's [tool.setuptools] packages (the wheel lacks them): {missing}"
    assert "py.typed" in config["package-data"]["flexforce"]
    assert (ROOT / "flexforce" / "py.typed").is_file()


def test_the_installed_copy_has_every_module():
    """A strict editable install links each file: a module added since is missing until reinstalled."""
    installed = Path(flexforce.__path__[-1])  # beside this folder when run from the repository's root
    if installed.resolve() == ROOT / "flexforce":
        return  # setuptools' default (lenient) editable install: the folders themselves, through its import hook
    missing = [f"{name}.{path.stem}" for name, folder in _package_dirs().items() for path in folder.glob("*.py")
               if not (installed.joinpath(*name.split(".")[1:]) / path.name).exists()]
    assert not missing, f"modules missing from the installed copy {installed}: {missing}; reinstall ({REINSTALL})"


def test_mypy_resolves_flexforce_outside_the_repository(tmp_path):
    """A user's file, type-checked in a folder of its own: mypy finds the installed package, reads
    its signatures (not ``Any``), and reports the one call that breaks them."""
    (tmp_path / "mypy.ini").write_text("[mypy]\n")
    (tmp_path / "user.py").write_text(textwrap.dedent("""\
        import flexforce as ff
        from flexforce.factors.physics import contact_wrench

        reveal_type(contact_wrench)
        rec: ff.Recording = ff.simulate("stand", seed="three")
        est: ff.Estimate = ff.run_ekf(rec, ff.ModelConfig.from_recording(rec))
        """))
    env = {k: v for k, v in os.environ.items() if k not in ("MYPYPATH", "PYTHONPATH")}
    done = subprocess.run([sys.executable, "-m", "mypy", "--config-file", "mypy.ini",
                           "--cache-dir", str(tmp_path / "cache"), "user.py"],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    out = done.stdout + done.stderr
    lines = [line for line in out.splitlines() if line.startswith("user.py:")]
    errors = [line for line in lines if ": error:" in line]
    assert not any("flexforce" in line and "import" in line for line in errors), (
        f"mypy did not resolve flexforce from its installed copy ({REINSTALL}, or a wheel):\n{out}")
    assert errors == ['user.py:5: error: Argument "seed" to "simulate" has incompatible type "str"; '
                      'expected "int | None"  [arg-type]'], out
    revealed = [line for line in lines if "Revealed type" in line]
    assert len(revealed) == 1 and "params: flexforce.datasets.quantities.ContactParams" in revealed[0], out
    assert done.returncode == 1, out
