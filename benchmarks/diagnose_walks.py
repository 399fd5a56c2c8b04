"""The diagnostics on simulated walks: hidden effects where every step lands a foot.

Usage::

    python benchmarks/diagnose_walks.py [--robots talos] [--only time-offset ...] [--jobs 2]

Writes ``benchmarks/results/diagnose_walks.json`` (every recording: the selection, the rounds'
scores and tests, the errors against the truth before and after adding the selection) and
``diagnose_walks.md`` (the table).

Each recording is the ``walk-short`` scenario (four steps in 9.5 s, arms swinging) on the given
robots, noise seed 3, the IMU bias random walk off, with one hidden effect or none, diagnosed as
``flexforce diagnose REC --add auto`` does (the default catalogue, which names the footholds on a
recording with touch-downs; at most three effects).  The simulated feet land where the floor stops
them while the recording keeps where the leg kinematics put them, so the footholds are expected in
every selection (``docs/diagnostics.md``, ``foothold``); the benchmark asks whether the hidden
effect is selected beside them, which other effects are, and what adding the selection does to
the errors against the truth.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from diagnose_confusion import KEYS  # type: ignore[import-not-found]  # noqa: E402

CASES = {
    "none": None,
    "time-offset": {"type": "time-offset", "delay": 0.015},
    "com-offset": {"type": "com-offset", "offset": [0.015, 0.0, 0.0]},
    "gyro-bias": {"type": "gyro-bias", "value": [0.0, 0.008, 0.0]},
}
"""The hidden effect of each recording (None: a clean one)."""
EXPECTED = {"foothold"}
"""Selected on every simulated walk (the landings), not counted as wrong."""


def one(robot: str, truth: str, jobs: int) -> dict:
    from flexforce.compare.diagnostics import diagnose
    from flexforce.datasets.sim.scenario import Scenario
    from flexforce.datasets.sim.simulator import Simulator
    from flexforce.factors.model import ModelConfig

    sc = Scenario.load("walk-short")
    sc.robot = robot
    sc.seed = 3
    sc.imu_noise = {"gyro_bias_rw": 0.0, "accel_bias_rw": 0.0}
    spec = CASES[truth]
    sc.effects = [spec] if spec else []
    rec = Simulator(sc).run()
    t0 = time.perf_counter()
    d = diagnose(rec, ModelConfig.from_recording(rec), add=["auto"], ekf=False, jobs=jobs)
    seconds = time.perf_counter() - t0
    ident = d.identifiability
    partners = set()
    if ident is not None and spec:
        partners = {b if a == truth else a for a, b in ((p.a, p.b) for p in ident.inseparable()) if truth in (a, b)}
    allowed = EXPECTED | ({truth} if spec else set()) | partners
    return {"robot": robot, "truth": truth, "selected": list(d.selected),
            "found": bool(spec) and truth in d.selected,
            "partner_found": bool(spec) and truth not in d.selected and bool(partners & set(d.selected)),
            "wrong": [s for s in d.selected if s not in allowed],
            "rounds": [[{"effect": c.effect, "score": c.score, "significant": c.significant,
                         "implausible": bool(c.implausible),
                         "T": None if c.screen is None else float(c.screen.statistic),
                         "p": None if c.screen is None else float(c.screen.p_value)} for c in row]
                       for row in d.rounds],
            "before": {k: d.before.rmse[k] for k in KEYS},
            "after": {k: d.after.rmse[k] for k in KEYS} if d.after else None,
            "seconds": round(seconds, 1)}


def markdown(runs: list[dict]) -> str:
    hidden = [r for r in runs if r["truth"] != "none"]
    head = [f"- hidden effect selected: {sum(r['found'] for r in hidden)} of {len(hidden)}"
            f" ({sum(r['partner_found'] for r in hidden)} more by an inseparable partner)",
            f"- recordings with a wrong selection (not the truth, its partners or the footholds): "
            f"{sum(bool(r['wrong']) for r in runs)} of {len(runs)}", "",
            "| robot | hidden | selected | wrong | force / CoP / tilt after ÷ before | time |",
            "|---|---|---|---|---|---|"]
    for r in runs:
        ratio = "—"
        if r["after"]:
            ratio = " / ".join(f"{r['after'][k] / r['before'][k]:.2f}" if r["before"][k] else "—" for k in KEYS)
        head.append(f"| {r['robot']} | {r['truth']} | {', '.join(r['selected']) or 'none'} | "
                    f"{', '.join(r['wrong']) or '—'} | {ratio} | {r['seconds']:.0f} s |")
    return "\n".join(head) + "\n"


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--robots", default="talos", help="comma-separated robots (romeo, talos)")
    ap.add_argument("--only", nargs="*", help=f"hidden effects to run (of {', '.join(CASES)})")
    ap.add_argument("--jobs", type=int, default=2, help="the diagnosis's worker processes")
    ap.add_argument("--out", default=str(HERE / "results" / "diagnose_walks.json"))
    args = ap.parse_args(argv)
    unknown = [t for t in args.only or () if t not in CASES]
    if unknown:
        sys.exit(f"unknown hidden effect(s) {', '.join(unknown)}; expected some of {', '.join(CASES)}")
    runs = []
    for robot in [x.strip() for x in args.robots.split(",") if x.strip()]:
        for truth in CASES:
            if args.only and truth not in args.only:
                continue
            r = one(robot, truth, args.jobs)
            print(f"{robot} {truth}: {', '.join(r['selected']) or 'none'} [{r['seconds']:.0f} s]", flush=True)
            runs.append(r)
    return write_results("diagnose_walks", runs, args.out, markdown(runs))


def write_results(name: str, runs: list[dict], out: str, table: str) -> dict:
    """``out`` (the JSON: the runs and the Python version) and the ``.md`` beside it (``table``);
    the table printed; the JSON's content returned."""
    result = {"benchmark": name, "runs": runs, "machine": {"python": platform.python_version()}}
    Path(out).write_text(json.dumps(result, indent=1) + "\n")
    Path(out).with_suffix(".md").write_text(table)
    print(table)
    return result


if __name__ == "__main__":
    main()
