"""Record the kernels ``flexforce demo`` compiles, with their argument types, into
``flexforce/demo_kernels.py`` (what :func:`flexforce.pipeline.prepare_demo_kernels` has a helper
process compile on a first run).  Run after changing a kernel's name or argument types::

    python benchmarks/demo_kernels.py

The demo runs here on an empty kernel cache (a temporary ``XDG_CACHE_HOME``) without the helper,
so that every kernel it calls is compiled here, in the order it calls them (~2 minutes on 2 cores).
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

LISTING = Path(__file__).resolve().parents[1] / "flexforce" / "demo_kernels.py"


def record() -> list[tuple[str, str, str]]:
    """Run the demo quietly on an empty kernel cache, without the helper; the kernels it compiled."""
    with tempfile.TemporaryDirectory() as tmp:
        os.environ["XDG_CACHE_HOME"] = tmp
        from flexforce import jit, pipeline
        from flexforce.cli import main

        pipeline.prepare_demo_kernels = lambda: None
        with jit.recording_compiles() as compiled:
            if main(["demo", "-q", "-o", os.path.join(tmp, "demo")]) != 0:
                raise SystemExit("the demo failed")
    return compiled


def write(kernels: list[tuple[str, str, str]], path: Path = LISTING) -> None:
    """Replace the listing of ``path`` (``DEMO_KERNELS``) with ``kernels``."""
    text = path.read_text(encoding="utf-8")
    start = text.index("DEMO_KERNELS: list")
    end = text.index("\n]\n", start) + 1
    rows = "".join(f"    ({m!r}, {f!r},\n     {s!r}),\n" for m, f, s in kernels)
    path.write_text(text[:start] + "DEMO_KERNELS: list[tuple[str, str, str]] = [\n" + rows + text[end:],
                    encoding="utf-8")


if __name__ == "__main__":
    kernels = record()
    write(kernels)
    print(f"{LISTING}: {len(kernels)} kernels")
