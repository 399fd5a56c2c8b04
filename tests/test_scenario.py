"""Scenario parameters of the simulated world: ambient disturbance, sensor noise, touch-down, walks.

The estimators' assumptions come from the robot configuration; these parameters change only the
world, so a scenario that departs from the configuration is a mismatched case.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import signal

from flexforce.datasets.robot import RobotConfig
from flexforce.datasets.sim.scenario import Scenario, Walk
from flexforce.datasets.sim.simulator import Simulator
from flexforce.errors import ConfigError
from flexforce.factors.model import ModelConfig


@pytest.mark.parametrize("raw, match", [
    ({"ambient": {"linear": -0.1}}, r"ambient.linear = -0.1 m/s\^2: expected a non-negative RMS level"),
    ({"ambient": {"angular": "x"}}, r"ambient.angular = 'x' rad/s\^2"),
    ({"ambient": {"corner": 600.0}},
     r"ambient.corner = 600.0 Hz: expected .* below half the integration rate \(500 Hz\)"),
    ({"ambient": {"scale": -3}}, r"ambient.scale = -3 \(factor\): expected a non-negative factor"),
    ({"ambient": {"level": 1.0}}, r"unknown key\(s\) \['level'\] in \[ambient\]"),
    ({"ambient": "loud"}, r"ambient = 'loud': expected true, false or a table"),
    ({"ambient": {"kind": "wind"}}, r"ambient.kind = 'wind': expected 'acceleration' or 'wrench'"),
    ({"ambient": {"kind": "wrench", "force": 5.0}}, r"ambient.torque is missing: .* \[N m\]"),
    ({"ambient": {"kind": "wrench", "force": 5.0, "torque": 1.0, "linear": 0.1}},
     r"ambient.linear does not apply to kind = 'wrench'"),
    ({"touchdown": "soft"}, r"touchdown = 'soft': expected one of \['floor', 'relaxed', 'deflected'\]"),
    ({"imu_noise": {"scale": 0.0 - 2}}, r"imu_noise.scale = -2.0 \(factor\)"),
    ({"walk": {"steps": 0}}, r"walk.steps = 0: expected a whole number of swings, at least 1"),
    ({"walk": {"stride": 0.8}}, r"walk.stride = 0.8 m: expected a forward displacement between -0.5 and 0.5 m"),
    ({"walk": {"double_support": 0}}, r"walk.double_support = 0 s: expected a positive duration"),
    ({"walk": {"pace": 1}}, r"unknown key\(s\) \['pace'\] in \[walk\]"),
    ({"walk": {"steps": 20}}, r"duration = 5.0 s: expected at least the walk's end \(32.5 s"),
    ({"posture": {"icub": {"l_knee": "bent"}}}, r"posture.icub.l_knee = 'bent' rad"),
    ({"walk": {"travel": [0.8, 0.2]}},
     r"walk.travel = \[0.8, 0.2\] \(fractions of the swing\): expected \[start, end\] with 0 <= start < end <= 1"),
    ({"swing": [{"contact": "right_foot", "lift": 1.0, "land": 2.0, "travel": [0.5, 1.5]}]},
     r"swing of right_foot: travel = \[0.5, 1.5\] \(fractions of the swing\)"),
])
def test_bad_scenario_input_is_named(raw, match):
    with pytest.raises(ConfigError, match=match):
        Scenario.from_dict({"name": "bad", "duration": 5.0, **raw})


def test_swing_travels_in_the_middle():
    sc = Scenario.from_dict({"name": "s", "duration": 3.0, "swing": [
        {"contact": "right_foot", "lift": 1.0, "land": 2.0, "displacement": [0.1, 0.0, 0.0], "travel": [0.25, 0.75]}]})
    sw = sc.swings()[0]
    for t in (1.0, 1.1, 1.25):  # lifting: no horizontal motion yet
        d, v, a = sw(t)
        assert d[0] == 0.0 and v[0] == 0.0 and a[0] == 0.0
    assert sw(1.5)[0][0] == pytest.approx(0.05)
    for t in (1.75, 1.9, 2.0):  # descending: arrived
        d, v, a = sw(t)
        assert d[0] == pytest.approx(0.1) and v[0] == 0.0 and a[0] == 0.0
    # velocity and acceleration are the derivatives of the displacement (central differences)
    h = 1e-5
    for t in (1.3, 1.5, 1.7):
        np.testing.assert_allclose(sw(t)[1], (sw(t + h)[0] - sw(t - h)[0]) / (2 * h), atol=1e-6)
        np.testing.assert_allclose(sw(t)[2], (sw(t + h)[1] - sw(t - h)[1]) / (2 * h), atol=1e-4)


def test_walk_alternates_single_and_double_support():
    walk = Walk(steps=5, start=1.0, double_support=1.0, single_support=0.5, stride=0.1, settle=1.0)
    base, swing = walk.items()
    assert [s["contact"] for s in swing] == ["right_foot", "left_foot"] * 2 + ["right_foot"]
    assert [b.get("toward") for b in base] == ["left_foot", "right_foot"] * 2 + ["left_foot", "middle"]
    # half a stride first and last: the feet start and end side by side
    right = sum(s["displacement"][0] for s in swing if s["contact"] == "right_foot")
    left = sum(s["displacement"][0] for s in swing if s["contact"] == "left_foot")
    assert right == pytest.approx(left) == pytest.approx(0.2)
    for b, s in zip(base, swing):  # the weight shift ends where the swing starts
        assert b["start"] + b["duration"] == pytest.approx(s["lift"])
    assert walk.end == pytest.approx(1.0 + 5 * 1.5 + 1.0)


@pytest.mark.parametrize("name, steps, at_least", [("walk", 20, 30.0), ("walk-short", 4, 8.0)])
def test_builtin_walks(name, steps, at_least):
    sc = Scenario.load(name)
    assert sc.duration >= at_least and len(sc.swings()) == steps
    assert sc.walk_spec().end <= sc.duration


def test_estimators_take_their_noise_from_the_robot_configuration():
    """A world whose IMU is twice as noisy as the data sheet: the recording says so (for reports),
    the estimators still assume the configuration's densities."""
    sc = Scenario.from_dict({"name": "noisy", "duration": 0.5, "imu_noise": {"scale": 2.0},
                             "ft_noise": {"scale": 3.0}})
    sim = Simulator(sc)
    rec = sim.run()
    cfg = RobotConfig.load("romeo")
    assert rec.meta["imu_noise"]["gyro_density"] == pytest.approx(2 * cfg.imu_noise.gyro_density)
    assert rec.meta["ft_noise"]["force"] == pytest.approx(3 * cfg.ft_noise.force)
    model = ModelConfig.from_recording(rec)
    assert model.gyro_sigma == pytest.approx(cfg.imu_noise.gyro_density * math.sqrt(200.0))
    assert model.accel_sigma == pytest.approx(cfg.imu_noise.accel_density * math.sqrt(200.0))
    assert model.ft_force_sigma == pytest.approx(cfg.ft_noise.force)


def test_imu_noise_scale_reaches_the_readings():
    base = {"name": "still", "duration": 2.0, "ambient": False}
    clean = Simulator(Scenario.from_dict(base), noise=False).run()
    noisy = Simulator(Scenario.from_dict({**base, "imu_noise": {"scale": 2.0}})).run()
    cfg = RobotConfig.load("romeo").imu_noise
    err = noisy.gyro - clean.gyro - noisy.truth.gyro_bias
    # 1200 draws: the sample std is within 5% of the true one at more than 3 sigma
    assert err.std() / (2 * cfg.gyro_sigma(200.0)) == pytest.approx(1.0, abs=0.05)
    err = noisy.accel - clean.accel - noisy.truth.accel_bias
    assert err.std() / (2 * cfg.accel_sigma(200.0)) == pytest.approx(1.0, abs=0.05)


def test_default_ambient_is_white_at_the_samples():
    """Default levels: the configuration's per-sample accelerometer noise (linear) and that over
    the IMU's lever to the feet (angular); linear between the samples."""
    sim = Simulator(Scenario.from_dict({"name": "amb", "duration": 1.0}))
    sa, sdw = sim.ambient
    assert sa == pytest.approx(RobotConfig.load("romeo").imu_noise.accel_sigma(200.0))
    table = sim._ambient_table(201, 5)
    assert table.shape == (1001, 6)
    x = table[::5]  # at the samples
    np.testing.assert_allclose(table[2::5], 0.6 * x[:-1] + 0.4 * x[1:], atol=1e-12)
    assert x[:, 3:].std() == pytest.approx(sa, rel=0.1)  # 603 draws: 10% is above 3 sigma
    assert x[:, :3].std() == pytest.approx(sdw, rel=0.1)
    scaled = Simulator(Scenario.from_dict({"name": "amb", "duration": 1.0, "ambient": {"scale": 3.0}}))
    np.testing.assert_allclose(scaled._ambient_table(201, 5), 3.0 * table, rtol=1e-12)


def test_band_limited_ambient_has_its_level_and_corner():
    sc = Scenario.from_dict({"name": "amb", "duration": 1.0,
                             "ambient": {"linear": 0.2, "angular": 0.5, "corner": 10.0}})
    sim = Simulator(sc)
    n = 20 * 200 + 1
    table = sim._ambient_table(n, 5)  # 20 s at 1 kHz
    # RMS at the stated level: 6 axes x 20 s of a 10 Hz process (~400 independent values each)
    assert table[:, 3:].std() == pytest.approx(0.2, rel=0.1)
    assert table[:, :3].std() == pytest.approx(0.5, rel=0.1)
    f, pxx = signal.welch(table[:, 3:], fs=1000.0, axis=0, nperseg=2048)
    p = pxx.mean(axis=1)
    low = p[(f > 0.5) & (f < 5.0)].mean()
    assert p[(f > 40.0) & (f < 60.0)].mean() < 0.01 * low  # second order: (10/50)^4 = 1.6e-3


@pytest.mark.parametrize("ambient", [{"scale": 3.0}, {"kind": "wrench", "force": 4.0, "torque": 0.5, "corner": 20.0}])
def test_ambient_disturbance_is_the_missing_wrench(ambient):
    """The truth's ambient wrench is what Newton-Euler (eq. 16, 23, written independently of the
    simulator) misses on the ground truth: with it, the residual vanishes."""
    from flexforce.factors import physics as ph

    sc = Scenario.from_dict({"name": "amb", "duration": 0.5, "ambient": ambient})
    sim = Simulator(sc)
    rec = sim.run()
    tr = rec.truth
    if ambient.get("kind") == "wrench":  # the wrench on the base is the table itself
        table = sim._ambient_table(rec.n, 5)[::5]
        np.testing.assert_allclose(tr.ambient_wrench[:, :3], table[:, 3:], atol=1e-12)
        assert rec.meta["ambient"]["sigma_force_N"] == 4.0
    m, g = rec.mass, rec.gravity
    h = rec.com[0, 2]
    for k in range(0, rec.n, 10):
        res = ph.newton_euler_residual(tr.R[k], tr.t[k], tr.w[k], tr.v[k], tr.dw[k], tr.a[k],
                                       tr.total_wrench[k] + tr.disturbance_wrench[k], rec.inputs(k), g)
        assert np.abs(res[:3]).max() < 1e-7 * m * g
        assert np.abs(res[3:]).max() < 1e-7 * m * g * h
        # without it, the residual is the ambient wrench
        miss = ph.newton_euler_residual(tr.R[k], tr.t[k], tr.w[k], tr.v[k], tr.dw[k], tr.a[k],
                                        tr.total_wrench[k], rec.inputs(k), g)
        np.testing.assert_allclose(miss, res + tr.ambient_wrench[k], atol=1e-9)
