"""Speed and agreement of the smoothers and of gtsam's solvers on the same recordings and factors.

Usage::

    OPENBLAS_NUM_THREADS=1 python benchmarks/smoother_speed.py [--quick] [--long-seconds 300]
        [--gtsam-long-seconds 60] [--gtsam-batch-long-seconds 10] [--lm-seconds 4]
        [--fixed-lag-compare-seconds 1.3] [--batch-seconds 60]

Prints JSON to stdout and writes ``benchmarks/results/smoother_speed.json``.  The default run
takes about 10 minutes on two busy cores; the options lengthen the runs.

What it measures:

- ``push_pitch``: the own batch and window fixed-lag smoothers (and gtsam's iSAM2 backend) on the
  ``push-pitch`` scenario as simulated (8 s, the paper's second experiment).
- ``batch_vs_gtsam_lm``: the own batch solver against gtsam's ``LevenbergMarquardtOptimizer`` on
  the graph of :class:`flexforce.smoother.graph.GraphBuilder` (the same factors and noise), on
  the first ``--lm-seconds`` of push-pitch: wall time, iterations, cost in the gtsam graph,
  accuracy against the truth and the largest difference between the two solutions; and gtsam's
  time per LM iteration against the number of steps (``lm_iteration_scaling``), with the same
  measurement on a chain of trivial CustomFactors (``custom_factor_chain_scaling``).
- ``fixed_lag_compare``: the window fixed-lag smoother, gtsam's IncrementalFixedLagSmoother
  (iSAM2) and gtsam's BatchFixedLagSmoother, 1 s lag, on the first ``--fixed-lag-compare-seconds``
  of push-pitch: time per update (median, p99), accuracy against the truth, and the largest
  difference to the window smoother's estimate.
- ``fixed_lag_long`` / ``gtsam_long``: long runs for stability (marginalisation over many
  windows; upstream gtsam fixed-lag issues 1638 and 1976 concern long runs) on a synthetic
  recording -- the ``stand`` scenario's first sample (a static equilibrium, exact) repeated with
  fresh IMU noise, so that long runs cost no simulation time: the window smoother over
  ``--long-seconds``, iSAM2 over ``--gtsam-long-seconds`` (1 s lag) and the BatchFixedLagSmoother
  over ``--gtsam-batch-long-seconds`` (``--gtsam-batch-long-lag``, shorter: its update costs grow
  with the square of the window, see ``lm_iteration_scaling``).  Each reports whether it finished,
  the update times in the first and second halves, and the drift from the static equilibrium.
- ``batch``: the own batch smoother over ``--batch-seconds`` of the synthetic recording.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.metadata
import json
import os
import platform
import time
from pathlib import Path
from typing import Any

import gtsam
import numpy as np

from flexforce.compare.metrics import evaluate
from flexforce.datasets.sim.scenario import Scenario
from flexforce.datasets.sim.simulator import Simulator
from flexforce.errors import EstimatorError
from flexforce.factors import core
from flexforce.factors.model import ModelConfig
from flexforce.smoother import run_batch, run_fixed_lag
from flexforce.smoother.batch import initial_trajectory
from flexforce.smoother.fixed_lag import GtsamFixedLagSmoother
from flexforce.smoother.graph import GraphBuilder
from flexforce.smoother.problem import Problem
from flexforce.smoother.result import make_estimate


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


def update_stats(seconds_per_update: np.ndarray | None) -> dict:
    if seconds_per_update is None:
        raise ValueError("the estimate has no per-update timings (time_per_step)")
    ms = 1e3 * np.asarray(seconds_per_update)
    return {"updates": int(ms.size), "median_ms": float(np.median(ms)), "p99_ms": float(np.percentile(ms, 99)),
            "max_ms": float(ms.max()), "mean_ms": float(ms.mean())}


def accuracy(est, rec) -> dict:
    """RMSE against the simulator's truth (rad -> mrad, m -> mm)."""
    r = evaluate(est, rec).rmse

    def scaled(key: str, factor: float = 1.0) -> float | None:
        value = r.get(key)
        return None if value is None else factor * value

    return {"rotation_mrad": scaled("rotation_rad", 1e3), "translation_mm": scaled("translation_m", 1e3),
            "force_N": scaled("force_N"), "contact_force_N": scaled("contact_force_N"), "cop_mm": scaled("cop_m", 1e3)}


def difference(a, b) -> dict:
    """Largest differences between two estimates of the same recording."""
    rot = max(float(np.linalg.norm(core.so3_log(np.ascontiguousarray(Ra @ Rb.T)))) for Ra, Rb in zip(a.R, b.R))
    return {"rotation_mrad": 1e3 * rot, "translation_mm": 1e3 * float(np.abs(a.t - b.t).max()),
            "contact_wrench_N": float(np.abs(a.wrench - b.wrench).max()),
            "contact_wrench_max_N": float(np.abs(b.wrench).max())}


def trajectory_values(builder: GraphBuilder, est) -> gtsam.Values:
    """gtsam Values of an Estimate (no effects) in the builder's keys."""
    from flexforce.smoother.linearize import Trajectory

    q = np.concatenate([est.t, est.w, est.v, est.dw, est.a], axis=1)
    return builder.values(Trajectory(est.R, q, est.wrench, np.zeros((est.n, 0))))


def run_gtsam_fixed_lag(rec, model, kind: str, lag: float) -> tuple[Any, float]:
    """gtsam's IncrementalFixedLagSmoother (``incremental``) or BatchFixedLagSmoother (``batch``)
    on the CustomFactors, one update per sample, no covariances; ``(Estimate, wall s)``."""
    prob = Problem.build(rec, model)
    t0 = time.perf_counter()
    fls = GtsamFixedLagSmoother(prob, lag, covariance=False, kind=kind)
    for _ in range(prob.n):
        fls.step()
    fls.finish()
    wall = time.perf_counter() - t0
    est = make_estimate(prob, "fixed_lag", fls.traj, None, time_per_step=fls.update_time,
                        meta={"backend": f"gtsam-{kind}"})
    est.total_time = wall
    return est, wall


def lm_params(max_iterations: int = 100) -> gtsam.LevenbergMarquardtParams:
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-7)  # the own batch solver's stopping rule
    params.setMaxIterations(max_iterations)
    return params


def batch_vs_gtsam_lm(rec, model, scaling_steps: list[int]) -> dict:
    """Own batch solver vs gtsam's LevenbergMarquardtOptimizer on the same graph."""
    out: dict[str, Any] = {"steps": rec.n, "seconds": rec.n * rec.dt}
    t0 = time.perf_counter()
    own = run_batch(rec, model, covariance=False)
    own_wall = time.perf_counter() - t0
    prob = Problem.build(rec, model)
    t0 = time.perf_counter()
    builder = GraphBuilder(prob)
    graph = builder.graph()
    initial = builder.values(initial_trajectory(prob))
    build = time.perf_counter() - t0
    t0 = time.perf_counter()
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, lm_params())
    result = optimizer.optimize()
    lm_wall = time.perf_counter() - t0
    theirs = make_estimate(prob, "gtsam_lm", builder.trajectory(result))
    own_cost = graph.error(trajectory_values(builder, own))
    out["factors"] = int(graph.size())
    out["own_batch"] = {"wall_s": own_wall, "iterations": own.meta["iterations"], "cost_in_gtsam_graph": own_cost,
                        "accuracy": accuracy(own, rec)}
    out["gtsam_lm"] = {"wall_s": lm_wall, "graph_build_s": build, "iterations": int(optimizer.iterations()),
                       "cost_in_gtsam_graph": float(graph.error(result)), "initial_cost": float(graph.error(initial)),
                       "accuracy": accuracy(theirs, rec)}
    out["speed_ratio_gtsam_over_own"] = lm_wall / own_wall
    out["agreement"] = difference(theirs, own)
    scaling = []
    for n in scaling_steps:
        p = Problem.build(rec.slice(0, n), model)
        b = GraphBuilder(p)
        g, v = b.graph(), b.values(initial_trajectory(p))
        direct, iteration = _linearize_and_iterate(g, v)
        scaling.append({"steps": n, "factors": int(g.size()), "linearize_from_python_s": direct,
                        "lm_iteration_s": iteration})
    out["lm_iteration_scaling"] = scaling
    out["custom_factor_chain_scaling"] = custom_factor_chain_scaling()
    return out


def custom_factor_chain_scaling(sizes=(500, 1000, 2000)) -> list[dict]:
    """One LM iteration on a chain of trivial 3-D CustomFactors (one per variable), against the
    graph's linearisation called from Python: isolates the binding's cost from our factors."""
    out = []
    noise = gtsam.noiseModel.Unit.Create(3)

    def error(this, values, H):
        x = values.atVector(this.keys()[0])
        if H is not None:
            H[0] = np.eye(3)
        return x - 1.0

    for n in sizes:
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        for k in range(n):
            values.insert(k, np.zeros(3))
            graph.add(gtsam.CustomFactor(noise, [k], error))
        direct, iteration = _linearize_and_iterate(graph, values)
        out.append({"factors": n, "linearize_from_python_s": direct, "lm_iteration_s": iteration})
    return out


def _linearize_and_iterate(graph, values) -> tuple[float, float]:
    """Seconds of ``graph.linearize(values)`` called from Python, and of one gtsam LM iteration."""
    t0 = time.perf_counter()
    graph.linearize(values)
    direct = time.perf_counter() - t0
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, lm_params(1))
    t0 = time.perf_counter()
    opt.iterate()
    return direct, time.perf_counter() - t0


def fixed_lag_compare(rec, model, lag: float = 1.0) -> dict:
    """Window fixed-lag vs gtsam's IncrementalFixedLagSmoother and BatchFixedLagSmoother."""
    out: dict[str, Any] = {"steps": rec.n, "seconds": rec.n * rec.dt, "lag_s": lag}
    full = int(round(lag / rec.dt)) + 1  # updates with a full window from this one on
    window = run_fixed_lag(rec, model, lag=lag, covariance=False)
    out["window"] = {**update_stats(window.time_per_step), "accuracy": accuracy(window, rec)}
    for name, kind in (("gtsam_incremental", "incremental"), ("gtsam_batch", "batch")):
        try:
            est, wall = run_gtsam_fixed_lag(rec, model, kind, lag)
        except EstimatorError as err:
            out[name] = {"error": str(err).strip().splitlines()[0]}
            continue
        out[name] = {**update_stats(est.time_per_step[1:]), "wall_s": wall,
                     "full_window_median_ms": float(1e3 * np.median(est.time_per_step[full:])),
                     "accuracy": accuracy(est, rec), "difference_to_window": difference(est, window)}
    return out


def long_run(rec, run, equilibrium_t) -> dict:
    """Stability of a long fixed-lag run: finished?, update times by half, drift from the equilibrium."""
    t0 = time.perf_counter()
    try:
        est = run(rec)
    except (EstimatorError, RuntimeError) as err:
        return {"seconds": rec.n * rec.dt, "finished": False, "error": str(err).strip().splitlines()[0],
                "wall_s": time.perf_counter() - t0}
    wall = time.perf_counter() - t0
    tps = est.time_per_step[1:]
    half = tps.size // 2
    last = min(12000, est.n // 5)
    return {"seconds": rec.n * rec.dt, "finished": True, "wall_s": wall, **update_stats(tps),
            "first_half_median_ms": float(1e3 * np.median(tps[:half])),
            "second_half_median_ms": float(1e3 * np.median(tps[half:])),
            "finite": bool(np.all(np.isfinite(est.t))),
            "max_drift_from_equilibrium_mm": float(1e3 * np.max(np.abs(est.t - equilibrium_t))),
            "last_fifth_position_std_mm": float(1e3 * np.max(np.std(est.t[-last:], axis=0)))}


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--long-seconds", type=float, default=300.0, help="window fixed-lag long run, s")
    parser.add_argument("--gtsam-long-seconds", type=float, default=60.0,
                        help="gtsam IncrementalFixedLagSmoother long run (1 s lag), s")
    parser.add_argument("--gtsam-batch-long-seconds", type=float, default=10.0,
                        help="gtsam BatchFixedLagSmoother long run, s")
    parser.add_argument("--gtsam-batch-long-lag", type=float, default=0.2,
                        help="lag of the BatchFixedLagSmoother long run, s")
    parser.add_argument("--lm-seconds", type=float, default=4.0,
                        help="push-pitch seconds for own batch vs gtsam Levenberg-Marquardt")
    parser.add_argument("--fixed-lag-compare-seconds", type=float, default=1.3,
                        help="push-pitch seconds for window vs gtsam fixed-lag smoothers (1 s lag)")
    parser.add_argument("--batch-seconds", type=float, default=60.0, help="synthetic batch run, s")
    parser.add_argument("--quick", action="store_true", help="short runs (smoke test)")
    parser.add_argument("--output", type=Path, default=Path(__file__).parent / "results" / "smoother_speed.json")
    args = parser.parse_args(argv)
    if args.quick:
        args.long_seconds, args.batch_seconds, args.gtsam_long_seconds = 5.0, 5.0, 3.0
        args.gtsam_batch_long_seconds, args.lm_seconds, args.fixed_lag_compare_seconds = 1.0, 0.5, 1.2
    started = time.perf_counter()

    out: dict[str, Any] = {
        "machine": {"python": platform.python_version(), "cpus": os.cpu_count(), "platform": platform.platform(),
                    "gtsam": importlib.metadata.version("gtsam")},
        "settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
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
        out["push_pitch"]["fixed_lag_gtsam_backend"] = update_stats(np.asarray(est.time_per_step)[1:])
    except Exception as err:  # noqa: BLE001 - reported, not fatal to the benchmark
        out["push_pitch"]["fixed_lag_gtsam_backend"] = {"error": str(err).strip().splitlines()[0]}

    n_lm = int(round(args.lm_seconds / rec.dt)) + 1
    scaling = sorted({max(20, n_lm // 4), max(40, n_lm // 2), n_lm})
    out["batch_vs_gtsam_lm"] = batch_vs_gtsam_lm(rec.slice(0, n_lm), model, scaling)
    out["batch_vs_gtsam_lm"]["recording"] = f"push-pitch, first {args.lm_seconds:g} s"
    n_fl = int(round(args.fixed_lag_compare_seconds / rec.dt)) + 1
    out["fixed_lag_compare"] = fixed_lag_compare(rec.slice(0, n_fl), model)
    out["fixed_lag_compare"]["recording"] = f"push-pitch, first {args.fixed_lag_compare_seconds:g} s"

    long = static_recording(args.long_seconds, seed=1)
    long_model = ModelConfig.from_recording(long)
    equilibrium_t = Problem.build(long.slice(0, 2), long_model).prior_mean[1][0:3]
    # covariances off: the Estimate would hold N x 18 x 18 of them (the smoother's own memory is
    # its window's ring buffers either way)
    out["fixed_lag_long"] = long_run(long, lambda r: run_fixed_lag(r, long_model, lag=1.0, covariance=False),
                                     equilibrium_t)
    n_g = int(round(args.gtsam_long_seconds * 200)) + 1
    n_b = int(round(args.gtsam_batch_long_seconds * 200)) + 1
    out["gtsam_long"] = {
        "incremental": {"lag_s": 1.0, **long_run(long.slice(0, n_g), lambda r: run_gtsam_fixed_lag(
            r, long_model, "incremental", 1.0)[0], equilibrium_t)},
        "batch": {"lag_s": args.gtsam_batch_long_lag, **long_run(long.slice(0, n_b), lambda r: run_gtsam_fixed_lag(
            r, long_model, "batch", args.gtsam_batch_long_lag)[0], equilibrium_t)}}

    big = static_recording(args.batch_seconds, seed=2)
    t0 = time.perf_counter()
    est = run_batch(big, ModelConfig.from_recording(big))
    out["batch"] = {"seconds": args.batch_seconds, "steps": big.n, "wall_s": time.perf_counter() - t0,
                    "iterations": est.meta["iterations"]}
    out["benchmark_wall_s"] = time.perf_counter() - started
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(out, indent=2) + "\n")
    print(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    main()
