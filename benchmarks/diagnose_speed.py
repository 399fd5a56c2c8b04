"""Speed and memory of a full diagnosis against the recording's length, and on the real iCub sway.

Usage::

    python benchmarks/diagnose_speed.py [--durations 20,60] [--icub] [--quick] [--jobs N]

Prints JSON to stdout and writes ``benchmarks/results/diagnose_speed.json``.

A full diagnosis is :func:`flexforce.compare.diagnostics.run.diagnose` with every registered candidate,
the screening, the identifiability table, the refits of the candidates that pass, the greedy
rounds and the add step (``add=["auto"]``), the EKF and the calibrated residual view of the
nominal and final fits: what ``flexforce diagnose REC --add auto`` does.  Each case runs in a fresh
child process (peak RSS from ``ru_maxrss``); the time of each stage comes from the diagnosis's own
progress messages.

Simulated cases: the ``sway`` scenario (Romeo standing on both feet, the CoM swaying) at 200 Hz
with a hidden gyroscope bias of (0, 0.01, 0) rad/s, ``--durations`` seconds long.  Real case
(``--icub``): the iCub CoM-sinusoid bag (20 s, beside the checkout) with the identified iCub
configuration.  ``--jobs N``: the diagnosis's own worker processes (``diagnose(jobs=N)``, what
``flexforce diagnose --jobs N`` does on one recording); the peak RSS of the largest worker is
reported beside the parent's.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ICUB_SWAY = HERE.parents[1] / "shared" / "data" / "icub" / "icub-com-sinusoid-20s.bag"


def _child(case: str, duration: float, jobs: int = 1) -> dict:
    """One diagnosis (runs in the child process)."""
    import resource

    from flexforce.compare.diagnostics import diagnose

    t_load = time.perf_counter()
    if case == "icub":
        from flexforce.datasets.io.rosimport import import_bag

        rec = import_bag(ICUB_SWAY, "icub-identified")
    else:
        from flexforce.datasets.sim.scenario import Scenario
        from flexforce.datasets.sim.simulator import Simulator

        sc = Scenario.load("sway")
        sc.duration = duration
        sc.seed = 0
        sc.effects = [{"type": "gyro-bias", "value": [0.0, 0.01, 0.0]}]
        rec = Simulator(sc).run()
    load_s = time.perf_counter() - t_load
    stages: list[dict] = []
    t0 = time.perf_counter()

    def progress(label, fraction, message=None):
        if message:
            stages.append({"at_s": round(time.perf_counter() - t0, 2), "stage": label, "message": message})

    d = diagnose(rec, add=["auto"], progress=progress, jobs=jobs)
    wall = time.perf_counter() - t0
    return {"case": case, "duration_s": float(rec.t_ns[-1] - rec.t_ns[0]) * 1e-9, "steps": int(rec.n),
            "load_s": round(load_s, 2), "diagnosis_s": round(wall, 2), "jobs": jobs,
            "selected": list(d.selected),
            "refitted": sum(1 for row in d.rounds for c in row),
            "screened": len(d.screening),
            "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1),
            "peak_rss_largest_worker_mb": round(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0, 1)
            if jobs > 1 else None,
            "stages": stages}


def run_case(case: str, duration: float, jobs: int = 1) -> dict:
    code = (f"import json, sys; sys.path.insert(0, {str(HERE)!r}); import diagnose_speed as b; "
            f"print('RESULT ' + json.dumps(b._child({case!r}, {duration!r}, {jobs!r})))")
    t0 = time.perf_counter()
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    line = next((x for x in out.stdout.splitlines() if x.startswith("RESULT ")), None)
    if line is None:
        return {"case": case, "duration_s": duration, "error": (out.stderr or out.stdout).strip().splitlines()[-1:]}
    res = json.loads(line[len("RESULT "):])
    res["process_s"] = round(time.perf_counter() - t0, 2)
    return res


TARGETS = (("60 s at 200 Hz, every candidate", "sway-gyro-bias", 60.0, 120.0),
           ("iCub 20 s sway, every candidate", "icub", 20.0, 60.0))
"""The issue's targets: (label, case, its duration in s, the diagnosis's time at most in s)."""


def machine_reference(repeats: int = 3) -> dict:
    """What the machine is, and how fast it runs a fixed workload (best of
    ``repeats``): dense Cholesky factorisations and solves (the smoother's kind of linear algebra)
    and a pure-Python loop.  Runs of this benchmark on different machines, or on one machine on
    different days, compare through it: the same code on the same recording took 79.4 s on one
    machine of this kind and 32 s on another."""
    import numpy as np

    rng = np.random.default_rng(0)
    a = rng.standard_normal((300, 300))
    spd = a @ a.T + 300.0 * np.eye(300)
    rhs = rng.standard_normal((300, 8))

    def linalg() -> None:
        for _ in range(60):
            np.linalg.solve(np.linalg.cholesky(spd), rhs)

    def python_loop() -> None:
        total = 0.0
        for i in range(1_000_000):
            total += i * 0.5
        if total < 0:
            raise AssertionError

    out: dict = {}
    for name, work in (("linalg_s", linalg), ("python_s", python_loop)):
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            work()
            times.append(time.perf_counter() - t0)
        out[name] = round(min(times), 4)
    model = ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"cpu": model or platform.processor() or platform.machine(), **out}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--durations", default="20,60", help="simulated lengths, s (comma-separated; '' for none)")
    ap.add_argument("--icub", action="store_true", help="also the real iCub CoM sway (20 s)")
    ap.add_argument("--quick", action="store_true", help="one 10 s recording")
    ap.add_argument("--jobs", type=int, default=1, help="the diagnosis's worker processes (default 1)")
    ap.add_argument("--out", default=str(HERE / "results" / "diagnose_speed.json"))
    args = ap.parse_args(argv)
    durations = [10.0] if args.quick else [float(x) for x in args.durations.split(",") if x.strip()]
    cases = [run_case("sway-gyro-bias", d, args.jobs) for d in durations]
    if args.icub:
        cases.append(run_case("icub", 20.0, args.jobs))
    reference = machine_reference()
    for c in cases:
        target = next((t for t in TARGETS if t[1] == c.get("case") and "diagnosis_s" in c
                       and abs(c.get("duration_s", 0.0) - t[2]) < 1.0), None)
        if target is not None:
            c["target_s"] = target[3]
            c["within_target"] = c["diagnosis_s"] <= target[3]
    result = {"benchmark": "diagnose_speed", "cases": cases,
              "targets": {label: f"<= {limit:g} s" for label, _, _, limit in TARGETS},
              "load_average_at_end": list(os.getloadavg()),
              "machine": {"python": platform.python_version(), "cpus": os.cpu_count(), **reference}}
    text = json.dumps(result, indent=1)
    print(text)
    if not args.quick:
        Path(args.out).write_text(text + "\n")
    return result


if __name__ == "__main__":
    main()
