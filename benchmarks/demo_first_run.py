"""Benchmark: ``flexforce demo`` on a fresh kernel cache (a first run after an install) and again.

    python benchmarks/demo_first_run.py [--repeat 2]

Writes a JSON record to stdout and to ``benchmarks/results/demo_first_run.json``.  Each cold run is
``flexforce demo`` in a fresh process with an empty user cache (a temporary ``XDG_CACHE_HOME``, so
every kernel is compiled, as on a new machine); the warm run repeats it with that cache filled.
Per run: the wall-clock time, the CPU time of the demo and its helper processes (user + system,
from ``getrusage(RUSAGE_CHILDREN)``), when the first line and each "done" line of the demo's
output came (seconds from the start), and whether the demo ran the fixed-lag smoother's general
window path (``flexforce.pipeline.demo_options``).  Targets: the first line within 10 s and the
whole demo within 40 s on a first run (``usable_cores`` is recorded: the helper needs two).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

TARGET_FIRST_LINE_S = 10.0
TARGET_WALL_S = 40.0
DONE = re.compile(r"\]\s+(\S+): done")


def one_run(cache: str, out: str) -> dict:
    """``flexforce demo -o out`` with ``XDG_CACHE_HOME=cache``: times and the lines that mark them."""
    env = dict(os.environ, XDG_CACHE_HOME=cache, PYTHONUNBUFFERED="1")
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "flexforce.cli", "demo", "-o", out], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    assert proc.stdout is not None
    first = None
    done: dict[str, float] = {}
    general = False
    for line in proc.stdout:
        at = time.perf_counter() - t0
        if first is None and line.strip():
            first = at
        for part in line.replace("\r", "\n").splitlines():
            m = DONE.search(part)
            if m:
                done[m.group(1)] = round(at, 2)
            general |= "general path" in part
    if proc.wait() != 0:
        raise SystemExit(f"flexforce demo failed (exit {proc.returncode})")
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"wall_s": round(wall, 2), "cpu_s": round(cpu, 2), "first_line_s": round(first or wall, 2),
            "done_at_s": done, "fixed_lag_general_path": general}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=2, help="cold runs (each with an empty cache)")
    parser.add_argument("--output", type=Path,
                        default=Path(__file__).resolve().parent / "results" / "demo_first_run.json")
    args = parser.parse_args()

    from flexforce.compare.reports.comparison import machine
    from flexforce.compare.runner import usable_cores

    cold, warm = [], None
    for i in range(max(1, args.repeat)):
        with tempfile.TemporaryDirectory() as tmp:
            cache = os.path.join(tmp, "cache")
            cold.append(one_run(cache, os.path.join(tmp, "demo")))
            if i == 0:
                warm = one_run(cache, os.path.join(tmp, "demo-again"))
    best = min(cold, key=lambda r: r["wall_s"])
    record = {
        "benchmark": "demo_first_run",
        "command": "python benchmarks/demo_first_run.py" + (f" --repeat {args.repeat}" if args.repeat != 2 else ""),
        "runs": "flexforce demo -o DIR, XDG_CACHE_HOME empty (cold) then filled (warm)",
        "cold": cold, "warm": warm,
        "cold_wall_s_best": best["wall_s"], "cold_wall_s_worst": max(r["wall_s"] for r in cold),
        "targets": {"first_line_s": TARGET_FIRST_LINE_S, "wall_s": TARGET_WALL_S},
        "first_line_met": all(r["first_line_s"] <= TARGET_FIRST_LINE_S for r in cold),
        "wall_met": all(r["wall_s"] <= TARGET_WALL_S for r in cold),
        "usable_cores": usable_cores(),
        "load_average_at_end": [round(x, 2) for x in os.getloadavg()],
        "machine": machine(),
    }
    text = json.dumps(record, indent=2)
    print(text)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(text + "\n")


if __name__ == "__main__":
    main()
