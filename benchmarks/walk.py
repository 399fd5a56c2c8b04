"""EKF, fixed-lag and batch smoothers on the simulated walk, with the world noisier than the model.

Usage::

    python benchmarks/walk.py [--robot romeo] [--scenario walk] [--estimators ekf fixed-lag batch]
                              [--imu-scale 2] [--ambient-scale 3] [--touchdown floor|relaxed|deflected] [--footholds]
                              [--out benchmarks/results/walk.json]

``benchmarks/results/walk_footholds.json`` is the same walk with ``--footholds``: the smoothers
estimate every contact episode's foothold (``footholds=True``) instead of holding the local one.
``benchmarks/results/walk_deflected.json`` is the same walk with ``--touchdown deflected``: the
world lands its feet as the estimators assume (a contact's rest at its local placement), which
separates what the noise costs from what the touch-down convention costs.

Prints JSON to stdout and writes it to ``--out``.

The world: the ``walk`` scenario (20 steps, 47 s, floor touch-down), its IMU twice as noisy as the
robot configuration says and its ambient disturbance three times the default level; the IMU's slow
bias drift is off (an effect for the diagnostics, not noise).  The estimators assume the robot
configuration, as they would on a real robot.

Per estimator, over the first and the last 10 s (after a 0.5 s start-up):
tilt (roll/pitch of the flexibility's rotation error) and force RMSE, their ratio last/first
(the target: at most 1.2, nothing grows with the length of the walk); the flexibility's
largest translation and tilt against the static deflection ``m g / sum k_fs`` (target: within 2x,
here for the estimate, and for the truth both its flexibility -- which also holds the world's
horizontal and yaw drift from the robot's belief, each foothold keeping where its foot touched --
and its springs' deflection); CoP (target: smoothers <= 5 mm) and hands (<= 2 mm)
RMSE; the mean NEES with its 95% band for a consistent estimator (reported, not forced: the model
is wrong on purpose).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin

from flexforce.compare.estimators import run_estimator
from flexforce.compare.metrics import chi2_mean_bounds, nees_series, state_error
from flexforce.datasets.sim.scenario import Scenario
from flexforce.datasets.sim.simulator import Simulator

RESULTS = Path(__file__).resolve().parent / "results"


def _rms(x: np.ndarray) -> float | None:
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x * x))) if x.size else None


def window_errors(est, rec, keep: np.ndarray) -> dict:
    """RMSE over the samples ``keep``: tilt (deg), total and per-contact force (N), CoP and hands (mm)."""
    tr = rec.truth
    e = state_error(est, tr)
    tilt = np.degrees(np.linalg.norm(e[:, :2], axis=1))
    force = np.linalg.norm(est.total_wrench[:, :3] - tr.total_wrench[:, :3], axis=1)
    fz = np.abs(est.total_wrench[:, 2] - tr.total_wrench[:, 2])
    cf = np.linalg.norm(est.wrench[..., :3] - tr.wrench[..., :3], axis=2)
    cf[~rec.contact_active] = np.nan
    cop = np.linalg.norm(est.cop[:, :2] - tr.cop[:, :2], axis=1)
    hands = []
    for p_w in tr.links.values():
        p_l = np.einsum("nji,nj->ni", tr.R, p_w - tr.t)
        hands.append(np.linalg.norm(np.einsum("nij,nj->ni", est.R, p_l) + est.t - p_w, axis=1))
    hand = np.max(hands, axis=0) if hands else np.full(rec.n, np.nan)
    return {
        "tilt_rmse_deg": _rms(tilt[keep]),
        "force_rmse_N": _rms(force[keep]),
        "vertical_force_rmse_N": _rms(fz[keep]),
        "contact_force_rmse_N": _rms(cf[keep].ravel()),
        "cop_rmse_mm": None if (cop_rms := _rms(cop[keep])) is None else 1e3 * cop_rms,
        "hand_rmse_mm": None if (hand_rms := _rms(hand[keep])) is None else 1e3 * hand_rms,
    }


def flexibility_extent(R: np.ndarray, t: np.ndarray, keep: np.ndarray) -> dict:
    tilt = np.degrees([np.linalg.norm(pin.log3(Rk)[:2]) for Rk in R[keep]])
    return {"max_translation_mm": 1e3 * float(np.linalg.norm(t[keep], axis=1).max()),
            "max_sinking_mm": -1e3 * float(t[keep, 2].min()), "max_tilt_deg": float(tilt.max())}


def spring_deflection(sim, rec) -> dict:
    """Largest deflection of the true springs (world contact placement minus its foothold), over
    the samples where each foot is where the robot planned it (m, rad).

    The truth's flexibility ``world_T_local`` also holds how far the world has drifted from the
    robot's belief in yaw and horizontal position (each foothold keeps where its foot actually
    touched), as leg odometry drifts; the springs' deflection is the physical part.
    """
    tr = rec.truth
    eps = rec.meta["contact_episodes"]
    worst_p, worst_r = 0.0, 0.0
    for k in range(0, rec.n, 5):
        t = rec.time[k]
        planned = sim.motion.contact_targets(t)[3]
        for i, name in enumerate(rec.contact_names):
            if not (rec.contact_active[k, i] and planned[i]):
                continue
            ep = next(e for e in eps if e["contact"] == name and e["start"] <= t + 1e-9
                      and (e["end"] is None or t < e["end"] - 1e-9))
            p_w = tr.R[k] @ rec.contact_p[k, i] + tr.t[k]
            R_w = tr.R[k] @ rec.contact_R[k, i]
            worst_p = max(worst_p, float(np.linalg.norm(p_w - np.array(ep["world_p"]))))
            worst_r = max(worst_r, float(np.linalg.norm(pin.log3(R_w @ np.array(ep["world_R"]).T))))
    return {"max_translation_mm": 1e3 * worst_p, "max_rotation_deg": float(np.degrees(worst_r))}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robot", default="romeo")
    ap.add_argument("--scenario", default="walk")
    ap.add_argument("--estimators", nargs="+", default=["ekf", "fixed-lag", "batch"])
    ap.add_argument("--imu-scale", type=float, default=2.0)
    ap.add_argument("--footholds", action="store_true",
                    help="the smoothers estimate the footholds (footholds=True; the EKF unchanged)")
    ap.add_argument("--ambient-scale", type=float, default=3.0)
    ap.add_argument("--touchdown", default=None, help="the world's touch-down convention (default: the scenario's, "
                                                       "floor); 'deflected' is the estimators' own")
    ap.add_argument("--window", type=float, default=10.0, help="s, length of the first and last windows")
    ap.add_argument("--out", type=Path, default=RESULTS / "walk.json")
    args = ap.parse_args(argv)

    sc = Scenario.load(args.scenario)
    sc.imu_noise = {"gyro_bias_rw": 0.0, "accel_bias_rw": 0.0, "scale": args.imu_scale}
    sc.ambient = {"scale": args.ambient_scale}
    if args.touchdown:
        sc.touchdown = args.touchdown
    t0 = time.perf_counter()
    sim = Simulator(sc, args.robot)
    rec = sim.run()
    sim_time = time.perf_counter() - t0
    tr = rec.truth
    assert tr is not None  # simulated
    mg = rec.mass * rec.gravity
    k_total = 2.0 * float(np.trace(sim.springs[0].K_fs)) / 3.0
    static = mg / k_total
    time_s = rec.time
    first = (time_s >= 0.5) & (time_s < 0.5 + args.window)
    last = time_s >= time_s[-1] - args.window
    allk = time_s >= 0.5
    active = rec.contact_active
    out: dict = {
        "benchmark": "walk",
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count()},
        "recording": {
            "robot": rec.robot, "scenario": sc.name, "duration_s": float(time_s[-1]), "samples": rec.n,
            "touch_downs": int(np.sum(active[1:] & ~active[:-1])),
            "single_support_s": float(np.sum(active.sum(axis=1) == 1) * rec.dt),
            "imu_noise_scale": args.imu_scale, "ambient_scale": args.ambient_scale,
            "touchdown": sc.touchdown, "simulation_s": sim_time, "smoothers_footholds": bool(args.footholds),
            "static_deflection_mm": 1e3 * static,
            "truth_flexibility": flexibility_extent(tr.R, tr.t, allk),
            "truth_spring_deflection": spring_deflection(sim, rec),
            "truth_drift_final_mm": (1e3 * tr.t[-1, :2]).tolist(),
        },
        "windows_s": {"first": [0.5, 0.5 + args.window], "last": [float(time_s[-1] - args.window), float(time_s[-1])]},
        "estimators": {},
    }
    for name in args.estimators:
        t0 = time.perf_counter()
        options: dict[str, Any] = {"footholds": True} if args.footholds and name != "ekf" else {}
        est = run_estimator(name, rec, **options)
        run_time = time.perf_counter() - t0
        f, l_ = window_errors(est, rec, first), window_errors(est, rec, last)
        flex = flexibility_extent(est.R, est.t, allk)
        ns = nees_series(est, tr)
        row = {"first": f, "last": l_, "all": window_errors(est, rec, allk), "run_s": run_time,
               "growth_last_over_first": {k: (l_[k] / f[k] if f[k] and l_[k] is not None else None)
                                          for k in ("tilt_rmse_deg", "force_rmse_N", "contact_force_rmse_N")},
               "flexibility": flex,
               "flexibility_over_static": flex["max_translation_mm"] / (1e3 * static)}
        if ns is not None:
            ok = allk & np.isfinite(ns)
            row["nees_mean"] = float(np.mean(ns[ok]))
            row["nees_band_95"] = list(chi2_mean_bounds(18, int(ok.sum())))
            row["nees_mean_first"] = float(np.nanmean(ns[first]))
            row["nees_mean_last"] = float(np.nanmean(ns[last]))
        smoother = name != "ekf"
        row["targets"] = {
            "tilt_growth_le_1.2": (row["growth_last_over_first"]["tilt_rmse_deg"] or np.inf) <= 1.2,
            "force_growth_le_1.2": (row["growth_last_over_first"]["force_rmse_N"] or np.inf) <= 1.2,
            "flexibility_le_2x_static": row["flexibility_over_static"] <= 2.0,
            "cop_le_5mm": (row["all"]["cop_rmse_mm"] or np.inf) <= 5.0 if smoother else None,
            "hands_le_2mm": (row["all"]["hand_rmse_mm"] or np.inf) <= 2.0 if smoother else None,
        }
        out["estimators"][name] = row
        print(json.dumps({name: row}, default=float), flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2, default=float) + "\n")
    return out


if __name__ == "__main__":
    main()
