"""The README is a front door that works as written.

Every ```python block of README.md runs as it stands, in a fresh process in an empty folder, exits 0
and prints what the ```text block after it says; the two install commands are those `.ci/run`
runs; the command-line table names every subcommand; every page of docs/ is linked with the
changelog and the results; and the page stays short (at most 150 lines), with no results tables or
release history, which live in docs/results.md and CHANGELOG.md.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"

_FENCE = re.compile(r"^```(\w*)\n(.*?)^```\s*$", re.M | re.S)


def _blocks() -> list[tuple[str, str]]:
    """``(language, body)`` of every fenced block, in order."""
    return [(m[1], m[2]) for m in _FENCE.finditer(README.read_text(encoding="utf-8"))]


def _examples() -> list[tuple[str, str | None]]:
    """Each python block with the text block right after it (its printed output), if any."""
    blocks = _blocks()
    out = []
    for i, (lang, body) in enumerate(blocks):
        if lang == "python":
            nxt = blocks[i + 1] if i + 1 < len(blocks) else None
            out.append((body, nxt[1] if nxt and nxt[0] == "text" else None))
    return out


def test_the_readme_has_a_python_example():
    assert _examples(), "README.md has no ```python block"


@pytest.mark.parametrize("index", range(len(_examples())))
def test_each_python_block_runs_as_written_and_prints_what_it_says(index, tmp_path):
    code, expected = _examples()[index]
    assert expected is not None, f"python block {index + 1}: no ```text block after it with what it prints"
    env = dict(os.environ, MPLBACKEND="Agg")
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, f"python block {index + 1} failed:\n{proc.stderr[-3000:]}"
    assert proc.stdout.strip() == expected.strip(), (
        f"python block {index + 1} printed:\n{proc.stdout}\nthe README says:\n{expected}")


def _ci_install_args() -> str:
    """What `.ci/run` passes to ``pip install`` for flexforce and its test extra."""
    for line in (ROOT / ".ci" / "run").read_text(encoding="utf-8").splitlines():
        found = re.match(r'\s*python -m pip install (-e .*\.\[test\].*)$', line)
        if found:
            return found[1].strip()
    raise AssertionError(".ci/run installs no test extra")


def test_the_two_commands_are_those_ci_runs():
    text = README.read_text(encoding="utf-8")
    args = _ci_install_args()
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8")
    assert re.search(r"^pytest -q$", ci, re.M), ".ci/run no longer runs the fast suite as `pytest -q`"
    assert f"pip install {args} && pytest -q" in text
    demo_args = args.replace('".[test]"', ".")
    assert f"pip install {demo_args} && flexforce demo" in text


def test_the_command_line_table_names_every_subcommand():
    from flexforce.cli import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    text = README.read_text(encoding="utf-8")
    missing = [name for name in sub.choices if f"`flexforce {name}" not in text]
    assert not missing, f"README's command line omits {missing}"


def test_every_doc_page_the_changelog_and_the_results_are_linked():
    text = README.read_text(encoding="utf-8")
    links = set(re.findall(r"\]\(([^)#]+)", text))
    pages = {p.relative_to(ROOT).as_posix() for p in (ROOT / "docs").glob("*.md")}
    assert pages | {"CHANGELOG.md", "docs/results.md"} <= links, sorted(pages - links)
    for link in links:
        if "://" not in link:
            assert (ROOT / link).exists(), f"README links to {link}, which does not exist"


def test_a_front_door_not_a_report():
    lines = README.read_text(encoding="utf-8").splitlines()
    assert len(lines) <= 150, f"README.md has {len(lines)} lines; at most 150"
    text = "\n".join(lines).lower()
    for history in ("before this release", "previous release", "(was ", " was "):
        assert history not in text, f"release history in README.md ({history!r}): CHANGELOG.md holds it"
    tables = [line for line in lines if line.startswith("|") and re.search(r"\d+(\.\d+)? ?(n|mm|µs|ms|°|s)\b", line)]
    assert not tables, f"a results table in README.md (docs/results.md holds them): {tables[:2]}"
