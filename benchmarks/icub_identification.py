"""iCub: identify the contact stiffness with the F/T normal forces, test IMU-only on the other log.

Usage::

    python benchmarks/icub_identification.py [--data ../shared/data/icub] [--no-reverse]
                                             [--no-write-config] [--max-iterations 60]

Prints JSON to stdout and writes ``benchmarks/results/icub_identification.json``; writes the
identified configuration ``datasets/robots/icub-identified.toml`` (unless ``--no-write-config``).

1. Identification. The CoM-sway bag (double support throughout) is imported with the ``icub``
   configuration and the batch smoother is fitted with the ``stiffness`` effect (scales of
   ``K_fs``, ``K_ts`` and of ``K_fd``, ``K_td``, one pair for both feet) and ``use_ft=True``: the
   measured normal forces (force.z; iCub's other F/T fields are NaN) are measurements.  The
   scales, their std (from the smoother's marginal covariance: data noise only, optimistic when
   the residuals are correlated in time) and the absolute k_fs, k_ts, k_fd, k_td are reported.
2. F/T offset.  The sum of the two normal forces is compared with m g; the identification is
   repeated with the offset removed (half per foot), to show what it does to the scales.
3. Test.  The walking bag is imported and the EKF, the fixed-lag and the batch smoothers are run
   IMU-only (``use_ft=False``) with the nominal and with the identified stiffness; per-foot
   vertical force RMSE against F/T and base tilt RMSE against Vicon
   (:func:`flexforce.compare.metrics.evaluate`, the first 0.5 s left out as in ``flexforce
   compare``).
4. Reverse split (``--no-reverse`` skips it): identify on the walk, test on the sway.
5. Diagnostics (``--no-diagnostics`` skips them): the profile of the data cost over a grid of
   stiffness scales with F/T fused (batch smoother without effects, nominal damping: independent
   of how the smoother handles constant effects), per family; IMU-only results over the same
   grid (the tilt / force trade-off); where the walk's vertical force error comes from (double
   support, stance foot in single support, the foot the Schmitt trigger calls unloaded while its
   F/T carries up to 150 N); the angle between the accelerometer's vertical, Vicon's and leg
   odometry's, in the base frame.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import os
import platform
import re
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from scipy.signal import savgol_filter
from scipy.spatial.transform import Rotation

from flexforce.compare.estimators import run_estimator
from flexforce.compare.metrics import evaluate
from flexforce.datasets.io.rosimport import import_bag
from flexforce.datasets.robot import ROBOTS_DIR, RobotConfig
from flexforce.factors.effects import make_effect
from flexforce.factors.model import ModelConfig
from flexforce.smoother import fit

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
DEFAULT_DATA = (ROOT / ".." / "shared" / "data" / "icub").resolve()
SWAY = "icub-com-sinusoid-20s.bag"
WALK = "icub-walk-12s"
ESTIMATORS = ("ekf", "fixed-lag", "batch")
SKIP = 0.5  # s, as flexforce compare
IDENTIFIED = ROBOTS_DIR / "icub-identified.toml"


def _f(x):
    return None if x is None or not np.isfinite(x) else float(x)


def ft_offset(rec) -> dict:
    """Sum of the measured normal forces against the weight, over the double-support samples.

    The vertical CoM acceleration term m c_z'' is left out: its mean over a recording is ~0."""
    fz = rec.ft[:, :, 2]
    both = np.all(rec.contact_active, axis=1) & np.all(np.isfinite(fz), axis=1)
    total = fz[both].sum(axis=1)
    mg = float(rec.mass * rec.gravity)
    return {"samples": int(both.sum()), "weight_N": mg, "sum_mean_N": float(total.mean()),
            "sum_std_N": float(total.std()), "offset_N": float(total.mean() - mg),
            "offset_percent": float(100 * (total.mean() - mg) / mg),
            "per_foot_mean_N": np.nanmean(np.where(rec.contact_active, fz, np.nan), axis=0).tolist()}


def with_ft_offset_removed(rec, offset: float):
    """A copy of ``rec`` with ``offset / n_active`` taken off each active foot's force.z."""
    ft = rec.ft.copy()
    nact = np.maximum(rec.contact_active.sum(axis=1), 1)
    ft[:, :, 2] -= np.where(rec.contact_active, offset / nact[:, None], 0.0)
    return dataclasses.replace(rec, ft=ft)


def identify(rec, robot: RobotConfig, max_iterations: int) -> dict:
    model = ModelConfig.from_recording(rec, robot=robot, use_ft=True, effects=(make_effect("stiffness"),))
    t0 = time.perf_counter()
    est, stats = fit(rec, model, max_iterations=max_iterations)
    wall = time.perf_counter() - t0
    rep = est.effects["stiffness"]
    (s, d), (ss, sd) = rep["value"], rep["std"]
    k = robot.stiffness
    m = evaluate(est, rec, skip=SKIP)
    return {
        "stiffness_scale": s, "stiffness_scale_std": ss, "damping_scale": d, "damping_scale_std": sd,
        "summary": rep["summary"],
        "k_fs_N_per_m": s * k.k_fs, "k_ts_Nm_per_rad": s * k.k_ts,
        "k_fd_Ns_per_m": d * k.k_fd, "k_td_Nms_per_rad": d * k.k_td,
        "k_fs_std": ss * k.k_fs, "k_ts_std": ss * k.k_ts, "k_fd_std": sd * k.k_fd, "k_td_std": sd * k.k_td,
        "iterations": est.meta.get("iterations"), "max_iterations": max_iterations,
        "converged": bool(est.meta.get("iterations", max_iterations) < max_iterations),
        "effective_dof": stats.effective_dof.get("stiffness"),
        "wall_s": wall,
        "fit_with_ft_vertical_force_rmse_N": _f(m.rmse.get("vertical_force_N")),
        "fit_with_ft_tilt_rmse_deg": (_f(np.degrees(m.rmse["rotation_rad"]))  # type: ignore[arg-type]
                                      if m.rmse.get("rotation_rad") is not None else None),
    }


def test_imu_only(rec, robot: RobotConfig) -> dict:
    model = ModelConfig.from_recording(rec, robot=robot, use_ft=False)
    out: dict[str, Any] = {}
    for name in ESTIMATORS:
        t0 = time.perf_counter()
        try:
            est = run_estimator(name, rec, model)
        except Exception as err:  # reported, not hidden
            out[name] = {"failed": f"{type(err).__name__}: {err}"}
            continue
        wall = time.perf_counter() - t0
        m = evaluate(est, rec, skip=SKIP)
        rot = m.rmse.get("rotation_rad")
        # Per-foot vertical force RMSE, and the same with the mean error (the F/T offset) removed.
        local = _foot_fz(est, rec)
        keep = rec.time >= SKIP
        e = local[keep] - rec.ft[keep, :, 2]
        per_foot = np.sqrt(np.nanmean(e * e, axis=0))
        bias = np.nanmean(e, axis=0)
        out[name] = {
            "vertical_force_rmse_N": _f(m.rmse.get("vertical_force_N")),
            "vertical_force_max_N": _f(m.max.get("vertical_force_N")),
            "vertical_force_rmse_per_foot_N": dict(zip(rec.contact_names, map(float, per_foot))),
            "vertical_force_mean_error_per_foot_N": dict(zip(rec.contact_names, map(float, bias))),
            "vertical_force_rmse_bias_removed_N": float(np.sqrt(np.nanmean((e - bias) ** 2))),
            "tilt_rmse_deg": _f(np.degrees(rot)) if rot is not None else None,
            "tilt_max_deg": (_f(np.degrees(m.max["rotation_rad"]))  # type: ignore[arg-type]
                             if m.max.get("rotation_rad") is not None else None),
            "wall_s": wall,
        }
    return out


def _foot_fz(est, rec) -> np.ndarray:
    """(N, C) estimated normal force in each contact frame (0 when not in contact), like the F/T."""
    n, c = rec.n, len(rec.contact_names)
    out = np.zeros((n, c))
    for i in range(c):
        Rc = np.einsum("nij,njk->nik", est.R, rec.contact_R[:, i])
        F = est.wrench[:, i, :3]
        fz = np.einsum("nji,nj->ni", Rc, F)[:, 2]
        out[:, i] = np.where(rec.contact_active[:, i], fz, 0.0)
    return out


def leg_odometry_tilt(rec) -> float | None:
    """Tilt RMSE (deg) of the kinematic base orientation alone (no flexibility) against Vicon."""
    from flexforce.compare.metrics import base_tilt_error

    class _Ident:
        R = np.tile(np.eye(3), (rec.n, 1, 1))

    base = rec.meta.get("base_frame")
    if base not in rec.mocap or rec.base_pose is None:
        return None
    e = base_tilt_error(_Ident, rec, base)
    e = e[rec.time >= SKIP]
    return float(np.degrees(np.sqrt(np.nanmean(e * e))))


def scaled(robot: RobotConfig, s: float, d: float = 1.0) -> RobotConfig:
    """The robot with its (isotropic: scalar) stiffness scaled by ``s`` and damping by ``d``."""
    k: Any = robot.stiffness
    return dataclasses.replace(robot, stiffness=dataclasses.replace(
        k, k_fs=k.k_fs * s, k_ts=k.k_ts * s, k_fd=k.k_fd * d, k_td=k.k_td * d))


GRID = (0.5, 0.7, 1.0, 1.5, 2.0, 3.0, 5.0, 10.0)


def profile(rec, robot: RobotConfig, max_iterations: int) -> list[dict]:
    """Data cost (F/T fused) of the batch smoother with the stiffness scaled by s, per family."""
    rows = []
    for s in GRID:
        est, stats = fit(rec, ModelConfig.from_recording(rec, robot=scaled(robot, s), use_ft=True),
                         max_iterations=max_iterations)
        fams = {f: 0.5 * float(np.nansum(np.asarray(v) ** 2)) for f, v in est.residuals.items() if v is not None}
        rows.append({"stiffness_scale": s, "cost_data": stats.cost_data,
                     "n_residuals": stats.n_residuals, "iterations": est.meta.get("iterations"),
                     **{f"cost_{f}": v for f, v in fams.items()}})
    return rows


def force_error_by_phase(rec, robot: RobotConfig) -> dict:
    """Share of the squared per-foot vertical force error (batch, IMU-only) by contact phase."""
    est = run_estimator("batch", rec, ModelConfig.from_recording(rec, robot=robot, use_ft=False))
    keep = rec.time >= SKIP
    e = (_foot_fz(est, rec) - rec.ft[:, :, 2])[keep]
    act = rec.contact_active[keep]
    ds = np.broadcast_to(act.all(axis=1)[:, None], e.shape)
    ss = np.broadcast_to((act.sum(axis=1) == 1)[:, None], e.shape) & act
    total = float(np.nansum(e * e))
    out: dict[str, Any] = {}
    for label, mask in (("double_support", ds), ("single_support_stance_foot", ss), ("foot_off_by_trigger", ~act)):
        v = e[mask]
        v = v[np.isfinite(v)]
        out[label] = {"samples": int(v.size), "rmse_N": float(np.sqrt(np.mean(v * v))) if v.size else None,
                      "share_of_squared_error": float(np.sum(v * v) / total) if total else None}
    off = np.where(~rec.contact_active, rec.ft[:, :, 2], np.nan)
    out["max_ft_while_off_N"] = float(np.nanmax(off)) if np.isfinite(off).any() else None
    return out


def vertical_agreement(rec) -> dict:
    """Mean angle (deg) between the vertical of the accelerometer (0.5 s smoothing), of Vicon and
    of leg odometry, all in the base frame: a bias or a mounting error of the IMU tilts the
    accelerometer's vertical, and an IMU-only estimator follows it."""
    R_lb = Rotation.from_quat(rec.base_pose[:, 3:]).as_matrix()
    R_bi = np.einsum("nji,njk->nik", R_lb, rec.imu_R)
    acc = savgol_filter(rec.accel, 51, 1, axis=0)
    g_acc = np.einsum("nij,nj->ni", R_bi, acc)
    g_acc /= np.linalg.norm(g_acc, axis=1)[:, None]
    pose = rec.mocap[rec.meta["base_frame"]]
    ok = np.all(np.isfinite(pose), axis=1)
    g_vic = Rotation.from_quat(pose[ok, 3:]).as_matrix()[:, 2, :]
    g_kin = R_lb[ok][:, 2, :]
    g_acc = g_acc[ok]

    def ang(u, v):
        return float(np.degrees(np.mean(np.arccos(np.clip(np.sum(u * v, axis=1), -1, 1)))))

    return {"accelerometer_vs_vicon_deg": ang(g_acc, g_vic), "accelerometer_vs_leg_odometry_deg": ang(g_acc, g_kin),
            "vicon_vs_leg_odometry_deg": ang(g_vic, g_kin)}


def source_hash() -> str:
    """Hash of the smoother's sources (the constant-effect handling was changing while this ran)."""
    h = hashlib.sha256()
    for f in sorted((ROOT / "smoother").glob("*.py")) + [ROOT / "factors" / "effects.py"]:
        h.update(f.read_bytes())
    return h.hexdigest()[:12]


def write_identified(ident: dict, source: Path, command: str, offset: dict) -> Path:
    text = (ROBOTS_DIR / "icub.toml").read_text()
    s, d = ident["stiffness_scale"], ident["damping_scale"]
    header = (
        "# iCub with the contact stiffness identified on the real CoM-sway recording (shared/data/icub,\n"
        f"# {source.name}, double support throughout): batch smoother with the `stiffness` effect and\n"
        "# the F/T normal forces fused as measurements (use_ft), starting from icub.toml. Obtained with\n"
        f"#   {command}\n"
        f"# scales: stiffness {s:.4f} +- {ident['stiffness_scale_std']:.4f}, damping {d:.4f} +- "
        f"{ident['damping_scale_std']:.4f} (std: data noise only)\n"
        f"# F/T sum of normal forces - m g on this log: {offset['offset_N']:+.1f} N "
        f"({offset['offset_percent']:+.1f} %), fused as is.\n"
        "# Results: benchmarks/results/icub_identification.json. How far to trust it: docs/real-logs.md\n"
        "# (the minimum of the F/T-fused cost is set by the IMU and Newton-Euler residuals, the F/T\n"
        "# term alone is lowest near the nominal 1x; the damping scale is weakly excited).\n#\n")
    text = re.sub(r'^name = "icub"', 'name = "icub-identified"', text, flags=re.M)
    block = (
        "[stiffness]\n"
        f"k_fs = {ident['k_fs_N_per_m']:.1f}   # N/m      (icub.toml 25000 x {s:.4f})\n"
        f"k_fd = {ident['k_fd_Ns_per_m']:.2f}   # N s/m    (icub.toml 300 x {d:.4f})\n"
        f"k_ts = {ident['k_ts_Nm_per_rad']:.2f}   # N m/rad  (icub.toml 300 x {s:.4f})\n"
        f"k_td = {ident['k_td_Nms_per_rad']:.3f}   # N m s/rad (icub.toml 5 x {d:.4f})\n")
    text, nsub = re.subn(r"^\[stiffness\]\n(?:k_\w+ = .*\n)+", block, text, flags=re.M)
    if nsub != 1:
        raise RuntimeError("icub.toml: [stiffness] block not found")
    IDENTIFIED.write_text(header + text)
    RobotConfig.load(IDENTIFIED)  # must load
    return IDENTIFIED


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--no-reverse", action="store_true", help="skip identify-on-walk / test-on-sway")
    ap.add_argument("--no-write-config", action="store_true")
    ap.add_argument("--no-diagnostics", action="store_true")
    ap.add_argument("--max-iterations", type=int, default=60)
    args = ap.parse_args(argv)
    command = "python benchmarks/icub_identification.py" + (f" --max-iterations {args.max_iterations}"
                                                             if args.max_iterations != 60 else "")
    nominal = RobotConfig.load("icub")
    result = {"machine": {"python": platform.python_version(), "cpus": os.cpu_count(), "platform": platform.platform()},
              "command": command, "skip_s": SKIP, "smoother_source_sha256": source_hash(),
              "nominal": {"k_fs": nominal.stiffness.k_fs, "k_fd": nominal.stiffness.k_fd,
                          "k_ts": nominal.stiffness.k_ts, "k_td": nominal.stiffness.k_td}}

    def log(msg):
        print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)

    recs = {}
    for key, fname in (("sway", SWAY), ("walk", WALK)):
        t0 = time.perf_counter()
        recs[key] = import_bag(args.data / fname, "icub")
        log(f"imported {fname} in {time.perf_counter() - t0:.1f} s")

    # 1-2. Identify on the sway, with and without the F/T offset.
    offsets = {k: ft_offset(r) for k, r in recs.items()}
    result["ft_offset"] = offsets
    log(f"F/T offsets: {json.dumps({k: round(v['offset_N'], 2) for k, v in offsets.items()})}")
    ident = identify(recs["sway"], nominal, args.max_iterations)
    log(f"sway identification: {ident['summary']} ({ident['iterations']} it, {ident['wall_s']:.0f} s)")
    ident_c = identify(with_ft_offset_removed(recs["sway"], offsets["sway"]["offset_N"]), nominal, args.max_iterations)
    log(f"sway identification, offset removed: {ident_c['summary']}")
    result["identify_on_sway"] = {"raw_ft": ident, "ft_offset_removed": ident_c}
    if not args.no_write_config:
        written = write_identified(ident, args.data / SWAY, command, offsets["sway"])
        result["identified_config"] = str(written.relative_to(ROOT))
    identified = RobotConfig.load(IDENTIFIED) if IDENTIFIED.exists() else dataclasses.replace(
        nominal, stiffness=dataclasses.replace(nominal.stiffness, k_fs=ident["k_fs_N_per_m"],
                                               k_ts=ident["k_ts_Nm_per_rad"], k_fd=ident["k_fd_Ns_per_m"],
                                               k_td=ident["k_td_Nms_per_rad"]))

    # 3. Test IMU-only on the walk.
    result["leg_odometry_tilt_rmse_deg"] = {k: leg_odometry_tilt(r) for k, r in recs.items()}
    test = {}
    for label, robot in (("nominal", nominal), ("identified_on_sway", identified)):
        test[label] = test_imu_only(recs["walk"], robot)
        log(f"walk, {label}: " + ", ".join(f"{e} Fz {v.get('vertical_force_rmse_N', float('nan')):.1f} N tilt "
                                           f"{v.get('tilt_rmse_deg', float('nan')):.2f} deg"
                                           for e, v in test[label].items()))
    result["test_on_walk"] = test

    # 4. Reverse split.
    if not args.no_reverse:
        ident_w = identify(recs["walk"], nominal, args.max_iterations)
        log(f"walk identification: {ident_w['summary']} ({ident_w['iterations']} it)")
        result["identify_on_walk"] = {"raw_ft": ident_w}
        walk_robot = dataclasses.replace(nominal, stiffness=dataclasses.replace(
            nominal.stiffness, k_fs=ident_w["k_fs_N_per_m"], k_ts=ident_w["k_ts_Nm_per_rad"],
            k_fd=ident_w["k_fd_Ns_per_m"], k_td=ident_w["k_td_Nms_per_rad"]))
        test = {}
        for label, robot in (("nominal", nominal), ("identified_on_walk", walk_robot)):
            test[label] = test_imu_only(recs["sway"], robot)
            log(f"sway, {label}: " + ", ".join(f"{e} Fz {v.get('vertical_force_rmse_N', float('nan')):.1f} N tilt "
                                               f"{v.get('tilt_rmse_deg', float('nan')):.2f} deg"
                                               for e, v in test[label].items()))
        result["test_on_sway"] = test

    # 5. Diagnostics.
    if not args.no_diagnostics:
        diag: dict[str, Any] = {"vertical_agreement": {k: vertical_agreement(r) for k, r in recs.items()},
                "walk_force_error_by_phase_batch_nominal": force_error_by_phase(recs["walk"], nominal)}
        diag["profile_sway_ft"] = profile(recs["sway"], nominal, args.max_iterations)
        log("sway profile: " + ", ".join(f"s={r['stiffness_scale']:g} {r['cost_data']:.0f}"
                                         for r in diag["profile_sway_ft"]))
        sweep = {}
        for s in GRID[2:]:
            for key in ("sway", "walk"):
                res = test_imu_only(recs[key], scaled(nominal, s))
                sweep[f"{key}_x{s:g}"] = {e: {"vertical_force_rmse_N": v.get("vertical_force_rmse_N"),
                                              "tilt_rmse_deg": v.get("tilt_rmse_deg")} for e, v in res.items()}
            log(f"IMU-only sweep s={s:g} done")
        diag["imu_only_stiffness_sweep"] = sweep
        result["diagnostics"] = diag

    text = json.dumps(result, indent=2, allow_nan=False)
    print(text)
    out = HERE / "results" / "icub_identification.json"
    out.parent.mkdir(exist_ok=True)
    out.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
