"""docs/examples/: each script runs as written, in seconds, through the public API only, and is
rendered to an HTML page (its code, what it printed, its figure embedded) as a notebook would be."""

from __future__ import annotations

import ast
import base64
import html
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import ICUB_DIR

EXAMPLES = Path(__file__).resolve().parents[1] / "docs" / "examples"
WALK = ICUB_DIR / "icub-walk-12s"
CASES = {"from_bag.py": ([str(WALK)], "from_bag.png"), "from_arrays.py": ([], "from_arrays.png")}
ALLOWED_IMPORTS = {"flexforce", "matplotlib.pyplot", "numpy", "sys"}


def render_html(script: Path, stdout: str, images: list[Path]) -> str:
    """A self-contained HTML page: the script's docstring as text, its code, what it printed and
    its figures (PNG, base64)."""
    source = script.read_text(encoding="utf-8")
    doc = ast.get_docstring(ast.parse(source)) or ""
    figures = "".join(f'<img alt="{html.escape(p.name)}" src="data:image/png;base64,'
                      f'{base64.b64encode(p.read_bytes()).decode()}">' for p in images)
    printed = f"<pre class=\"out\">{html.escape(stdout)}</pre>" if stdout.strip() else ""
    return (f"<!DOCTYPE html>\n<html><head><meta charset=\"utf-8\"><title>{html.escape(script.name)}</title>"
            "</head><body>"
            f"<h1>{html.escape(script.name)}</h1><p>{html.escape(doc)}</p>"
            f"<pre><code>{html.escape(source)}</code></pre>{printed}{figures}</body></html>\n")


def test_every_example_is_covered():
    assert sorted(p.name for p in EXAMPLES.glob("*.py")) == sorted(CASES)


@pytest.mark.parametrize("name", sorted(CASES))
def test_an_example_uses_the_public_api_only(name):
    tree = ast.parse((EXAMPLES / name).read_text(encoding="utf-8"))
    imported = {alias.name for node in ast.walk(tree) if isinstance(node, ast.Import) for alias in node.names}
    imported |= {node.module for node in ast.walk(tree) if isinstance(node, ast.ImportFrom) and node.module}
    assert imported <= ALLOWED_IMPORTS, f"{name} imports {sorted(imported - ALLOWED_IMPORTS)}"
    assert "flexforce" in imported
    body = [node for node in tree.body if not (isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant))]
    lines = {n for node in body for n in range(node.lineno, (node.end_lineno or node.lineno) + 1)}
    assert len(lines) <= 30, f"{name} has {len(lines)} lines of code; an example is short"


@pytest.mark.parametrize("name", sorted(CASES))
def test_an_example_runs_in_seconds_and_renders_to_html(name, tmp_path):
    args, png = CASES[name]
    if name == "from_bag.py" and not WALK.exists():
        pytest.skip(f"the iCub walk bag is not at {WALK}")
    env = dict(os.environ, MPLBACKEND="Agg")
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, str(EXAMPLES / name), *args], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=120)
    elapsed = time.perf_counter() - start
    assert proc.returncode == 0, f"{name} failed:\n{proc.stderr[-3000:]}"
    assert elapsed < 30.0, f"{name} took {elapsed:.1f} s; an example runs in seconds"
    figure = tmp_path / png
    assert figure.is_file() and figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    page = tmp_path / f"{Path(name).stem}.html"
    page.write_text(render_html(EXAMPLES / name, proc.stdout, [figure]), encoding="utf-8")
    text = page.read_text(encoding="utf-8")
    assert "import flexforce as ff" in text and "data:image/png;base64,iVBORw0KGgo" in text
    assert base64.b64encode(figure.read_bytes()).decode() in text


def test_the_html_page_escapes_the_code(tmp_path):
    script = tmp_path / "s.py"
    script.write_text('"""a <b> & c"""\nx = 1 < 2\n')
    text = render_html(script, "", [])
    assert "a &lt;b&gt; &amp; c" in text and "x = 1 &lt; 2" in text and "<img" not in text
