"""Footholds of real logs: the ground prior on a landing sole, its configuration, and leg odometry
against motion capture on the shipped iCub walk."""

from __future__ import annotations

import dataclasses
import types

import numpy as np
import pinocchio as pin
import pytest
from conftest import ICUB_DIR

from flexforce.datasets.io.localframe import on_ground
from flexforce.datasets.robot import FootholdConfig, RobotConfig
from flexforce.errors import ConfigError

WALK = ICUB_DIR / "icub-walk-12s"


def _tilted(angle: float, yaw: float, p) -> pin.SE3:
    """A sole at ``p`` with yaw ``yaw`` then tilted by ``angle`` about a horizontal axis."""
    R = pin.exp3(np.array([0.6, 0.8, 0.0]) * angle) @ pin.exp3(np.array([0.0, 0.0, yaw]))
    return pin.SE3(R, np.asarray(p, dtype=float))


@pytest.mark.parametrize("angle", [1e-7, 0.01, 0.2])
def test_ground_prior_removes_its_share_of_the_tilt_and_height(angle):
    """The fused sole keeps its yaw and horizontal position; its tilt and height off the floor
    shrink by ``1 - w``, ``w = s_kin^2 / (s_kin^2 + s_ground^2)``, computed by hand here."""
    cfg = FootholdConfig(ground_sigma_tilt=0.01, kinematics_sigma_tilt=0.02,
                         ground_sigma_height=0.003, kinematics_sigma_height=0.004)
    w_tilt, w_height = 0.02**2 / (0.02**2 + 0.01**2), 0.004**2 / (0.004**2 + 0.003**2)
    M = _tilted(angle, 0.7, [0.3, -0.1, 0.012])
    fused, tilt, height = on_ground(M, cfg)
    assert tilt == pytest.approx(angle, rel=1e-9, abs=1e-12) and height == pytest.approx(0.012)
    z = fused.rotation[:, 2]
    assert np.arctan2(np.linalg.norm(z[:2]), z[2]) == pytest.approx((1 - w_tilt) * angle, rel=1e-6, abs=1e-12)
    np.testing.assert_allclose(fused.translation, [0.3, -0.1, (1 - w_height) * 0.012], atol=1e-12)
    # yaw: the sole's x axis keeps its heading in the horizontal plane
    x0, x1 = M.rotation[:2, 0], fused.rotation[:2, 0]
    assert np.arctan2(x1[1], x1[0]) == pytest.approx(np.arctan2(x0[1], x0[0]), abs=2 * angle**2 + 1e-9)


def test_no_ground_prior_keeps_the_kinematics_and_a_plane_can_be_sloped():
    M = _tilted(0.05, 0.0, [0.1, 0.0, 0.02])
    fused, _, _ = on_ground(M, None)
    assert fused.isApprox(M)
    assert FootholdConfig(terrain="none").tilt_weight == 0.0
    # a 0.05 rad slope, the sole lying on it: nothing to correct
    n = M.rotation[:, 2]
    cfg = FootholdConfig(terrain="plane", plane_normal=tuple(2 * n), plane_height=2 * float(n @ M.translation))
    fused, tilt, height = on_ground(M, cfg)
    assert tilt == pytest.approx(0.0, abs=1e-7) and height == pytest.approx(0.0, abs=1e-12)
    assert fused.isApprox(M, 1e-9)


@pytest.mark.parametrize("key, value, match", [
    ("terrain", "bumpy", "footholds.terrain = 'bumpy'; expected 'flat', 'plane' or 'none'"),
    ("ground_sigma_tilt", 0.0, "footholds.ground_sigma_tilt = 0.0; expected a positive number of rad"),
    ("kinematics_sigma_height", float("nan"), "footholds.kinematics_sigma_height = nan; expected a positive"),
    ("plane_normal", (0.0, 0.0, 0.0), "footholds.plane_normal"),
])
def test_bad_foothold_configuration(key, value, match):
    with pytest.raises(ConfigError, match=match.replace("(", r"\(").replace(")", r"\)")):
        FootholdConfig(**{key: value})


def test_unknown_foothold_key_is_refused():
    raw = {"name": "r", "urdf": "x.urdf", "imu_frame": "imu", "contacts": [], "footholds": {"terain": "flat"},
           "stiffness": {"k_fs": 1e4, "k_fd": 100.0, "k_ts": 300.0, "k_td": 5.0}}
    with pytest.raises(ConfigError, match=r"unknown key\(s\) \['terain'\] in \[footholds\]"):
        RobotConfig.from_dict(raw)


@pytest.mark.skipif(not WALK.exists(), reason="the iCub recordings are not beside this checkout")
def test_leg_odometry_tilt_on_the_icub_walk():
    """Leg odometry alone (no estimator) against Vicon: the ground prior takes the touch-down
    tilts out of the local frame.  Measured RMSE (after 0.5 s): 1.26 deg without the prior
    (kinematic footholds), 1.13 deg with it; bound: the measured value plus 0.05 deg."""
    from flexforce.compare.metrics import base_tilt_error
    from flexforce.datasets.io.rosimport import import_bag

    out = {}
    for terrain in ("none", "flat"):
        cfg = RobotConfig.load("icub")
        rec = import_bag(WALK, dataclasses.replace(cfg, footholds=FootholdConfig(terrain=terrain)))
        still = types.SimpleNamespace(R=np.tile(np.eye(3), (rec.n, 1, 1)))
        tilt = base_tilt_error(still, rec, "root_link")[rec.time > 0.5]
        out[terrain] = float(np.degrees(np.sqrt(np.nanmean(tilt**2))))
    assert out["flat"] < 1.13 + 0.05
    assert out["flat"] < out["none"] - 0.08
