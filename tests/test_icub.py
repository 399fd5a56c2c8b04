"""The real iCub recordings through ``flexforce compare``, IMU-only, with the identified stiffness.

The references are the robot's own sensors: the legs' F/T normal forces (not fused) and the
Vicon tilt of the root link.  The bounds hold the figures of the README's iCub table against
what a user would get without an estimator: the weight shared equally between the feet in
contact (forces) and leg odometry, i.e. a rigid robot (tilt).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import ICUB_DIR

from flexforce.cli import main
from flexforce.datasets.rosimport import import_bag

WALK = ICUB_DIR / "icub-walk-12s"
SWAY = ICUB_DIR / "icub-com-sinusoid-20s.bag"
pytestmark = pytest.mark.skipif(not SWAY.exists() or not WALK.exists(),
                                reason="the iCub recordings are not beside this checkout")
SKIP = 0.5  # s, as the comparison leaves out


def _naive(bag):
    """Equal-split vertical force RMSE against F/T, and leg odometry's tilt RMSE against Vicon."""
    from scipy.spatial.transform import Rotation

    rec = import_bag(bag, "icub-identified")
    keep = rec.time >= rec.time[0] + SKIP
    act = rec.contact_active
    share = np.where(act, rec.mass * 9.81 / np.maximum(act.sum(axis=1, keepdims=True), 1), 0.0)
    force = float(np.sqrt(np.nanmean((share - rec.ft[:, :, 2])[keep] ** 2)))
    mocap = rec.mocap["root_link"]
    ok = keep & np.all(np.isfinite(mocap), axis=1)
    up_odometry = Rotation.from_quat(rec.base_pose[ok, 3:]).as_matrix()[:, 2, :]
    up_vicon = Rotation.from_quat(mocap[ok, 3:]).as_matrix()[:, 2, :]
    tilt = np.arccos(np.clip(np.sum(up_odometry * up_vicon, axis=1), -1, 1))
    return force, float(np.sqrt(np.mean(tilt ** 2)))


def _compare(bag, tmp_path):
    out = tmp_path / bag.stem
    assert main(["compare", str(bag), "--robot", "icub-identified", "-o", str(out), "-q"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert not summary.get("failures"), summary.get("failures")
    return {k: v["rmse"] for k, v in summary["estimators"].items()}


def test_icub_sway_imu_only(tmp_path, capsys):
    """CoM sway (double support): every estimator's per-foot vertical force is well below the
    equal split, the tilt within 1 deg of Vicon -- but not better than leg odometry (the
    accelerometer's vertical disagrees with Vicon's by 0.6 deg: README)."""
    naive_force, odometry_tilt = _naive(SWAY)
    assert 18.0 < naive_force < 26.0 and np.degrees(odometry_tilt) < 0.6
    rmse = _compare(SWAY, tmp_path)
    assert set(rmse) == {"ekf", "fixed_lag", "batch"}
    for name, r in rmse.items():
        assert r["vertical_force_N"] < 0.55 * naive_force, (name, r["vertical_force_N"], naive_force)
        assert np.degrees(r["rotation_rad"]) < 1.0, (name, np.degrees(r["rotation_rad"]))


def test_icub_walk_imu_only(tmp_path, capsys):
    """Walk: the tilt is within 1.7 deg of Vicon for every estimator and the smoothers beat leg
    odometry; the vertical force is no better than the equal split (the contact detection, not
    the estimator, sets it: README)."""
    naive_force, odometry_tilt = _naive(WALK)
    rmse = _compare(WALK, tmp_path)
    for name, r in rmse.items():
        assert np.degrees(r["rotation_rad"]) < 1.7, (name, np.degrees(r["rotation_rad"]))
        assert r["vertical_force_N"] < 1.3 * naive_force, (name, r["vertical_force_N"], naive_force)
    assert rmse["fixed_lag"]["rotation_rad"] < odometry_tilt
