"""Confusion matrix of the diagnostics: every catalogue effect hidden in simulated data, several
magnitudes and seeds, ranked among every registered effect.

Usage::

    python benchmarks/diagnose_confusion.py [--seeds 0 1] [--duration 3] [--jobs 2] [--quick]

Prints JSON to stdout and writes ``benchmarks/results/diagnose_confusion.json`` (and a Markdown
table, ``diagnose_confusion.md``).

Each recording is the ``sway`` scenario (standing on both feet, the CoM swaying: enough motion
for the contact parameters to show) with one hidden effect of the catalogue at a large and a
small magnitude (``CASES``), or none, the IMU bias random walk off (so that "none" means none).
:func:`flexforce.compare.diagnostics.run.diagnose` ranks every registered effect by greedy forward
selection and adds the significant ones (``add=["auto"]``).  Per recording: the first effect
selected (the row of the confusion matrix is the truth, the column the first selected effect,
``none`` when nothing is significant), all the effects selected, and the force, CoP and tilt
RMSE before and after adding them.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from flexforce.compare.diagnostics.config import DEFAULT
from flexforce.compare.diagnostics.run import Candidate, mark_rivals

PUSH = {"type": "external-wrench", "link": "@base", "start": 1.5, "duration": 0.4}
CASES = {
    "external-wrench": [{**PUSH, "force": [40.0, 0.0, 0.0]}, {**PUSH, "force": [0.0, 15.0, 0.0]}],
    "gyro-bias": [{"type": "gyro-bias", "value": [0.0, 0.01, 0.0]},
                  {"type": "gyro-bias", "value": [0.003, 0.0, 0.0]}],
    "accel-bias": [{"type": "accel-bias", "value": [0.08, -0.05, 0.0]},
                   {"type": "accel-bias", "value": [0.0, 0.03, 0.0]}],
    "stiffness": [{"type": "stiffness", "stiffness": 0.7, "damping": 1.0},
                  {"type": "stiffness", "stiffness": 1.2, "damping": 1.0}],
    "anisotropic-stiffness": [{"type": "anisotropic-stiffness", "k_fs": [1.0, 1.0, 0.7], "k_ts": [0.7, 1.0, 1.0]},
                              {"type": "anisotropic-stiffness", "k_fs": [1.0, 1.0, 1.0], "k_ts": [1.0, 1.3, 1.0]}],
    "nonlinear-stiffness": [{"type": "nonlinear-stiffness", "beta_f": 4000.0, "beta_t": 0.0},
                            {"type": "nonlinear-stiffness", "beta_f": 0.0, "beta_t": 400.0}],
    "com-offset": [{"type": "com-offset", "offset": [0.02, 0.0, 0.0]},
                   {"type": "com-offset", "offset": [0.0, -0.01, 0.0]}],
}
KEYS = ("force_N", "cop_m", "rotation_rad")


def one(job):
    truth, level, effect, seed, duration = job
    try:
        return _one(truth, level, effect, seed, duration)
    except Exception as exc:  # one failed recording must not lose the others
        return {"truth": truth, "level": level, "effect": effect, "seed": seed, "selected": [],
                "first": "error", "error": f"{type(exc).__name__}: {exc}"}


def _one(truth, level, effect, seed, duration):
    from flexforce.compare.diagnostics import diagnose
    from flexforce.datasets.sim.scenario import Scenario
    from flexforce.datasets.sim.simulator import Simulator

    sc = Scenario.load("sway")
    sc.duration = duration
    sc.seed = seed
    sc.imu_noise = {"gyro_bias_rw": 0.0, "accel_bias_rw": 0.0}
    sc.effects = [effect] if effect else []
    rec = Simulator(sc).run()
    t0 = time.perf_counter()
    d = diagnose(rec, add=["auto"], ekf=False, max_effects=2)
    out = {"truth": truth, "level": level, "effect": effect, "seed": seed,
           "selected": list(d.selected), "first": d.selected[0] if d.selected else "none",
           "ranking": [{"effect": c.effect, "score": c.score, "significant": c.significant, "summary": c.summary}
                       for c in d.rounds[0]] if d.rounds else [],
           "before": {k: d.before.rmse[k] for k in KEYS},
           "after": {k: d.after.rmse[k] for k in KEYS} if d.after else None,
           "before_flags": len(d.before.flags), "after_flags": len(d.after.flags) if d.after else None,
           "seconds": time.perf_counter() - t0}
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--duration", type=float, default=3.0)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--quick", action="store_true", help="large magnitude, first seed only")
    ap.add_argument("--only", nargs="*", default=None, help="truths to run (effect names or 'none')")
    ap.add_argument("--fresh", action="store_true", help="ignore the results already in --out")
    ap.add_argument("--out", default=str(Path(__file__).with_name("results") / "diagnose_confusion.json"))
    args = ap.parse_args()
    seeds = args.seeds[:1] if args.quick else args.seeds
    jobs = []
    for seed in seeds:
        if args.only is None or "none" in args.only:
            jobs.append(("none", None, None, seed, args.duration))
        for name, levels in CASES.items():
            if args.only is not None and name not in args.only:
                continue
            for level, eff in enumerate(levels[:1] if args.quick else levels):
                jobs.append((name, level, eff, seed, args.duration))
    t0 = time.perf_counter()
    # Each finished recording is appended to a side file, so that an interrupted run resumes.
    partial = Path(args.out).with_suffix(".partial.jsonl")
    done = {}
    if Path(args.out).exists() and not args.fresh:  # a finished run: recompute the tables only
        for r in json.loads(Path(args.out).read_text()).get("details", []):
            if r.get("first") != "error":
                done[(r["truth"], r["level"], r["seed"])] = r
    if partial.exists():
        for line in partial.read_text().splitlines():
            r = json.loads(line)
            done[(r["truth"], r["level"], r["seed"])] = r
    todo = [j for j in jobs if (j[0], j[1], j[3]) not in done]
    with ProcessPoolExecutor(max_workers=args.jobs) as pool, partial.open("a") as fh:
        for r in pool.map(one, todo):
            done[(r["truth"], r["level"], r["seed"])] = r
            fh.write(json.dumps(r) + "\n")
            fh.flush()
    runs = [done[(j[0], j[1], j[3])] for j in jobs]
    for r in runs:  # the first round's rivals of its best, by the diagnosis's own rule
        row = [Candidate(c["effect"], (), 1, c["score"], None, None, None, c["significant"])
               for c in r.get("ranking") or []]
        mark_rivals(row)
        r["rivals"] = list(row[0].rivals) if row else []
    truths = ["none", *CASES]
    cols = [*truths, "error"]
    matrix = {t: {c: 0 for c in cols} for t in truths}
    for r in runs:
        matrix[r["truth"]][r["first"] if r["first"] in cols else "none"] += 1
    falls = {}
    for r in runs:
        if r["truth"] == "none" or r.get("after") is None:
            continue
        for k in KEYS:
            falls.setdefault(r["truth"], {}).setdefault(k, []).append(r["after"][k] / r["before"][k])
    result = {
        "benchmark": "diagnose_confusion", "scenario": "sway", "duration_s": args.duration, "seeds": seeds,
        "cases": CASES, "matrix": matrix,
        "correct_first": sum(r["first"] == r["truth"] for r in runs), "runs": len(runs),
        "tie": DEFAULT.tie, "ambiguous_first": [[r["truth"], r["level"], r["seed"], r["first"], r["rivals"]]
                                          for r in runs if r["rivals"]],
        "selected": {f'{r["truth"]}/{r["level"]}/{r["seed"]}': r["selected"] for r in runs},
        "error_ratio_after_before": {t: {k: [float(np.min(v)), float(np.max(v))] for k, v in d.items()}
                                     for t, d in falls.items()},
        "details": runs, "wall_s": time.perf_counter() - t0,
        "machine": {"python": platform.python_version(), "cpus": os.cpu_count()},
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=1))
    lines = ["| truth \\ first selected | " + " | ".join(cols) + " |", "|---" * (len(cols) + 1) + "|"]
    for t in truths:
        lines.append(f"| {t} | " + " | ".join(str(matrix[t][c]) if matrix[t][c] else "." for c in cols) + " |")
    Path(args.out).with_suffix(".md").write_text("\n".join(lines) + "\n")
    partial.unlink()
    print(json.dumps({k: v for k, v in result.items() if k != "details"}, indent=1))


if __name__ == "__main__":
    main()
