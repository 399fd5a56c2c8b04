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
  damping (``K_fs``, ``K_fd`` z, contact frame) scaled by 3, and with every spring scaled by 2.

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


def run(path: Path) -> dict:
    rec = ff.load_recording(path, ROBOT)
    model = ff.ModelConfig.from_recording(rec, robot=ff.RobotConfig.load(ROBOT))
    n = rec.n
    out: dict[str, Any] = {"recording": path.name, "samples": n}
    phases = _phases(rec)
    root = rec.mocap["root_link"]
    vicon = root[:, 2] - _base_pose(rec)[:, 2]
    out["vicon_height_mm"] = {ph: round(float(np.nanmean(vicon[m]) * 1e3), 2) for ph, m in phases.items() if m.any()}
    rows = {"leg_odometry": row(rec, np.tile(np.eye(3), (n, 1, 1)), np.zeros((n, 3)))}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for name, fn in (("ekf", ff.run_ekf), ("fixed_lag", ff.run_fixed_lag), ("batch", ff.run_batch)):
            est = fn(rec, model)
            rows[name] = row(rec, est.R, est.t)
        out["rows"] = rows
        out["stiffness_scaled"] = {
            key: _foot_rmse(rec, ff.run_fixed_lag(rec, _scaled(model, **kw)))
            for key, kw in (("identified", {}), ("vertical_x3", {"vertical": 3.0}), ("every_x2", {"every": 2.0}))}
    return out


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
    for key, name in RECORDINGS.items():
        record[key] = run(args.data / name)
    text = json.dumps(record, indent=2)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(text + "\n", encoding="utf-8")
    print(text)


if __name__ == "__main__":
    main()
