"""Robot inputs from pinocchio: the paper's local-frame quantities and their time derivatives."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from flexforce.datasets.recording import Recording
from flexforce.datasets.robot import RobotConfig, RobotModel, Stiffness, check_toppling
from flexforce.errors import ConfigError, ConfigWarning, DataError

STIFFNESS = "[stiffness]\nk_fs = 28000.0\nk_fd = 420.0\nk_ts = 450.0\nk_td = 8.0\n"


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


def test_inertia_rate_equals_the_analytic_sum_over_the_bodies(robot):
    """dI_l/dt from pinocchio's dccrba equals the per-body analytic sum to rounding (~1e-15
    relative), at slow and fast motions, and is zero at rest."""
    rng = np.random.default_rng(3)
    model, data = robot.model, robot.data
    worst = 0.0
    for scale in (1e-3, 0.1, 1.0, 10.0):
        for _ in range(5):
            q = robot.q_reference.copy()
            q[:3] = rng.normal(0.0, 1.0, 3)
            q[3:7] = pin.Quaternion(pin.exp3(rng.normal(0.0, 0.3, 3))).coeffs()
            q[7:] += rng.normal(0.0, 0.3, model.nq - 7)
            v = scale * rng.standard_normal(model.nv)
            pin.forwardKinematics(model, data, q, v)
            ref = robot._inertia_rate_bodies()
            new = robot._inertia_rate(q, v)
            worst = max(worst, float(np.abs(new - ref).max() / np.abs(ref).max()))
    assert worst < 1e-12
    assert not robot._inertia_rate(robot.q_reference, np.zeros(model.nv)).any()


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
    bad.write_text('name = "x"\nurdf = "nowhere.urdf"\nimu_frame = "imu"\ncontacts = []\n' + STIFFNESS)
    with pytest.raises(ConfigError, match="URDF of robot 'x' not found"):
        RobotModel(RobotConfig.load(bad))
    bad.write_text("name = [")
    with pytest.raises(ConfigError, match="not valid TOML"):
        RobotConfig.load(bad)


# ---- validation at load ---------------------------------------------------------------------------
ROMEO_TOML = Path(RobotConfig.load("romeo").source).read_text()


def _romeo_with(tmp_path, old: str, new: str) -> Path:
    assert old in ROMEO_TOML
    path = tmp_path / "robot.toml"
    path.write_text(ROMEO_TOML.replace(old, new))
    return path


@pytest.mark.parametrize("old, new, message", [
    ("k_fs = 28000.0", "k_fs = -28000.0",
     "stiffness.k_fs = -28000.0 N/m; expected a positive, finite stiffness"),
    ("k_fs = 28000.0", "k_fs = nan", "stiffness.k_fs = nan N/m; expected a positive, finite stiffness"),
    ("k_fs = 28000.0", 'k_fs = "stiff"', "stiffness.k_fs = 'stiff' N/m; expected a positive, finite stiffness"),
    ("k_ts = 450.0", "k_ts = 0.0", "stiffness.k_ts = 0.0 N m/rad; expected a positive, finite stiffness"),
    ("k_ts = 450.0", "k_ts = [450.0, -1.0, 450.0]",
     r"stiffness.k_ts = \[450.0, -1.0, 450.0\] N m/rad; expected a positive, finite stiffness \(a number, or 3"),
    ("k_fd = 420.0", "k_fd = -1.0", "stiffness.k_fd = -1.0 N s/m; expected a positive, finite damping"),
    ("k_td = 8.0", "k_td = inf", "stiffness.k_td = inf N m s/rad; expected a positive, finite damping"),
    ("k_td = 8.0", "", r"\[stiffness\] lacks k_td \(N m s/rad\).*expected all of k_fs, k_fd, k_ts and k_td"),
    ("k_td = 8.0", "k_td = 8.0\nk_tx = 1.0", r"unknown key\(s\) \['k_tx'\] in \[stiffness\]"),
    ("[stiffness]", "gravity = -9.81\n[stiffness]",
     "gravity = -9.81 m/s\\^2 in robot configuration .*; expected a positive, finite acceleration"),
    ("[stiffness]", "[imu_noise]\ngyro_density = 0.0\n[stiffness]",
     r"imu_noise.gyro_density = 0.0 rad/s/sqrt\(Hz\); expected a positive, finite noise density"),
    ("[stiffness]", "[ft_noise]\nforce = -2.0\n[stiffness]",
     "ft_noise.force = -2.0 N; expected a positive, finite standard deviation"),
])
def test_bad_springs_and_noise_are_refused_at_load(tmp_path, old, new, message):
    """Each message names the key, its value, its unit and what is expected (and the file)."""
    path = _romeo_with(tmp_path, old, new)
    with pytest.raises(ConfigError, match=message) as info:
        RobotConfig.load(path)
    assert str(path) in str(info.value)


def test_a_missing_stiffness_section_is_an_error(tmp_path):
    """No silent HRP-2 defaults: the springs are the robot's (DESIGN.md, "Stability")."""
    path = tmp_path / "robot.toml"
    path.write_text(ROMEO_TOML.split("[stiffness]")[0])
    with pytest.raises(ConfigError, match=r"the \[stiffness\] section is missing in robot configuration .*robot.toml; "
                                          r"expected .*k_fs \(N/m\), k_fd \(N s/m\), k_ts \(N m/rad\)"):
        RobotConfig.load(path)


def test_stiffness_checked_when_built_in_python():
    with pytest.raises(ConfigError, match="stiffness.k_fs = -1.0 N/m"):
        Stiffness(k_fs=-1.0)
    with pytest.raises(ConfigError, match=r"stiffness.k_ts = \[1.0, 2.0\] N m/rad"):
        Stiffness(k_ts=(1.0, 2.0))


def test_k_ts_against_gravity_toppling(tmp_path):
    """Romeo: m g h = 40.5 kg x 9.81 x 0.663 m = 263 N m/rad.  Below it with both feet in force (2 k_ts): an
    error; below it for one foot alone: a warning (single support unstable, double support fine)."""
    with pytest.warns(ConfigWarning, match=r"stiffness.k_ts = 200 N m/rad of robot 'romeo' is not above the "
                                           r"gravity toppling stiffness m g h = 40.5 kg x 9.81 m/s\^2 x 0.66\d m = "
                                           r"26\d N m/rad"):
        RobotModel(RobotConfig.load(_romeo_with(tmp_path, "k_ts = 450.0", "k_ts = 200.0")))
    with pytest.raises(ConfigError, match=r"stiffness.k_ts = 100.0 N m/rad of robot 'romeo': with its 2 contact\(s\) "
                                          r"in force the tilt stiffness about y \(pitch\) is 200 N m/rad, not above "
                                          r"the gravity toppling stiffness m g h = .* expected a stiffer k_ts"):
        RobotModel(RobotConfig.load(_romeo_with(tmp_path, "k_ts = 450.0", "k_ts = 100.0")))


def test_toppling_counts_the_contact_spacing():
    """Two feet 0.2 m apart: the vertical springs add k_fs d^2 about the roll axis, not about pitch."""
    stiffness = Stiffness(k_fs=1e4, k_fd=1.0, k_ts=60.0, k_td=1.0)
    feet = np.array([[0.0, 0.1, 0.0], [0.0, -0.1, 0.0]])
    R = np.array([np.eye(3)] * 2)
    check_toppling(stiffness, 10.0, np.array([0.0, 0.0, 1.0]), feet[:1] * 0, R[:1], gravity=1.0)  # 60 > 10
    with pytest.raises(ConfigError, match=r"about y \(pitch\) is 120 N m/rad"):  # roll: 120 + 2 * 1e4 * 0.01
        check_toppling(stiffness, 200.0, np.array([0.0, 0.0, 1.0]), feet, R, gravity=1.0)


def test_negative_and_zero_masses_in_the_urdf(tmp_path):
    import re

    config = RobotConfig.load("romeo")
    urdf = Path(config.urdf).read_text()
    for value, message in (("-1.0", r"the mass of the links moved by joint '\w+' in the URDF .*neg.urdf is "
                                    r"-\d+\.\d+ kg; expected a non-negative, finite mass"),
                           ("0.0", "the total mass of robot 'romeo' in the URDF .*neg.urdf is 0.0 kg; expected a "
                                   "positive mass")):
        (tmp_path / "neg.urdf").write_text(re.sub(r'<mass value="[^"]*"', f'<mass value="{value}"', urdf))
        path = _romeo_with(tmp_path, 'urdf = "erd:romeo_description/urdf/romeo.urdf"',
                           f'urdf = "{tmp_path / "neg.urdf"}"')
        with pytest.raises(ConfigError, match=message):
            RobotModel(RobotConfig.load(path))


def test_a_negative_inertia_in_the_urdf(tmp_path):
    """A link's rotational inertia with a negative principal moment: refused naming the joint and
    the moments (a small one was accepted silently, a large one ended in a covariance failure)."""
    import re

    config = RobotConfig.load("romeo")
    urdf = Path(config.urdf).read_text()
    bad, n = re.subn(r'ixx="[^"]*"', 'ixx="-2.0"', urdf, count=1)
    assert n == 1
    (tmp_path / "neg.urdf").write_text(bad)
    path = _romeo_with(tmp_path, 'urdf = "erd:romeo_description/urdf/romeo.urdf"', f'urdf = "{tmp_path / "neg.urdf"}"')
    with pytest.raises(ConfigError, match=r"the rotational inertia of the links moved by joint '\w+' in the URDF "
                                          r".*neg.urdf is not positive semi-definite \(principal moments \[-"):
        RobotModel(RobotConfig.load(path))


def test_a_recording_too_short_for_the_estimators():
    from flexforce.compare.estimators import run_estimator

    rec = _short_recording(3)
    with pytest.raises(DataError, match="recording has 3 sample\\(s\\) at 200 Hz; the estimators need at least 10 "
                                        "samples"):
        run_estimator("ekf", rec)
    assert Recording.MIN_SAMPLES == 10


def _short_recording(n: int) -> Recording:
    from flexforce.datasets.sim.scenario import Scenario
    from flexforce.datasets.sim.simulator import Simulator

    rec = Simulator(Scenario.from_dict({"name": "s", "duration": 0.1}), noise=False).run()
    return rec.slice(0, n)


def test_imu_bias_random_walks_may_be_zero():
    from flexforce.datasets.robot import ImuNoise

    ImuNoise(gyro_bias_rw=0.0, accel_bias_rw=0.0)
    with pytest.raises(ConfigError, match=r"imu_noise.accel_bias_rw = -1.0 m/s\^3/sqrt\(Hz\); expected a finite "
                                          "random walk >= 0"):
        ImuNoise(accel_bias_rw=-1.0)


def test_imu_filter_is_checked():
    """``[ros] imu_filter``: ``none`` by default; another value than ``none`` or ``savgol`` is refused,
    naming the key, the value, the configuration and the expected values."""
    from flexforce.datasets.robot import RosConfig

    assert RosConfig().imu_filter == "none" and RosConfig(imu_filter="savgol").imu_filter == "savgol"
    raw = {"name": "x", "urdf": "x", "imu_frame": "x", "contacts": [],
           "stiffness": {"k_fs": 1e4, "k_fd": 1e2, "k_ts": 3e2, "k_td": 5.0}, "ros": {"imu_filter": "lowpass"}}
    with pytest.raises(ConfigError, match=r"ros.imu_filter = 'lowpass'; expected 'none' \(the readings as given\) "
                                          r"or 'savgol' \(the joints' Savitzky-Golay smoother\) in robot "
                                          "configuration x.toml"):
        RobotConfig.from_dict(raw, source="x.toml")


def test_a_file_that_is_no_urdf_is_one_error_line(tmp_path, capfd):
    """urdfdom prints its parse errors on the C stderr: they go into the one ConfigError instead of
    coming before it."""
    bad = tmp_path / "robot.urdf"
    bad.write_text('name = "not xml"\n')
    path = _romeo_with(tmp_path, 'urdf = "erd:romeo_description/urdf/romeo.urdf"', f'urdf = "{bad}"')
    with pytest.raises(ConfigError, match=r"cannot read URDF .*robot.urdf: .*\(Error: .*XML"):
        RobotModel(RobotConfig.load(path))
    assert capfd.readouterr().err == ""
