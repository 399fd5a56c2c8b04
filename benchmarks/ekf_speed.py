"""Benchmark: microseconds per step of the EKF over a simulated recording (default 60 s).

    python benchmarks/ekf_speed.py [--scenario push-pitch] [--duration 60] [--reference-steps 1000]

Writes a JSON record to stdout and to ``benchmarks/results/ekf_speed.json``.  The per-step time is
the wall-clock time of one predict + update + outputs (covariances, wrenches, CoP), Python call
included, as stored in ``Estimate.time_per_step``; numba's compilation (or cache load) is done by
a warm-up run first and reported apart.  ``cold_compile_s`` is the time a fresh process takes to
import the kernel and run 10 steps with an empty numba cache (a temporary ``NUMBA_CACHE_DIR``, the
first run on a new machine); ``cached_load_s`` the same in a second process once that cache exists.
Target: <= 100 us per step (the authors' C++ filter runs
about 20 us per step on this kind of machine).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from flexforce.compare import _ekf_kernel
from flexforce.compare.ekf import run_ekf
from flexforce.datasets.scenario import Scenario
from flexforce.datasets.simulator import simulate
from flexforce.factors.model import ModelConfig

_COMPILE_PROBE = """
import time
t0 = time.perf_counter()
from flexforce.compare.ekf import run_ekf
from flexforce.datasets.scenario import Scenario
from flexforce.datasets.simulator import simulate
from flexforce.factors.model import ModelConfig
sc = Scenario.load('stand'); sc.duration = 0.05
rec = simulate(sc)
t1 = time.perf_counter()
from flexforce.compare import _ekf_kernel
run_ekf(rec, ModelConfig.from_recording(rec), fast=True)
print(time.perf_counter() - t1)
"""


def compile_times(repeat: int = 1) -> dict:
    """Kernel import + compile + 10 steps in a fresh process, with an empty then a filled cache (s)."""
    cold: list[float] = []
    warm: list[float] = []
    for _ in range(repeat):
        with tempfile.TemporaryDirectory() as cache:
            env = dict(os.environ, NUMBA_CACHE_DIR=cache)
            for out in (cold, warm):
                res = subprocess.run([sys.executable, "-c", _COMPILE_PROBE], env=env, capture_output=True, text=True,
                                     check=True)
                out.append(float(res.stdout.strip().splitlines()[-1]))
    return {"cold_compile_s": round(min(cold), 2), "cold_compile_s_runs": [round(c, 2) for c in cold],
            "cached_load_s": round(min(warm), 2)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="push-pitch")
    parser.add_argument("--duration", type=float, default=60.0, help="simulated seconds")
    parser.add_argument("--reference-steps", type=int, default=1000,
                        help="steps on which to time the numpy reference path (0 to skip)")
    parser.add_argument("--compile-repeat", type=int, default=2,
                        help="fresh-process cold compilations to time (0 to skip)")
    parser.add_argument("--output", type=Path, default=Path(__file__).resolve().parent / "results" / "ekf_speed.json")
    args = parser.parse_args()

    scenario = Scenario.load(args.scenario)
    scenario.duration = args.duration
    t0 = time.perf_counter()
    rec = simulate(scenario)
    sim_s = time.perf_counter() - t0
    model = ModelConfig.from_recording(rec)

    record = {"benchmark": "ekf_speed", "scenario": args.scenario, "duration_s": args.duration, "steps": rec.n,
              "rate_hz": 1.0 / rec.dt, "simulation_s": round(sim_s, 2), "numba": _ekf_kernel.AVAILABLE,
              "machine": {"python": platform.python_version(), "processor": platform.processor() or platform.machine(),
                          "numpy": np.__version__},
              "target_us_per_step": 100.0, "authors_cpp_us_per_step": 20.0}
    if _ekf_kernel.AVAILABLE:
        import numba

        record["machine"]["numba"] = numba.__version__
        if args.compile_repeat > 0:
            record.update(compile_times(args.compile_repeat))
        t0 = time.perf_counter()
        run_ekf(rec.slice(0, 10), model, fast=True)  # compile or load numba's cache
        record["warmup_compile_s"] = round(time.perf_counter() - t0, 2)
        est = run_ekf(rec, model, fast=True)
        assert est.time_per_step is not None
        tps = np.asarray(est.time_per_step) * 1e6
        record["fast"] = {"us_per_step_mean": round(float(tps.mean()), 2),
                          "us_per_step_median": round(float(np.median(tps)), 2),
                          "us_per_step_p99": round(float(np.percentile(tps, 99)), 2),
                          "us_per_step_wall": round(1e6 * est.total_time / rec.n, 2),
                          "total_s": round(est.total_time, 3)}
    if args.reference_steps > 0:
        est = run_ekf(rec.slice(0, min(args.reference_steps, rec.n)), model, fast=False)
        assert est.time_per_step is not None
        tps = np.asarray(est.time_per_step) * 1e6
        record["reference"] = {"steps": est.n, "us_per_step_mean": round(float(tps.mean()), 1),
                               "us_per_step_median": round(float(np.median(tps)), 1)}
    text = json.dumps(record, indent=2)
    print(text)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(text + "\n")


if __name__ == "__main__":
    main()
