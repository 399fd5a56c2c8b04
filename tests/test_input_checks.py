"""Inputs that are wrong but look right are refused with one error naming the value, its unit and
what was expected (issue 42): command-line counts and seeds, a scenario's timing fields (in its
TOML file and as overrides), a robot configuration's grid rate and IMU ranges, and time stamps in
seconds instead of integer nanoseconds."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np
import pytest

from flexforce.cli import main
from flexforce.datasets.recording import Recording
from flexforce.datasets.robot import RobotConfig
from flexforce.datasets.sim.scenario import MAX_SAMPLES, Scenario
from flexforce.errors import ConfigError, DataError

ROMEO = Path(__file__).resolve().parents[1] / "datasets" / "robots" / "romeo.toml"


# ----------------------------------------------------------------------------------------------
# command line: counts and seeds (argparse refuses them, exit status 2, before any work)
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("argv, match", [
    (["compare", "stand", "--seeds", "0"], r"argument --seeds: '0'; expected a number of noise seeds, a whole "
                                           r"number >= 1"),
    (["compare", "stand", "--seeds", "-2"], r"argument --seeds: '-2'; expected a number of noise seeds"),
    (["compare", "stand", "--seeds", "five"], r"argument --seeds: 'five'; expected a number of noise seeds"),
    (["diagnose", "stand", "--max-effects", "-1"], r"argument --max-effects: '-1'; expected a number of effects, "
                                                   r"a whole number >= 0"),
    (["diagnose", "stand", "--seed", "-2"], r"argument --seed: '-2'; expected a noise seed, a whole number >= 0"),
    (["simulate", "stand", "--seed", "-1"], r"argument --seed: '-1'; expected a noise seed"),
    (["simulate", "stand", "--duration", "five"], r"argument --duration: invalid float value: 'five'"),
])
def test_cli_counts_are_checked(argv, match, tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main([*argv, "-o", str(tmp_path / "out"), "-q"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert len(re.findall(match, err)) == 1, err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("duration, match", [
    ("-1", r"duration = -1.0 s: expected the recording's length in seconds, a positive, finite number"),
    ("0", r"duration = 0.0 s: expected the recording's length in seconds"),
    ("nan", r"duration = nan s: expected the recording's length in seconds"),
    ("1e7", r"duration = 1e\+07 s at rate = 200 Hz is 2e\+09 samples, above the bound of 1,000,000 samples "
            r"\(the simulator holds the whole recording in memory: about 2e\+04 GB here, 10 kB a sample\); "
            r"expected at most 5000 s at this rate: shorten the duration"),
])
def test_simulate_duration_is_checked_before_work(duration, match, tmp_path, capsys):
    """One line, exit status 1, nothing written: the scenario refuses the override on assignment."""
    out = tmp_path / "rec"
    assert main(["simulate", "stand", "--duration", duration, "-o", str(out), "-q"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("flexforce simulate: error: scenario stand: ")
    assert re.search(match, err), err
    assert not out.exists() or not any(out.iterdir())


# ----------------------------------------------------------------------------------------------
# scenario files: the timing fields
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("line, match", [
    ('duration = "five"', r"scenario s: duration = 'five' s: expected the recording's length in seconds, "
                          r"a positive, finite number"),
    ("duration = -1.0", r"scenario s: duration = -1.0 s: expected"),
    ("duration = true", r"scenario s: duration = True s: expected"),
    ('rate = "200"', r"scenario s: rate = '200' Hz: expected the recording's sampling rate in Hz"),
    ("sim_rate = 0.0", r"scenario s: sim_rate = 0.0 Hz: expected the integration rate in Hz"),
    ('seed = "one"', r"scenario s: seed = 'one': expected a noise seed, a whole number >= 0"),
    ("seed = -3", r"scenario s: seed = -3: expected a noise seed"),
    ("seed = 1.5", r"scenario s: seed = 1.5: expected a noise seed"),
    ("duration = 1e6", r"scenario s: duration = 1e\+06 s at rate = 200 Hz is 2e\+08 samples, above the bound"),
])
def test_scenario_toml_timing_is_checked(line, match, tmp_path):
    path = tmp_path / "s.toml"
    path.write_text(f'name = "s"\n{line}\n')
    with pytest.raises(ConfigError, match=match):
        Scenario.load(path)


def test_scenario_size_bound_counts_the_rate(tmp_path):
    """The bound is on samples: a long recording at a low rate is fine, the same at a high rate not."""
    path = tmp_path / "s.toml"
    path.write_text(f'name = "s"\nduration = {MAX_SAMPLES / 100.0}\nrate = 100.0\nsim_rate = 1000.0\n')
    sc = Scenario.load(path)
    assert sc.duration * sc.rate == MAX_SAMPLES
    with pytest.raises(ConfigError, match=r"expected at most 5000 s at this rate"):
        sc.rate = 200.0
    good = Scenario.load("stand")
    good.duration, good.seed = 2, np.int64(4)  # whole numbers of seconds, numpy seeds: accepted as given
    assert good.duration == 2 and good.seed == 4


# ----------------------------------------------------------------------------------------------
# robot configurations: grid rate and IMU ranges
# ----------------------------------------------------------------------------------------------


def _robot(tmp_path: Path, extra: str) -> Path:
    path = tmp_path / "robot.toml"
    path.write_text(ROMEO.read_text() + "\n" + extra + "\n")
    return path


@pytest.mark.parametrize("extra, match", [
    ("[ros]\nrate = 1e6", r"ros.rate = 1000000.0 Hz; expected a grid rate between 10 Hz and 10000 Hz"),
    ("[ros]\nrate = 2.0", r"ros.rate = 2.0 Hz; expected a grid rate between 10 Hz and 10000 Hz"),
    ('[ros]\nrate = "fast"', r"ros.rate = 'fast' Hz; expected a grid rate"),
    ("[imu_noise]\naccel_range = 5.0", r"imu_noise.accel_range = 5.0 m/s\^2; expected a full scale above gravity "
                                       r"\(9.8\d* m/s\^2\): an accelerometer at rest reads g"),
    ("[imu_noise]\ngyro_range = 0.0", r"imu_noise.gyro_range = 0.0 rad/s; expected the sensor's positive full scale "
                                      r"\(a reading at or beyond it is saturated"),
    ("[imu_noise]\ngyro_range = -1.0", r"imu_noise.gyro_range = -1.0 rad/s; expected the sensor's positive"),
])
def test_robot_config_rates_and_ranges_are_checked(extra, match, tmp_path):
    path = _robot(tmp_path, extra)
    with pytest.raises(ConfigError, match=match) as exc:
        RobotConfig.load(path)
    assert str(path) in str(exc.value)


def test_robot_config_sane_rates_and_ranges_load(tmp_path):
    cfg = RobotConfig.load(_robot(tmp_path, "[ros]\nrate = 1000.0\n[imu_noise]\naccel_range = 20.0\n"
                                            "gyro_range = inf"))
    assert cfg.ros.rate == 1000.0 and cfg.imu_noise.accel_range == 20.0
    text = ROMEO.read_text().replace('name = "romeo"', 'name = "romeo"\ngravity = 1.62', 1)
    (tmp_path / "moon.toml").write_text(text + "\n[imu_noise]\naccel_range = 5.0\n")
    moon = RobotConfig.load(tmp_path / "moon.toml")  # the bound is the configuration's own gravity
    assert moon.gravity == 1.62 and moon.imu_noise.accel_range == 5.0


# ----------------------------------------------------------------------------------------------
# recordings: time stamps in integer nanoseconds
# ----------------------------------------------------------------------------------------------


def _recording(n: int = 20) -> Recording:
    rng = np.random.default_rng(0)
    eye = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    return Recording.from_arrays(
        np.arange(n, dtype=np.int64) * 5_000_000, robot="r", contact_names=("a",), mass=10.0,
        com=rng.normal(size=(n, 3)), com_vel=np.zeros((n, 3)), com_acc=np.zeros((n, 3)), inertia=eye,
        inertia_dot=np.zeros((n, 3, 3)), sigma=np.zeros((n, 3)), sigma_dot=np.zeros((n, 3)), imu_R=eye,
        imu_p=np.zeros((n, 3)), imu_v=np.zeros((n, 3)), imu_a=np.zeros((n, 3)), imu_w=np.zeros((n, 3)),
        contact_active=np.ones((n, 1), dtype=bool), contact_p=np.zeros((n, 1, 3)),
        contact_R=eye[:, None], gyro=np.zeros((n, 3)), accel=rng.normal(size=(n, 3)))


def test_validate_refuses_float_seconds():
    """A Recording built field by field with float seconds (dt would read 5e-12 s) is refused by
    validate(), which the estimators call, with the same message as from_arrays."""
    rec = _recording()
    bad = dataclasses.replace(rec, t_ns=rec.time)
    assert bad.dt == pytest.approx(5e-12)
    with pytest.raises(DataError, match=r"t_ns has dtype float64, values 0 to 0.095; expected integer "
                                        r"nanoseconds \(int64\), e.g. np.round\(t_seconds \* 1e9\)"):
        bad.validate()
    with pytest.raises(DataError, match=r"t_ns has dtype float64"):
        Recording.from_arrays(rec.time, robot=rec.robot, contact_names=rec.contact_names, mass=rec.mass,
                              **_arrays(rec))


def test_validate_refuses_integer_seconds_and_milliseconds():
    rec = _recording()
    with pytest.raises(DataError, match=r"t_ns steps by 5 ns \(median\), a rate of 2e\+08 Hz: these look like "
                                        r"seconds, milliseconds or microseconds; expected integer nanoseconds"):
        dataclasses.replace(rec, t_ns=np.arange(rec.n, dtype=np.int64) * 5).validate()
    assert rec.validate() is rec


def _arrays(rec: Recording) -> dict:
    names = ("com", "com_vel", "com_acc", "inertia", "inertia_dot", "sigma", "sigma_dot", "imu_R", "imu_p",
             "imu_v", "imu_a", "imu_w", "contact_active", "contact_p", "contact_R", "gyro", "accel")
    return {k: getattr(rec, k) for k in names}
