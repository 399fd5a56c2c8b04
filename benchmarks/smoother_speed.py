"""Speed of the smoothers: fixed-lag update times at 200 Hz with a 1 s lag, and batch over 60 s.

Usage::

    python benchmarks/smoother_speed.py [--long-seconds 300] [--batch-seconds 60] [--quick]

Prints JSON to stdout and writes ``benchmarks/results/smoother_speed.json``.

Recordings: the ``push-pitch`` scenario as simulated (8 s, the paper's second experiment), and a
long synthetic one -- the ``stand`` scenario's first sample (a static equilibrium, exact) repeated
for minutes with fresh IMU noise -- so that long fixed-lag runs (marginalisation over many
windows, gtsam issues 1638 and 1976) cost no simulation time.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np

from flexforce.datasets.scenario import Scenario
from flexforce.datasets.simulator import Simulator
from flexforce.factors.model import ModelConfig
from flexforce.smoother import run_batch, run_fixed_lag


def static_recording(seconds: float, seed: int = 0):
    """The ``stand`` equilibrium repeated for ``seconds`` at 200 Hz, with white IMU noise."""
    sc = Scenario.load("stand")
    sc.duration = 0.05
    base = Simulator(sc, noise=False).run().slice(0, 1)
    n = int(round(seconds * 200)) + 1
    fields: dict[str, Any] = {}
    for f in dataclasses.fields(base):
        value = getattr(base, f.name)
        if isinstance(value, np.ndarray) and value.ndim >= 1 and value.shape[0] == 1 and f.name != "t_ns":
            fields[f.name] = np.repeat(value, n, axis=0)
    rec = dataclasses.replace(base, t_ns=np.arange(n, dtype=np.int64) * 5_000_000, truth=None, **fields)
    model = ModelConfig.from_recording(rec)
    rng = np.random.default_rng(seed)
    rec.gyro = rec.gyro + rng.normal(0.0, model.gyro_sigma, rec.gyro.shape)
    rec.accel = rec.accel + rng.normal(0.0, model.accel_sigma, rec.accel.shape)
    return rec.validate()


def update_stats(seconds_per_update: np.ndarray) -> dict:
    ms = 1e3 * np.asarray(seconds_per_update)
    return {"updates": int(ms.size), "median_ms": float(np.median(ms)), "p99_ms": float(np.percentile(ms, 99)),
            "max_ms": float(ms.max()), "mean_ms": float(ms.mean())}


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--long-seconds", type=float, default=300.0, help="synthetic fixed-lag run, s")
    parser.add_argument("--batch-seconds", type=float, default=60.0, help="synthetic batch run, s")
    parser.add_argument("--quick", action="store_true", help="short runs (smoke test)")
    parser.add_argument("--output", type=Path, default=Path(__file__).parent / "results" / "smoother_speed.json")
    args = parser.parse_args(argv)
    if args.quick:
        args.long_seconds, args.batch_seconds = 5.0, 5.0

    out: dict[str, Any] = {
        "machine": {"python": platform.python_version(), "cpus": os.cpu_count(), "platform": platform.platform()},
        "targets": {"fixed_lag_median_ms": 1.0, "fixed_lag_p99_ms": 5.0, "batch_60s_s": 20.0}}
    # warm-up: compile the kernels (numba caches them on disk)
    warm = static_recording(0.5)
    run_batch(warm, ModelConfig.from_recording(warm))
    run_fixed_lag(warm, ModelConfig.from_recording(warm), lag=0.1)

    sc = Scenario.load("push-pitch")
    if args.quick:
        sc.duration = 2.0
    t0 = time.perf_counter()
    rec = Simulator(sc).run()
    out["push_pitch"] = {"seconds": rec.n * rec.dt, "simulation_s": time.perf_counter() - t0}
    model = ModelConfig.from_recording(rec)
    t0 = time.perf_counter()
    run_batch(rec, model)
    out["push_pitch"]["batch_s"] = time.perf_counter() - t0
    est = run_fixed_lag(rec, model, lag=1.0)
    out["push_pitch"]["fixed_lag"] = update_stats(est.time_per_step)
    out["push_pitch"]["fixed_lag"]["covariance_extraction_mean_ms_per_update"] = 1e3 * est.meta["cov_time_median_s"]
    try:  # the reference backend, for comparison (updates only)
        est = run_fixed_lag(rec, model, lag=1.0, backend="gtsam", covariance=False)
        out["push_pitch"]["fixed_lag_gtsam_backend"] = update_stats(est.time_per_step[1:])
    except Exception as err:  # noqa: BLE001 - reported, not fatal to the benchmark
        out["push_pitch"]["fixed_lag_gtsam_backend"] = {"error": str(err).strip().splitlines()[0]}

    long = static_recording(args.long_seconds, seed=1)
    t0 = time.perf_counter()
    # covariances off: the Estimate would hold N x 18 x 18 of them (the smoother's own memory is
    # its window's ring buffers either way)
    est = run_fixed_lag(long, ModelConfig.from_recording(long), lag=1.0, covariance=False)
    wall = time.perf_counter() - t0
    tps = est.time_per_step
    half = tps.size // 2
    out["fixed_lag_long"] = {"wall_s": wall}
    out["fixed_lag_long"] |= {"seconds": args.long_seconds, **update_stats(tps),
                             "first_half_median_ms": float(1e3 * np.median(tps[:half])),
                             "second_half_median_ms": float(1e3 * np.median(tps[half:])),
                             "finite": bool(np.all(np.isfinite(est.t))),
                             "max_abs_translation_m": float(np.max(np.abs(est.t))),
                             "last_minute_position_std_mm": float(1e3 * np.max(np.std(est.t[-12000:], axis=0)))}

    big = static_recording(args.batch_seconds, seed=2)
    t0 = time.perf_counter()
    est = run_batch(big, ModelConfig.from_recording(big))
    out["batch"] = {"seconds": args.batch_seconds, "steps": big.n, "wall_s": time.perf_counter() - t0,
                    "iterations": est.meta["iterations"]}
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(out, indent=2) + "\n")
    print(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    main()
