"""Benchmark: what the estimators' tilt and vertical errors on the real iCub recordings are made of.

    python benchmarks/real_error_sources.py [--data ../shared/data/icub] [--output OUT.json]

For the iCub walk and CoM sway (``icub-identified``, IMU only), and for leg odometry (the rigid
robot: no flexibility), the EKF, the fixed-lag and the batch smoother:

- ``tilt``: the angle between the estimated and Vicon's vertical, seen from the root link, split
  into its components about the root link's x and y axes (the cross product of the two verticals,
  mrad), from 0.5 s: their means (the constant part: Vicon's marker frame against the URDF's, an
  accelerometer bias, the model's static deflection) and standard deviations (the varying part),
  and the RMSE of the angle (summary.json's ``rotation_rad``);
- ``flexibility_mean_mrad``: the mean of the estimated flexibility's rotation vector (x, y, z);
- ``height_mm``: the root link's height above its kinematic (leg-odometry) height, per phase:
  Vicon's and each estimate's (the flexibility applied to the kinematic base), mean over the
  standing phase (before the first lift-off), walking single support and walking double support.
  Vicon's difference between single and double support is the real robot's sink change on a
  weight transfer; the model's is ``m g / k_fs`` and half of it.
- ``stiffness_scaled``: the fixed-lag smoother's per-foot F_z RMSE against the F/T (the contacts
  in force, from 0.5 s) with the identified springs as they are, with the vertical stiffness and
  damping (``K_fs``, ``K_fd`` z, contact frame) scaled by 3, and with every spring scaled by 2;
- ``force_budget``: per estimator, where the per-foot F_z error against the F/T lies (every foot,
  from 0.5 s): feet the Schmitt trigger calls released while their F/T still carries more than
  20 N, released feet below that, feet in force within 50 ms of a contact switch, and feet in force
  away from switches in double and in single support; per part the samples, its share of the
  summed squared error, its RMS and its mean (estimate minus F/T), N;
- ``split``: the double-support split (both feet in force, 50 ms away from switches, from 0.5 s).
  ``normal_share``: the least-squares line of the right foot's share of the summed normal force
  against the lever rule's share (the CoM's projection on the line joining the soles; slope 1
  for point feet, below 1 when the soles' torques carry part of the roll moment), for the F/T and
  each estimate; ``model_normal_share``: the springs' share ``k_fs d^2 / 2 / (k_fs d^2 / 2 + 2
  k_ts)`` at the mean sole distance ``d``; ``standing_bias_N``: per foot, the mean estimate minus
  F/T while standing; ``accel_tilt_sensitivity_N_per_mrad``: how much the fixed-lag smoother's
  standing left-foot bias moves per mrad when the accelerometer readings are rotated by +-6 mrad
  about the IMU's x and y axes; ``closure``: the left sole against the right at the first sample
  by the leg kinematics (height mm, roll and pitch mrad);
- ``ft_sum_minus_weight_N``: the F/T normal forces' sum minus m g, mean per phase;
- ``touch_down``: per estimator, around every touch-down (a contact coming into force): the mean
  of the summed normal force minus the F/T sum over the TOUCH_DOWN_S before it and after it
  (``total_before_N``, ``total_after_N``; most negative and most positive per touch-down, averaged:
  ``dip_N``, ``peak_N``), and the root link's mean rise by the flexibility (as ``height_mm``) from
  TOUCH_DOWN_S before to TOUCH_DOWN_S after (``rise_mm``); Vicon's root-link rise against the
  kinematic base over the same spans (``vicon_rise_mm``);
- ``com_offset``: the batch smoother fitted with an accelerometer bias and a CoM offset (x, y,
  local frame; :class:`flexforce.factors.effects.newton_euler.ComOffset`) on each recording
  (``fitted``: value and std, mm and m/s^2), and each estimator's per-foot and total F_z RMSE and
  tilt RMSE with the recording's inputs moved by the CoM offset fitted on the *other* recording
  (``from_other``: identified on one log, tested on the other), beside the same without it
  (``nominal``).

Writes the JSON record to ``benchmarks/results/real_error_sources.json`` and prints it.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import warnings
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

import flexforce as ff
from flexforce.compare.band import moved_com

HERE = Path(__file__).resolve().parent
DATA = HERE.parents[1] / "shared" / "data" / "icub"
RECORDINGS = {"walk": "icub-walk-12s", "sway": "icub-com-sinusoid-20s.bag"}
ROBOT = "icub-identified"
SKIP_S = 0.5


def _phases(rec: ff.Recording) -> dict[str, np.ndarray]:
    """Step masks: standing (from SKIP_S until the first lift-off), walking single and double support."""
    t = (rec.t_ns - rec.t_ns[0]) * 1e-9
    n_on = rec.contact_active.sum(axis=1)
    lifted = np.flatnonzero(n_on < rec.contact_active.shape[1])
    first_lift = t[lifted[0]] if lifted.size else np.inf
    after = t >= SKIP_S
    walking = t >= first_lift
    return {"standing": after & ~walking, "walking_single_support": after & walking & (n_on == 1),
            "walking_double_support": after & walking & (n_on >= 2)}


def _base_pose(rec: ff.Recording) -> np.ndarray:
    if rec.base_pose is None or "root_link" not in rec.mocap:
        raise SystemExit(f"{rec.meta.get('source')}: no kinematic base pose or no Vicon root link to compare with")
    return rec.base_pose


def _round(x: Any, nd: int = 2) -> Any:
    return [round(float(v), nd) for v in np.atleast_1d(x)]


def row(rec: ff.Recording, R_flex: np.ndarray, t_flex: np.ndarray) -> dict:
    """The tilt decomposition and the heights of one estimate (``R_flex``, ``t_flex``: its flexibility)."""
    t = (rec.t_ns - rec.t_ns[0]) * 1e-9
    keep = t >= SKIP_S
    base = _base_pose(rec)
    root = rec.mocap["root_link"]
    R_local = Rotation.from_quat(base[:, 3:]).as_matrix()
    R_est = np.einsum("nij,njk->nik", R_flex, R_local)
    R_vicon = Rotation.from_quat(root[:, 3:]).as_matrix()
    g_est, g_vicon = R_est[:, 2, :], R_vicon[:, 2, :]  # world z in the root link's frame
    err = np.cross(g_vicon, g_est)[keep] * 1e3
    angle = np.arccos(np.clip(np.sum(g_est * g_vicon, axis=1), -1.0, 1.0))[keep] * 1e3
    rotvec = Rotation.from_matrix(R_flex[keep]).as_rotvec() * 1e3
    height = (np.einsum("nij,nj->ni", R_flex, base[:, :3]) + t_flex)[:, 2] - base[:, 2]
    return {"tilt": {"mean_x_y_mrad": _round(err.mean(axis=0)[:2]), "std_x_y_mrad": _round(err.std(axis=0)[:2]),
                     "rmse_mrad": round(float(np.sqrt(np.mean(angle**2))), 2)},
            "flexibility_mean_mrad": _round(rotvec.mean(axis=0)),
            "height_mm": {ph: round(float(np.mean(height[m]) * 1e3), 2) for ph, m in _phases(rec).items() if m.any()}}


def _scaled(model: ff.ModelConfig, vertical: float = 1.0, every: float = 1.0) -> ff.ModelConfig:
    """``model`` with each contact's vertical (contact-frame z) translational stiffness and damping
    scaled by ``vertical`` and every spring by ``every``."""
    S = np.diag([1.0, 1.0, vertical])
    cps = tuple(dataclasses.replace(cp, K_fs=every * S @ cp.K_fs, K_fd=S @ cp.K_fd, K_ts=every * cp.K_ts)
                for cp in model.contact_params)
    return dataclasses.replace(model, contact_params=cps)


def _foot_rmse(rec: ff.Recording, est: ff.Estimate) -> float:
    t = (rec.t_ns - rec.t_ns[0]) * 1e-9
    if rec.ft is None:
        raise SystemExit("the recording has no F/T to compare with")
    ft = rec.ft[:, :, 2]
    on = rec.contact_active & (t >= SKIP_S)[:, None] & np.isfinite(ft)
    return round(float(np.sqrt(np.mean((est.wrench[:, :, 2] - ft)[on] ** 2))), 2)


BUDGET_LOADED_N = 20.0
"""``force_budget``: a foot the trigger released that still carries more than this (F/T), N."""
SWITCH_S = 0.05
"""``force_budget``, ``split``: samples within this of a contact switch are the transitions, s."""
TILT_PROBE_MRAD = 6.0
"""``split``: the accelerometer rotation of the sensitivity probe, mrad."""


def _near_switch(rec: ff.Recording) -> np.ndarray:
    """(N,) bool: within SWITCH_S of a change of any contact's state."""
    t = (rec.t_ns - rec.t_ns[0]) * 1e-9
    changed = np.zeros(rec.n, dtype=bool)
    changed[1:] = (rec.contact_active[1:] != rec.contact_active[:-1]).any(axis=1)
    times = t[changed]
    if not times.size:
        return changed
    idx = np.clip(np.searchsorted(times, t), 1, times.size) - 1
    nearest = np.minimum(np.abs(t - times[idx]), np.abs(t - times[np.minimum(idx + 1, times.size - 1)]))
    return nearest <= SWITCH_S + 1e-9


def force_budget(rec: ff.Recording, est: ff.Estimate) -> dict:
    """Where one estimate's per-foot F_z error lies (module docstring, ``force_budget``)."""
    t = (rec.t_ns - rec.t_ns[0]) * 1e-9
    assert rec.ft is not None
    ft, act = rec.ft[:, :, 2], rec.contact_active
    err = est.wrench[:, :, 2] - ft
    keep = (t >= SKIP_S)[:, None] & np.isfinite(ft)
    near = _near_switch(rec)[:, None]
    n_on = act.sum(axis=1)[:, None]
    parts = {"released_loaded": ~act & (ft > BUDGET_LOADED_N), "released": ~act & (ft <= BUDGET_LOADED_N),
             "in_force_switch": act & near, "in_force_double_support": act & ~near & (n_on >= 2),
             "in_force_single_support": act & ~near & (n_on == 1)}
    total = float(np.sum(err[keep] ** 2))
    out = {}
    for name, mask in parts.items():
        e = err[mask & keep]
        out[name] = {"samples": int(e.size), "share": round(float(np.sum(e**2)) / total, 3) if total else None,
                     "rms_N": round(float(np.sqrt(np.mean(e**2))), 1) if e.size else None,
                     "mean_N": round(float(np.mean(e)), 1) if e.size else None}
    return out


def _share_line(rec: ff.Recording, fz: np.ndarray, mask: np.ndarray) -> list[float]:
    """``[slope, intercept]`` of the right foot's normal-force share against the lever rule's."""
    pl, pr = rec.contact_p[:, 0, :2], rec.contact_p[:, 1, :2]
    d = np.linalg.norm(pr - pl, axis=1)
    lever = np.einsum("ij,ij->i", rec.com[:, :2] - pl, (pr - pl) / d[:, None]) / d
    share = fz[:, 1] / fz.sum(axis=1)
    A = np.c_[lever[mask], np.ones(int(mask.sum()))]
    coef, *_ = np.linalg.lstsq(A, share[mask], rcond=None)
    return _round(coef, 3)


def split(rec: ff.Recording, model: ff.ModelConfig, estimates: dict[str, ff.Estimate]) -> dict:
    """The double-support split (module docstring, ``split``)."""
    t = (rec.t_ns - rec.t_ns[0]) * 1e-9
    assert rec.ft is not None
    ft = rec.ft[:, :, 2]
    ds = rec.contact_active.all(axis=1) & ~_near_switch(rec) & (t >= SKIP_S) & np.isfinite(ft).all(axis=1)
    standing = _phases(rec)["standing"]
    d = float(np.mean(np.linalg.norm(rec.contact_p[ds, 1, :2] - rec.contact_p[ds, 0, :2], axis=1)))
    k_fs = float(model.contact_params[0].K_fs[2, 2])
    k_ts = float(model.contact_params[0].K_ts[0, 0])
    vertical = k_fs * d**2 / 2
    out: dict[str, Any] = {"sole_distance_m": round(d, 3),
                           "model_normal_share": round(vertical / (vertical + 2 * k_ts), 3),
                           "normal_share": {"ft": _share_line(rec, ft, ds)}}
    for name, est in estimates.items():
        out["normal_share"][name] = _share_line(rec, est.wrench[:, :, 2], ds)
    if standing.any():
        out["standing_bias_N"] = {name: _round(np.mean(est.wrench[standing, :, 2] - ft[standing], axis=0), 1)
                                  for name, est in estimates.items()}
        sens = {}
        for axis in "xy":
            bias = []
            for sign in (-1.0, 1.0):
                R = Rotation.from_euler(axis, sign * TILT_PROBE_MRAD * 1e-3).as_matrix()
                est = ff.run_fixed_lag(dataclasses.replace(rec, accel=rec.accel @ R.T), model)
                bias.append(float(np.mean(est.wrench[standing, 0, 2] - ft[standing, 0])))
            sens[axis] = round((bias[1] - bias[0]) / (2 * TILT_PROBE_MRAD), 3)
        out["accel_tilt_sensitivity_N_per_mrad"] = sens
    rel = rec.contact_R[0, 1].T @ rec.contact_R[0, 0]
    out["closure"] = {"height_mm": round(float((rec.contact_p[0, 0, 2] - rec.contact_p[0, 1, 2]) * 1e3), 3),
                      "roll_pitch_mrad": _round(Rotation.from_matrix(rel).as_euler("xyz")[:2] * 1e3, 3)}
    return out


ESTIMATORS = (("ekf", ff.run_ekf), ("fixed_lag", ff.run_fixed_lag), ("batch", ff.run_batch))

TOUCH_DOWN_S = 0.1
"""``touch_down``: the span before and after a touch-down, s."""


def _touch_downs(rec: ff.Recording) -> np.ndarray:
    """Steps at which a contact comes into force (after SKIP_S, with TOUCH_DOWN_S on both sides)."""
    t = (rec.t_ns - rec.t_ns[0]) * 1e-9
    act = rec.contact_active
    on = np.flatnonzero((act[1:] & ~act[:-1]).any(axis=1)) + 1
    return on[(t[on] - TOUCH_DOWN_S >= SKIP_S) & (t[on] + TOUCH_DOWN_S <= t[-1])]


def touch_down(rec: ff.Recording, est: ff.Estimate) -> dict | None:
    """The total force and vertical motion around the touch-downs (module docstring)."""
    ks = _touch_downs(rec)
    if not ks.size:
        return None
    assert rec.ft is not None
    w = int(round(TOUCH_DOWN_S / float(np.median(np.diff(rec.t_ns)) * 1e-9)))
    err = est.wrench[:, :, 2].sum(axis=1) - np.nansum(rec.ft[:, :, 2], axis=1)
    before = [err[k - w:k] for k in ks]
    after = [err[k:k + w] for k in ks]
    base = _base_pose(rec)[:, :3]
    height = (np.einsum("nij,nj->ni", est.R, base) + est.t)[:, 2] - base[:, 2]  # the root link's, as in row()
    rise = [height[k + w] - height[k - w] for k in ks]
    return {"touch_downs": int(ks.size), "total_before_N": round(float(np.mean(np.concatenate(before))), 1),
            "total_after_N": round(float(np.mean(np.concatenate(after))), 1),
            "dip_N": round(float(np.mean([min(b.min(), a.min()) for b, a in zip(before, after)])), 1),
            "peak_N": round(float(np.mean([max(b.max(), a.max()) for b, a in zip(before, after)])), 1),
            "rise_mm": round(float(np.mean(rise)) * 1e3, 2)}


def _errors(rec: ff.Recording, est: ff.Estimate) -> dict:
    """Per-foot and total F_z RMSE against the F/T (contacts in force, from SKIP_S) and tilt RMSE, mrad."""
    t = (rec.t_ns - rec.t_ns[0]) * 1e-9
    keep = t >= SKIP_S
    assert rec.ft is not None
    total = est.wrench[keep, :, 2].sum(axis=1) - np.nansum(rec.ft[keep, :, 2], axis=1)
    tilt = row(rec, est.R, est.t)["tilt"]["rmse_mrad"]
    return {"foot_N": _foot_rmse(rec, est), "total_N": round(float(np.sqrt(np.mean(total**2))), 2), "tilt_mrad": tilt}


def fit_com_offset(rec: ff.Recording, model: ff.ModelConfig) -> dict:
    """The batch fit with ``accel-bias`` and ``com-offset``: their values and stds."""
    from flexforce.factors.effects import make_effect
    from flexforce.smoother import fit

    est, _ = fit(rec, dataclasses.replace(model, effects=(make_effect("accel-bias"), make_effect("com-offset"))))
    com, bias = est.effects["com-offset"], est.effects["accel-bias"]
    return {"com_offset_mm": _round(np.asarray(com["value"]) * 1e3, 1),
            "com_std_mm": _round(np.asarray(com["std"]) * 1e3, 1),
            "accel_bias": _round(bias["value"], 3), "accel_bias_std": _round(bias["std"], 3)}


def run(name: str, rec: ff.Recording, model: ff.ModelConfig) -> tuple[dict, dict[str, ff.Estimate]]:
    """The record of one recording (``name``: its file), and its estimates by estimator."""
    n = rec.n
    out: dict[str, Any] = {"recording": name, "samples": n}
    phases = _phases(rec)
    root = rec.mocap["root_link"]
    vicon = root[:, 2] - _base_pose(rec)[:, 2]
    out["vicon_height_mm"] = {ph: round(float(np.nanmean(vicon[m]) * 1e3), 2) for ph, m in phases.items() if m.any()}
    assert rec.ft is not None
    mg = rec.mass * rec.gravity
    out["ft_sum_minus_weight_N"] = {ph: round(float(np.nanmean(rec.ft[m, :, 2].sum(axis=1)) - mg), 1)
                                    for ph, m in phases.items() if m.any()}
    rows = {"leg_odometry": row(rec, np.tile(np.eye(3), (n, 1, 1)), np.zeros((n, 3)))}
    estimates: dict[str, ff.Estimate] = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for name, fn in ESTIMATORS:
            est = estimates[name] = fn(rec, model)
            rows[name] = row(rec, est.R, est.t)
        out["rows"] = rows
        out["force_budget"] = {name: force_budget(rec, est) for name, est in estimates.items()}
        out["split"] = split(rec, model, estimates)
        downs = {name: touch_down(rec, est) for name, est in estimates.items()}
        if any(downs.values()):
            ks = _touch_downs(rec)
            w = int(round(TOUCH_DOWN_S / float(np.median(np.diff(rec.t_ns)) * 1e-9)))
            vicon_rise = [vicon[k + w] - vicon[k - w] for k in ks]
            out["touch_down"] = {"vicon_rise_mm": round(float(np.nanmean(vicon_rise)) * 1e3, 2), **downs}
        out["stiffness_scaled"] = {
            key: _foot_rmse(rec, ff.run_fixed_lag(rec, _scaled(model, **kw)))
            for key, kw in (("identified", {}), ("vertical_x3", {"vertical": 3.0}), ("every_x2", {"every": 2.0}))}
    return out, estimates


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--output", type=Path, default=HERE / "results" / "real_error_sources.json")
    args = parser.parse_args()
    record: dict[str, Any] = {
        "benchmark": "real_error_sources", "command": "python benchmarks/real_error_sources.py", "robot": ROBOT,
        "reference": "Vicon root link (a reference, not ground truth)", "skip_s": SKIP_S,
        "machine": {"python": platform.python_version(), "processor": platform.machine() or platform.processor(),
                    "numpy": np.__version__}}
    recs = {key: ff.load_recording(args.data / name, ROBOT) for key, name in RECORDINGS.items()}
    models = {key: ff.ModelConfig.from_recording(r, robot=ff.RobotConfig.load(ROBOT)) for key, r in recs.items()}
    estimates = {}
    for key, name in RECORDINGS.items():
        record[key], estimates[key] = run(name, recs[key], models[key])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        fitted = {key: fit_com_offset(recs[key], models[key]) for key in recs}
        for key, rec in recs.items():
            other = next(k for k in recs if k != key)
            moved = moved_com(rec, models[key], np.asarray(fitted[other]["com_offset_mm"]) * 1e-3)
            record[key]["com_offset"] = {
                "fitted": fitted[key], "from": other,
                "nominal": {n: _errors(rec, est) for n, est in estimates[key].items()},
                "from_other": {n: _errors(moved, fn(moved, models[key])) for n, fn in ESTIMATORS}}
    text = json.dumps(record, indent=2)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(text + "\n", encoding="utf-8")
    print(text)


if __name__ == "__main__":
    main()
