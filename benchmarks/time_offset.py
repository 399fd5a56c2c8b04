"""The IMU time offset refitted alone, against the truth, on recordings of every kind.

Usage::

    python benchmarks/time_offset.py [--jobs 2]

Writes ``benchmarks/results/time_offset.json`` (every recording: the true and estimated offset,
its sigma, the evidence, the refit's time) and ``time_offset.md`` (the table).

The recordings are 3 s of the wide benchmark's motions (``sway``, ``com-step``,
``weight-shift`` on Romeo and TALOS, noise seed 0, the IMU bias random walk off) with a hidden
offset of 20, 50 or 6 ms or none, and TALOS's short walk (9.5 s, seed 3) with 15 ms or none, where
the footholds are fitted beside the offset (every landing corrects its foothold; without them the
offset stands in for the landings).  Each is ``diagnose(rec, candidates=["time-offset"])``
(``["foothold", "time-offset"]`` on the walks, the offset scored beside the footholds): one
screening and, where it passes, one refit.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent

CASES = [
    ("romeo", "sway", 0.02), ("romeo", "com-step", 0.02), ("talos", "sway", 0.02), ("talos", "sway", 0.05),
    ("talos", "com-step", 0.006), ("romeo", "weight-shift", 0.006), ("talos", "weight-shift", 0.0),
    ("romeo", "sway", 0.0), ("talos", "walk-short", 0.015), ("talos", "walk-short", 0.0),
]
"""(robot, scenario, true offset in s)."""


def one(case) -> dict:
    from flexforce.compare.diagnostics import diagnose
    from flexforce.datasets.sim.scenario import Scenario
    from flexforce.datasets.sim.simulator import Simulator
    from flexforce.factors.model import ModelConfig

    robot, motion, delay = case
    walk = motion.startswith("walk")
    sc = Scenario.load(motion)
    sc.robot = robot
    sc.seed = 3 if walk else 0
    if not walk:
        sc.duration = 3.0
    sc.imu_noise = {"gyro_bias_rw": 0.0, "accel_bias_rw": 0.0}
    sc.effects = [{"type": "time-offset", "delay": delay}] if delay else []
    rec = Simulator(sc).run()
    cands = ["foothold", "time-offset"] if walk else ["time-offset"]
    t0 = time.perf_counter()
    d = diagnose(rec, ModelConfig.from_recording(rec), candidates=cands, add=(), ekf=False, identify=False,
                 max_effects=2)
    seconds = time.perf_counter() - t0
    c = next(c for c in d.ranking if c.effect == "time-offset")
    value = std = None
    if c.parameters and "value" in c.parameters:
        value, std = float(c.parameters["value"][0]), float(c.parameters["std"][0])
    return {"robot": robot, "motion": motion, "truth_ms": 1e3 * delay,
            "beside": [k for k in cands if k != "time-offset"],
            "significant": bool(c.significant), "value_ms": None if value is None else 1e3 * value,
            "std_ms": None if std is None else 1e3 * std, "lr": c.lr, "score": c.score,
            "T": None if c.screen is None else float(c.screen.statistic),
            "p": None if c.screen is None else float(c.screen.p_value), "seconds": round(seconds, 1)}


def markdown(runs: list[dict]) -> str:
    rows = ["| robot | motion | true τ | estimate | significant | 2ΔE | score test T | time |",
            "|---|---|---|---|---|---|---|---|"]
    for r in runs:
        est = "not refitted" if r["value_ms"] is None else f"{r['value_ms']:.1f} ± {r['std_ms']:.1f} ms"
        beside = f" (beside {', '.join(r['beside'])})" if r["beside"] else ""
        rows.append(f"| {r['robot']} | {r['motion']}{beside} | {r['truth_ms']:g} ms | {est} | "
                    f"{'yes' if r['significant'] else 'no'} | {'—' if r['lr'] is None else format(r['lr'], '.1f')} | "
                    f"{'—' if r['T'] is None else format(r['T'], '.1f')} | {r['seconds']:.0f} s |")
    return "\n".join(rows) + "\n"


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--jobs", type=int, default=2, help="recordings diagnosed at once")
    ap.add_argument("--out", default=str(HERE / "results" / "time_offset.json"))
    args = ap.parse_args(argv)
    sys.path.insert(0, str(HERE))
    from flexforce.compare.runner import fork_map

    runs: list[dict | None] = [None] * len(CASES)
    for i, ok, r, _ in fork_map(one, CASES, jobs=args.jobs):
        if not ok:
            raise RuntimeError(f"{CASES[i]}: {type(r).__name__}: {r}")
        print(f"{r['robot']} {r['motion']} {r['truth_ms']:g} ms: "
              f"{'-' if r['value_ms'] is None else format(r['value_ms'], '.2f')} ms [{r['seconds']:.0f} s]", flush=True)
        runs[i] = r
    done = [r for r in runs if r is not None]  # in CASES's order
    from diagnose_walks import write_results  # type: ignore[import-not-found]

    return write_results("time_offset", done, args.out, markdown(done))

if __name__ == "__main__":
    main()
