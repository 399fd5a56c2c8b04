"""Robot inputs from pinocchio: the paper's local-frame quantities and their time derivatives."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from flexforce.datasets.robot import RobotConfig, RobotModel
from flexforce.errors import ConfigError


@pytest.fixture(scope="module", params=["romeo", "talos", "icub"])
def robot(request):
    config = RobotConfig.load(request.param)
    if not Path(config.urdf).exists():  # the iCub's URDF lives with its recordings, beside the checkout
        pytest.skip(f"URDF of robot '{request.param}' not beside this checkout: {config.urdf}")
    return RobotModel(config)


def _trajectory(robot, seed=0):
    """A smooth trajectory q(t) = q0 + v0 t + a0 t^2/2 on the configuration manifold."""
    rng = np.random.default_rng(seed)
    q0 = robot.q_reference.copy()
    v0 = 0.3 * rng.standard_normal(robot.model.nv)
    a0 = rng.standard_normal(robot.model.nv)

    def at(t):
        return pin.integrate(robot.model, q0, v0 * t + 0.5 * a0 * t * t), v0 + a0 * t, a0

    return at


def test_inputs_are_time_derivatives_of_each_other(robot):
    """dc, ddc, dI, dsigma and the IMU's velocity and acceleration are the derivatives of the rest."""
    at = _trajectory(robot)
    h = 1e-5
    k0 = robot.kinematics(*at(0.0))
    kp = robot.kinematics(*at(h))
    km = robot.kinematics(*at(-h))

    def d(f):
        return (f(kp) - f(km)) / (2 * h)

    i0 = k0.inputs
    np.testing.assert_allclose(d(lambda k: k.inputs.c), i0.dc, atol=1e-7)
    np.testing.assert_allclose(d(lambda k: k.inputs.dc), i0.ddc, atol=1e-6)
    np.testing.assert_allclose(d(lambda k: k.inputs.I), i0.dI, atol=1e-6 * max(1.0, np.abs(i0.dI).max()))
    np.testing.assert_allclose(d(lambda k: k.inputs.sigma), i0.dsigma,
                               atol=1e-6 * max(1.0, np.abs(i0.dsigma).max()))
    np.testing.assert_allclose(d(lambda k: k.imu.p), k0.imu.v, atol=1e-7)
    np.testing.assert_allclose(d(lambda k: k.imu.v), k0.imu.a, atol=1e-6)
    # angular velocity of the IMU: dR/dt = [w]x R
    dR = d(lambda k: k.imu.R)
    W = dR @ k0.imu.R.T
    np.testing.assert_allclose([W[2, 1], W[0, 2], W[1, 0]], k0.imu.w, atol=1e-7)


def test_inertia_and_momentum_about_the_local_origin(robot):
    """Correction 3: I_l = sum of body inertias about the origin; sigma_l = sum of body momenta."""
    model = robot.model
    data = model.createData()
    q, v, a = _trajectory(robot, seed=1)(0.0)
    kin = robot.kinematics(q, v, a)
    pin.forwardKinematics(model, data, q, v)
    I = np.zeros((3, 3))
    sigma = np.zeros(3)
    for i in range(1, model.njoints):
        Y = model.inertias[i]
        M = data.oMi[i]
        R = M.rotation
        c = M.translation + R @ Y.lever
        vi = data.v[i]
        w = R @ vi.angular
        dc = R @ (vi.linear + np.cross(vi.angular, Y.lever))
        Ic = R @ Y.inertia @ R.T
        S = pin.skew(c)
        I += Ic - Y.mass * S @ S
        sigma += Ic @ w + Y.mass * np.cross(c, dc)
    np.testing.assert_allclose(kin.inputs.I, I, atol=1e-10)
    np.testing.assert_allclose(kin.inputs.sigma, sigma, atol=1e-10)
    assert kin.inputs.m == pytest.approx(sum(model.inertias[i].mass for i in range(1, model.njoints)))


def test_reference_posture_stands_on_the_ground(robot):
    kin = robot.kinematics(robot.q_reference, np.zeros(robot.model.nv), np.zeros(robot.model.nv))
    np.testing.assert_allclose(kin.contact_p[:, 2], 0.0, atol=1e-12)
    np.testing.assert_allclose(kin.contact_p[:, :2].mean(axis=0), 0.0, atol=1e-12)
    assert kin.inputs.c[2] > 0.4  # CoM well above the soles
    # The default stiffness keeps even single support stable (DESIGN.md, "Stability").
    k_ts = robot.contact_params()[0].K_ts[0, 0]
    assert k_ts > robot.mass * robot.config.gravity * kin.inputs.c[2]


def test_config_errors_are_clear(tmp_path):
    with pytest.raises(ConfigError, match="unknown robot 'hrp9'.*romeo"):
        RobotConfig.load("hrp9")
    bad = tmp_path / "bad.toml"
    bad.write_text(RobotConfig.load("romeo").source and open(RobotConfig.load("romeo").source).read()
                   .replace('frame = "l_sole"', 'frame = "l_foot_that_is_not"'))
    with pytest.raises(ConfigError, match="frame 'l_foot_that_is_not'.*not in the URDF"):
        RobotModel(RobotConfig.load(bad))
    bad.write_text('name = "x"\nurdf = "nowhere.urdf"\nimu_frame = "imu"\ncontacts = []\ncolour = 1\n')
    with pytest.raises(ConfigError, match="unknown key.*colour"):
        RobotConfig.load(bad)
    bad.write_text('name = "x"\nurdf = "nowhere.urdf"\nimu_frame = "imu"\ncontacts = []\n')
    with pytest.raises(ConfigError, match="URDF of robot 'x' not found"):
        RobotModel(RobotConfig.load(bad))
    bad.write_text("name = [")
    with pytest.raises(ConfigError, match="not valid TOML"):
        RobotConfig.load(bad)
