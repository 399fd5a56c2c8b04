"""Inputs that are wrong but look right are refused with one error naming the value, its unit and
what was expected (issue 42): command-line counts and seeds, a scenario's timing fields (in its
TOML file and as overrides), a robot configuration's grid rate and IMU ranges, and time stamps in
seconds instead of integer nanoseconds."""

from __future__ import annotations

import dataclasses
import re
import warnings
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


# ----------------------------------------------------------------------------------------------
# sensor faults recognised from the data: clipping, units, stuck and missing sensors
# ----------------------------------------------------------------------------------------------


def _live(n: int = 400, seed: int = 0) -> Recording:
    """4 s at 100 Hz of a swaying robot: noisy IMU readings (the gyrometer follows the joint
    kinematics' rotation rate), force-only F/T sensors on two feet (torques NaN, as iCub's)."""
    rng = np.random.default_rng(seed)
    s = np.arange(n) * 0.01
    eye = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    imu_w = np.stack([0.6 * np.sin(2 * s), 0.4 * np.cos(3 * s), 0.3 * np.sin(s)], axis=1)
    accel = np.stack([2.0 * np.sin(2 * s), 1.0 * np.cos(s), 9.81 + 0.5 * np.sin(5 * s)], axis=1)
    ft = np.full((n, 2, 6), np.nan)
    ft[:, :, :3] = np.stack([200.0 + 20.0 * np.sin(s + 1.0), 150.0 - 20.0 * np.sin(s)], axis=1)[:, :, None]
    ft[:, :, :3] += rng.normal(scale=2.0, size=(n, 2, 3))
    return Recording.from_arrays(
        np.arange(n, dtype=np.int64) * 10_000_000, robot="r", contact_names=("left_foot", "right_foot"), mass=30.0,
        com=np.zeros((n, 3)), com_vel=np.zeros((n, 3)), com_acc=np.zeros((n, 3)), inertia=eye,
        inertia_dot=np.zeros((n, 3, 3)), sigma=np.zeros((n, 3)), sigma_dot=np.zeros((n, 3)), imu_R=eye,
        imu_p=np.zeros((n, 3)), imu_v=np.zeros((n, 3)), imu_a=np.zeros((n, 3)), imu_w=imu_w,
        contact_active=np.ones((n, 2), dtype=bool), contact_p=np.zeros((n, 2, 3)),
        contact_R=np.broadcast_to(np.eye(3), (n, 2, 3, 3)).copy(),
        gyro=imu_w + rng.normal(scale=0.005, size=(n, 3)), accel=accel + rng.normal(scale=0.02, size=(n, 3)), ft=ft)


def _kinds(findings) -> list[tuple[str, str]]:
    return [(f.sensor, f.kind) for f in findings]


def test_sensor_check_finds_nothing_on_live_data():
    from flexforce.datasets.sensorcheck import check_recording, screen

    rec = _live()
    assert check_recording(rec) == []
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert screen(rec) is rec
    assert "sensor_faults" not in rec.meta


@pytest.mark.parametrize("name, axis, limit", [("accel", 0, 1.5), ("gyro", 0, 0.3), ("gyro", 2, 0.2)])
def test_clipped_imu_is_recognised_from_its_flat_tops(name, axis, limit):
    from flexforce.datasets.sensorcheck import check_recording

    rec = _live()
    getattr(rec, name)[:, axis] = np.clip(getattr(rec, name)[:, axis], -limit, limit)
    found = [f for f in check_recording(rec) if f.kind == "clipped"]
    assert {f.sensor for f in found} == {name} and len(found) == 2  # both sides
    top = next(f for f in found if f"at {limit:g} " in f.detail)
    assert f"axis {'xyz'[axis]}" in top.detail and f"imu_noise.{name}_range = {limit:g}" in top.effect
    at = np.flatnonzero(getattr(rec, name)[:, axis] == limit)
    assert top.t0 == pytest.approx(rec.time[at[0]]) and top.t1 == pytest.approx(rec.time[at[-1]])
    assert "clipped from t = " in top.message() and "effect: " in top.message()


def test_a_signal_cut_while_dwelling_near_its_range_is_clipped():
    """A walk's accelerometer axis that lives near its full scale and is resampled onto the grid:
    the samples interpolated between a flat top and its neighbours, and the signal's own time
    near the limit, fill the band just inside the top (as many as at it, on the iCub walk cut at
    -8 m/s^2: 204 at the top, 270 within 1 % of the span); its many separate flat tops still make
    it clipped.  The same signal uncut is not."""
    from flexforce.datasets.sensorcheck import check_recording

    rec = _live()
    s = rec.time
    rng = np.random.default_rng(4)
    y = -7.9 - 0.12 * np.sin(7.0 * s) + rng.normal(scale=0.04, size=s.size) + 2.0 * (np.sin(0.9 * s) > 0.9)
    rec.accel[:, 1] = y
    assert [f for f in check_recording(rec) if f.kind == "clipped"] == []
    cut = np.clip(y, -8.0, None)
    rec.accel[:, 1] = np.interp(s + 0.3 * rec.dt, s, cut)  # resampled a third of a period later
    rec.accel[-1, 1] = cut[-1]
    at = np.abs(rec.accel[:, 1] + 8.0) <= 1e-9
    near = ~at & (rec.accel[:, 1] + 8.0 <= 0.05 * np.ptp(rec.accel[:, 1]))
    assert near.sum() >= at.sum()  # the band test alone would take it for a turn
    (found,) = [f for f in check_recording(rec) if f.kind == "clipped"]
    assert found.sensor == "accel" and found.channel == "axis y" and "at -8 m/s^2" in found.detail


def test_an_axis_constant_to_rounding_is_not_clipping():
    """A noise-free simulation at rest: the accelerometer's z sits at its extreme throughout, varying
    by 1e-13 m/s^2 only (rounding): constant, not clipped."""
    from flexforce.datasets.sensorcheck import check_recording

    rec = _live()
    rng = np.random.default_rng(1)
    rec.accel[:] = np.array([-0.1287, 3.4e-4, 9.80915]) + 1e-13 * rng.standard_normal(rec.accel.shape)
    assert [f for f in check_recording(rec) if f.kind == "clipped"] == []


def test_quantised_extremes_are_not_clipping():
    """A coarsely quantised axis repeats its extreme value without being clipped."""
    from flexforce.datasets.sensorcheck import check_recording

    rec = _live()
    rec.gyro[:] = np.round(rec.gyro / 0.1) * 0.1
    assert [f for f in check_recording(rec) if f.kind == "clipped"] == []


@pytest.mark.parametrize("scale, match", [
    (1 / 9.81, r"accel units from t = 0.000 s to 3.990 s: the accelerometer's norm has a median of 1.0\d* over the "
               r"recording against gravity 9.81 m/s\^2: the readings are in g; expected m/s\^2"),
    (1000 / 9.81, r"median of 1\d{3}.* times gravity .*not in m/s\^2 \(mg\? cm/s\^2\?\)"),
])
def test_accelerometer_in_g_or_mg_is_refused(scale, match):
    from flexforce.datasets.sensorcheck import screen

    rec = _live()
    rec.accel *= scale
    with pytest.raises(DataError, match=match) as exc:
        screen(rec, where="walk.mcap")
    assert str(exc.value).startswith("walk.mcap: ")


def test_accelerometer_off_gravity_is_a_warning():
    from flexforce.datasets.sensorcheck import SensorFaultWarning, screen

    rec = _live()
    rec.accel *= 0.8
    with pytest.warns(SensorFaultWarning, match=r"accel units .*median of 7.9\d* m/s\^2 .*\(-19 %\).*effect: "):
        screen(rec)
    assert [f["kind"] for f in rec.meta["sensor_faults"]] == ["units"]


def test_gyrometer_in_degrees_is_recognised_against_the_kinematics():
    """Following the joint kinematics at 57 times their rate: deg/s, refused (as an accelerometer in
    g); without kinematics to compare with, a median rate no robot reaches: a warning."""
    from flexforce.datasets.sensorcheck import check_recording, screen

    rec = _live()
    rec.gyro = np.degrees(rec.gyro)
    (found,) = check_recording(rec)
    assert (found.sensor, found.kind, found.severity) == ("gyro", "units", "error")
    assert re.search(r"reads 5\d.\d times the rotation rate of the joint kinematics .*are in deg/s", found.detail)
    with pytest.raises(DataError, match=r"gyro units .* are in deg/s \(57.3\); expected rad/s .* refused"):
        screen(rec)
    # without joint kinematics (a rigid IMU mount), a median rate no walking robot reaches
    rec.imu_w[:] = 0.0
    (found,) = check_recording(rec)
    assert "median of" in found.detail and "deg/s?" in found.detail
    rec.gyro = np.radians(rec.gyro)
    assert check_recording(rec) == []


@pytest.mark.parametrize("name, perm, sign, match", [
    ("accel", [2, 1, 0], 1.0, r"accel axes .* mean reading \(\(9.8\d, .*\) is 8\d deg from the specific force"),
    ("gyro", [1, 0, 2], -1.0, r"gyro axes .* x axis follows the joint kinematics' rotation rate about -y"),
])
def test_swapped_imu_axes_are_refused(name, perm, sign, match):
    """Readings in another frame than the configuration's IMU frame: the accelerometer's gravity
    along another axis than the kinematics put it, a gyro axis following another kinematic axis
    (a swap with a sign flip was 195 N off on the iCub walk, silently)."""
    from flexforce.datasets.sensorcheck import check_recording, screen

    rec = _live()
    y = getattr(rec, name)
    swapped = y[:, perm].copy()
    swapped[:, 0] *= sign
    setattr(rec, name, swapped)
    found = [f for f in check_recording(rec) if f.kind == "axes"]
    assert len(found) == 1 and found[0].sensor == name and found[0].severity == "error"
    with pytest.raises(DataError, match=match):
        screen(rec)


def test_a_motion_capture_gap_is_reported():
    """A body's pose missing for 0.5 s: one finding with its span (the tilt against it left those
    samples out silently)."""
    from flexforce.datasets.sensorcheck import check_recording

    rec = _live()
    pose = np.tile([0.0, 0.0, 0.6, 0.0, 0.0, 0.0, 1.0], (rec.n, 1))
    pose[100:150] = np.nan
    rec.mocap["torso"] = pose
    (found,) = [f for f in check_recording(rec) if f.sensor.startswith("mocap/")]
    assert (found.sensor, found.kind) == ("mocap/torso", "missing")
    assert found.t0 == pytest.approx(rec.time[100]) and found.t1 == pytest.approx(rec.time[149])
    pose[100:150] = 0.0
    pose[100:105, 2] = np.nan  # 50 ms: below the reported length
    assert [f for f in check_recording(rec) if f.sensor.startswith("mocap/")] == []


def test_one_gyro_axis_in_degrees_is_refused_naming_it():
    """One axis in deg/s, the others in rad/s: refused naming the axis (the whole gyro looked like
    deg/s, or its samples beyond the range read as missing)."""
    from flexforce.datasets.sensorcheck import check_recording

    rec = _live()
    rec.gyro[:, 0] = np.degrees(rec.gyro[:, 0])
    (found,) = [f for f in check_recording(rec) if f.kind == "units"]
    assert found.severity == "error" and found.channel == "axis x"
    assert re.search(r"axis x \(5\d\.?\d* times, correlation [01]\.\d\d\) reads .* in deg/s .* while axis y, z",
                     found.detail)


def test_stuck_sensors_are_reported_with_their_span():
    from flexforce.datasets.sensorcheck import STUCK_MIN_S, check_recording

    rec = _live()
    rec.ft[100:, :, 2] = rec.ft[100, :, 2]  # both feet frozen from t = 1 s
    rec.accel[50:70, 1] = rec.accel[50, 1]  # 0.2 s: a network hold, not reported
    found = check_recording(rec, topics={"ft/left_foot": "/lf/wrench"})
    assert _kinds(found) == [("ft/left_foot (/lf/wrench)", "stuck"), ("ft/right_foot", "stuck")]
    assert found[0].t0 == pytest.approx(1.0) and found[0].t1 == pytest.approx(3.99)
    assert "F_z is constant at" in found[0].detail and "contact states" in found[0].effect
    rec.accel[50:50 + int(STUCK_MIN_S / 0.01) + 1, 1] = rec.accel[50, 1]
    assert ("accel", "stuck") in _kinds(check_recording(rec))
    rec.meta["noise"] = False  # a noise-free simulation may be exactly constant
    assert check_recording(rec) == []


def test_missing_ft_is_reported_per_contact_and_span():
    from flexforce.datasets.sensorcheck import check_recording

    rec = _live()
    rec.ft[100:300] = np.nan  # both F/T sensors silent for 2 s
    rec.ft[350:352, 0] = np.nan  # 20 ms: below the reported span
    found = check_recording(rec)
    assert _kinds(found) == [("ft/left_foot", "missing"), ("ft/right_foot", "missing")]
    assert (found[0].t0, found[0].t1) == pytest.approx((1.0, 2.99))
    assert "200 samples (2.000 s)" in found[0].detail and "hold their last value" in found[0].effect


def test_window_keeps_and_shifts_the_fault_spans():
    from flexforce.datasets.sensorcheck import screen

    rec = _live()
    rec.ft[100:300] = np.nan
    with pytest.warns(RuntimeWarning, match="missing"):
        screen(rec)
    cut = rec.window(2.0, 3.5)
    assert [(f["t0"], f["t1"]) for f in cut.meta["sensor_faults"]] == [(0.0, 0.99), (0.0, 0.99)]
    assert rec.window(3.2, 3.9).meta["sensor_faults"] == []


def test_faults_reach_the_command_line_and_summary_json(tmp_path, capsys):
    """``flexforce run`` on a flexforce bag with a stuck F/T prints one warning naming the fault, its
    span and effect; a comparison writes it into summary.json's ``warnings``."""
    from flexforce import simulate
    from flexforce.compare.runner import compare
    from flexforce.datasets.io.bagio import save_recording
    from flexforce.pipeline import load_or_simulate

    rec = simulate("stand", duration=1.0, seed=1)
    rec.ft[60:, 0] = rec.ft[60, 0]
    bag = save_recording(rec, tmp_path / "stuck.mcap")
    assert main(["run", str(bag), "--estimator", "ekf", "-o", str(tmp_path / "est.npz"), "-q"]) == 0
    err = capsys.readouterr().err
    assert re.search(r"flexforce run: warning: .*stuck.mcap: ft/left_foot stuck from t = 0.300 s to 1.000 s: F_x is "
                     r"constant at .*; effect: the F/T reference is wrong there", err), err
    with pytest.warns(RuntimeWarning, match="stuck"):
        loaded = load_or_simulate(bag)
    comp = compare(loaded.window(0.1, None), estimators=("ekf",), baseline=False, peers=False, crb=False)
    kinds = {(w["sensor"], w["kind"], w["t0"]) for w in comp.summary()["warnings"]}
    assert ("ft/left_foot", "stuck", 0.2) in kinds


def test_importer_names_the_topic_and_refuses_g(tmp_path):
    """A raw bag: a frozen F/T topic is a warning naming the topic; an accelerometer in g is refused
    naming the bag."""
    from test_rosimport import ROS, UPPER, Motion, robot_topics, stamps, write_bag

    from flexforce.datasets.io.rosimport import import_bag
    from flexforce.datasets.robot import RobotModel
    from flexforce.datasets.sensorcheck import SensorFaultWarning

    model = RobotModel(dataclasses.replace(RobotConfig.load("romeo"), ros=ROS))
    t = stamps(n=160)
    forces = 200.0 + np.random.default_rng(2).normal(scale=2.0, size=(len(t), 2))
    forces[60:, 1] = forces[60, 1]
    topics = robot_topics(model, Motion(model, UPPER), t, forces=forces)
    with pytest.warns(SensorFaultWarning) as caught:
        rec = import_bag(write_bag(tmp_path / "stuck", "mcap", topics), model)
    assert [str(w.message).split(" from t")[0] for w in caught] == [f"{tmp_path / 'stuck'}: ft/right_foot (/rf/wrench) "
                                                                    "stuck"]
    assert rec.meta["sensor_faults"][0]["kind"] == "stuck"
    for _, f in topics["/imu"][1]:
        f["accel"] = f["accel"] / 9.81
    with pytest.raises(DataError, match=r"g: accel \(/imu\) units from t = 0.000 s .* the readings are in g"):
        import_bag(write_bag(tmp_path / "g", "mcap", topics), model)


def test_streamed_bag_is_checked_part_by_part(tmp_path):
    """The same raw bags streamed (0.5 s parts): the frozen F/T topic is warned about once, over
    the parts it spans, with the offline import's start; the accelerometer in g is refused."""
    from test_rosimport import ROS, UPPER, Motion, robot_topics, stamps, write_bag

    from flexforce.datasets.io.rosimport import import_bag
    from flexforce.datasets.io.stream import stream_bag
    from flexforce.datasets.robot import RobotModel
    from flexforce.datasets.sensorcheck import SensorFaultWarning, StreamScreen

    model = RobotModel(dataclasses.replace(RobotConfig.load("romeo"), ros=ROS))
    t = stamps(n=400)
    forces = 200.0 + np.random.default_rng(2).normal(scale=2.0, size=(len(t), 2))
    forces[60:, 1] = forces[60, 1]
    topics = robot_topics(model, Motion(model, UPPER), t, forces=forces)
    bag = write_bag(tmp_path / "stuck", "mcap", topics)
    with pytest.warns(SensorFaultWarning):
        offline = import_bag(bag, model).meta["sensor_faults"]
    with pytest.warns(SensorFaultWarning) as caught:
        parts = list(stream_bag(bag, model, part_seconds=0.5))
    assert len(parts) >= 3
    msgs = [str(w.message) for w in caught if issubclass(w.category, SensorFaultWarning)]
    # first seen while it lasts ("to at least"), then its whole span at the end of the stream
    assert [m.split(" from t")[0].split(", whole span")[0] for m in msgs] == \
        [f"{bag}: ft/right_foot (/rf/wrench) stuck"] * 2
    assert "to at least" in msgs[0] and "whole span" in msgs[1]
    (stuck,) = [f for f in offline if f["kind"] == "stuck"]
    start = float(re.search(r"from t = ([0-9.]+) s", msgs[0]).group(1))
    dt = parts[0].dt  # the streamed grid starts and steps as the offline one, within a period
    assert start == pytest.approx(stuck["t0"], abs=dt)
    span = re.search(r"from t = ([0-9.]+) s to ([0-9.]+) s", msgs[1])
    assert span is not None
    assert float(span.group(1)) == pytest.approx(stuck["t0"], abs=dt)
    assert float(span.group(2)) == pytest.approx(stuck["t1"], abs=dt)
    # the whole span, joined over the parts, in a checker's findings
    check = StreamScreen({"ft/right_foot": "/rf/wrench"})
    with pytest.warns(SensorFaultWarning):
        for part in stream_bag(bag, model, part_seconds=0.5):
            check(part)
    (found,) = check.findings
    assert found.kind == "stuck" and found.channel == "F_z"  # the topic carries the normal force only
    assert found.t0 == pytest.approx(stuck["t0"], abs=dt) and found.t1 == pytest.approx(stuck["t1"], abs=dt)
    # both F/T topics silent from 1 s to the end: a part wholly silent continues the gap (alone it
    # would look like a sensor not measured); the whole span as the offline import finds it
    silent = 200.0 + np.random.default_rng(3).normal(scale=2.0, size=(len(t), 2))
    silent[100:] = np.nan
    gap = write_bag(tmp_path / "silent", "mcap", robot_topics(model, Motion(model, UPPER), t, forces=silent))
    with pytest.warns(SensorFaultWarning):
        offline = import_bag(gap, model).meta["sensor_faults"]
    check = StreamScreen({"ft/left_foot": "/lf/wrench", "ft/right_foot": "/rf/wrench"})
    with pytest.warns(SensorFaultWarning):
        for part in stream_bag(gap, model, part_seconds=0.5):
            check(part)
    assert [(f.sensor, f.kind) for f in check.findings] == [(f["sensor"], "missing") for f in offline]
    for f, g in zip(check.findings, offline):
        assert f.t0 == pytest.approx(g["t0"], abs=dt) and f.t1 == pytest.approx(g["t1"], abs=dt)
    for _, f in topics["/imu"][1]:
        f["accel"] = f["accel"] / 9.81
    with pytest.raises(DataError, match=r"g: accel \(/imu\) units from t = 0.000 s .* the readings are in g"):
        list(stream_bag(write_bag(tmp_path / "g", "mcap", topics), model))


def _romeo_raw(n: int, forces=None, seed: int = 0, **ros_changes):
    """Romeo's raw topics as ``test_rosimport`` simulates them (the upper body moving): ``n`` IMU
    stamps, the feet's F/T reading ``forces`` ((n, 2) N; default 200 N with 2 N of noise drawn with
    ``seed``), the test ``[ros]`` table with ``ros_changes``.  Returns ``(model, stamps, topics)``."""
    from test_rosimport import ROS, UPPER, Motion, robot_topics, stamps

    from flexforce.datasets.robot import RobotModel

    model = RobotModel(dataclasses.replace(RobotConfig.load("romeo"), ros=dataclasses.replace(ROS, **ros_changes)))
    t = stamps(n=n)
    if forces is None:
        forces = 200.0 + np.random.default_rng(seed).normal(scale=2.0, size=(len(t), 2))
    return model, t, robot_topics(model, Motion(model, UPPER), t, forces=forces)


def _refused_both_ways(bag, model, error: type[Exception], pattern: str) -> None:
    """``bag`` is refused with ``error`` matching ``pattern``, imported offline and streamed."""
    from flexforce.datasets.io.rosimport import import_bag
    from flexforce.datasets.io.stream import stream_bag

    with pytest.raises(error, match=pattern):
        import_bag(bag, model)
    with pytest.raises(error, match=pattern):
        list(stream_bag(bag, model, part_seconds=0.5))


def test_streamed_clip_is_judged_before_the_imu_filter(tmp_path):
    """``ros.imu_filter = "savgol"`` rounds a flat top off: the streamed screen judges the readings
    as resampled, before the filter (``StreamImporter.raw_imu``), as the offline import does."""
    from test_rosimport import write_bag

    from flexforce.datasets.io.rosimport import import_bag
    from flexforce.datasets.io.stream import stream_bag
    from flexforce.datasets.sensorcheck import SensorFaultWarning, StreamScreen

    model, _, topics = _romeo_raw(400, seed=5, imu_filter="savgol")
    for i, (_, f) in enumerate(topics["/imu"][1]):  # a 4 Hz vibration, cut at 1 m/s^2 above gravity
        f["accel"] = np.array([f["accel"][0], f["accel"][1], f["accel"][2] + 2.0 * np.sin(0.25 * i)])
    limit = float(np.median([f["accel"][2] for _, f in topics["/imu"][1]])) + 1.0
    for _, f in topics["/imu"][1]:
        f["accel"][2] = min(f["accel"][2], limit)
    bag = write_bag(tmp_path / "clip", "mcap", topics)
    with pytest.warns(SensorFaultWarning):
        offline = import_bag(bag, model)
    assert [f["kind"] for f in offline.meta["sensor_faults"]] == ["clipped"]
    with pytest.warns(SensorFaultWarning) as caught:
        parts = list(stream_bag(bag, model, part_seconds=0.5))
    msgs = [str(w.message) for w in caught if issubclass(w.category, SensorFaultWarning)]
    assert msgs and all("accel (/imu) clipped" in m for m in msgs) and f"at {limit:.6g} m/s^2" in msgs[0]
    # the filtered parts alone do not show it: the filter rounded the flat tops off
    alone = StreamScreen({"accel": "/imu", "gyro": "/imu"})
    with warnings.catch_warnings():
        warnings.simplefilter("error", SensorFaultWarning)
        for part in parts:
            alone(part)
    assert alone.findings == []


def test_a_stream_without_a_first_contact_names_its_ft_topics(tmp_path):
    """Both F/T topics without a finite reading: the streamed import names them and what they
    read (the smoother's "no contact is active at the first sample" said neither)."""
    from test_rosimport import write_bag

    from flexforce.datasets.io.stream import stream_bag

    model, _, topics = _romeo_raw(200, forces=np.full((200, 2), np.nan))
    bag = write_bag(tmp_path / "nan", "mcap", topics)
    pattern = (r"no contact is in force at the stream's first sample.*left_foot \(/lf/wrench\): "
               r"no finite normal force in the first \d+ samples.*contacts='fixed'")
    with pytest.raises(DataError, match=pattern):
        list(stream_bag(bag, model, part_seconds=0.5))


def test_a_savgol_window_too_short_for_the_grid_is_refused(tmp_path):
    """``savgol_window`` shorter than the polynomial needs on the bag's grid: refused, offline and
    streamed (it was widened silently to ``order + 2`` samples)."""
    from test_rosimport import write_bag


    model, _, topics = _romeo_raw(200, seed=6, savgol_window=0.001)
    bag = write_bag(tmp_path / "b", "mcap", topics)
    _refused_both_ways(bag, model, ConfigError,
                       r"ros.savgol_window = 0.001 s is 1 sample\(s\) on this .* Hz grid; expected at least 5 samples")


def test_joint_stamps_on_another_clock_are_refused(tmp_path):
    """Joint states stamped 10 s after the IMU (another clock; logged together): offline, their
    short overlap is refused; streamed, their stamps against the log time (they were paired 10 s
    apart, exit 0)."""
    from test_rosimport import write_bag

    from flexforce.datasets.io.rosimport import import_bag
    from flexforce.datasets.io.stream import stream_bag

    model, _, topics = _romeo_raw(400, seed=7)
    msgtype, msgs = topics["/joint_states"]
    topics["/joint_states"] = (msgtype, [(s + 3_000_000_000, {**f, "log": s}) for s, f in msgs])
    bag = write_bag(tmp_path / "clock", "mcap", topics)
    with pytest.raises(DataError, match=r"topics /imu and /joint_states overlap [0-9.]+ s only .* clocks look "
                                        r"\+3.000 s apart; expected simultaneous logs"):
        import_bag(bag, model)
    with pytest.raises(DataError, match=r"the header stamps of /joint_states run \+3.000 s from those of /imu .* "
                                        r"two clocks"):
        list(stream_bag(bag, model, part_seconds=0.5))


def test_a_span_without_a_contact_in_force_is_refused(tmp_path):
    """Both feet unloaded for longer than a flight (a contact missing from the configuration, a
    threshold too high): refused, naming the span, offline and streamed (the EKF ended in "the
    predicted state covariance is not positive definite")."""
    from test_rosimport import stamps, write_bag

    from flexforce.datasets.io.rosimport import AIRBORNE_MAX_S, import_bag

    t = stamps(n=400)
    forces = 200.0 + np.random.default_rng(8).normal(scale=2.0, size=(len(t), 2))
    dt = float(np.median(np.diff(t))) * 1e-9
    off = int(np.ceil(2 * AIRBORNE_MAX_S / dt))
    forces[150:150 + off] = 1.0
    model, _, topics = _romeo_raw(400, forces=forces)
    bag = write_bag(tmp_path / "air", "mcap", topics)
    _refused_both_ways(bag, model, DataError,
                       r"no configured contact \(left_foot, right_foot\) is in force in .* from t = 1\.[45]\d\d s")
    forces[150 + off // 4:150 + off] = 200.0  # a quarter of it: within a flight's length
    short = write_bag(tmp_path / "hop", "mcap", _romeo_raw(400, forces=forces)[2])
    assert (~import_bag(short, model).contact_active.any(axis=1)).sum() > 0


def test_ft_topics_that_never_read_are_missing(tmp_path):
    """With ``contacts="fixed"`` the F/T are only a reference: topics in the bag that never read a
    number are reported missing over the whole recording, offline and at the end of a stream (they
    were silent: no force reference, a result 118 N off on the iCub walk against the real F/T)."""
    from test_rosimport import write_bag

    from flexforce.datasets.io.rosimport import import_bag
    from flexforce.datasets.io.stream import stream_bag
    from flexforce.datasets.sensorcheck import SensorFaultWarning

    model, _, topics = _romeo_raw(300, forces=np.full((300, 2), np.nan))
    bag = write_bag(tmp_path / "nanft", "mcap", topics)
    pattern = r"ft/left_foot \(/lf/wrench\) missing from t = 0.000 s .*no finite, nonzero reading in the whole"
    with pytest.warns(SensorFaultWarning, match=pattern):
        import_bag(bag, model, contacts="fixed")
    with pytest.warns(SensorFaultWarning, match=pattern):
        list(stream_bag(bag, model, contacts="fixed", part_seconds=0.5))


def test_an_imu_ending_early_is_warned_about(tmp_path):
    """The IMU stopping 1 s before the joint states: the recording is their common span, and the
    samples left out are named (they were cut silently)."""
    from test_rosimport import write_bag

    from flexforce.datasets.io.rosimport import import_bag
    from flexforce.datasets.io.stream import stream_bag
    from flexforce.datasets.sensorcheck import SensorFaultWarning

    model, t, topics = _romeo_raw(400, seed=9)
    msgtype, msgs = topics["/imu"]
    topics["/imu"] = (msgtype, [m for m in msgs if m[0] <= t[-1] - 1_000_000_000])
    bag = write_bag(tmp_path / "short", "mcap", topics)
    with pytest.warns(SensorFaultWarning, match=r"topic /joint_states runs 1.0\d\d s after topic /imu ends"):
        rec = import_bag(bag, model)
    assert rec.time[-1] < (t[-1] - t[0]) * 1e-9 - 0.9
    with pytest.warns(SensorFaultWarning, match=r"topic /joint_states runs 1.0\d\d s after topic /imu ends"):
        list(stream_bag(bag, model, part_seconds=0.5))


def test_real_icub_logs_raise_no_sensor_fault():
    """The shipped iCub recordings (irregular stamps, 0.17 s network gaps, held values) are clean."""
    from conftest import ICUB_DIR

    from flexforce.datasets.io.rosimport import import_bag

    bags = [ICUB_DIR / "icub-walk-12s", ICUB_DIR / "icub-com-sinusoid-20s.bag"]
    if not all(b.exists() for b in bags):
        pytest.skip("iCub recordings not available")
    for bag in bags:
        with warnings.catch_warnings():
            warnings.simplefilter("error", RuntimeWarning)
            rec = import_bag(bag, "icub-identified")
        assert "sensor_faults" not in rec.meta


# ----------------------------------------------------------------------------------------------
# effect plugins: validated when loaded, their file named in every error
# ----------------------------------------------------------------------------------------------

_NAN_PLUGIN = '''
import numpy as np


class NanBias:
    name = "nan-bias"
    dim = 3
    labels = ("b_x [rad/s]", "b_y [rad/s]", "b_z [rad/s]")

    def prior(self, problem):
        return np.full(3, {mean}), np.full(3, 0.1)

    def random_walk_sigma(self, problem):
        return np.full(3, 1e-8)

    def residual_terms(self, family, problem, steps, R, q, W, e):
        if family != "imu":
            return None
        n = len(steps)
        dr = np.zeros((n, 6))
        dr[:, :3] = e * {scale}
        return dr, np.zeros((n, 6, 18)), np.zeros((n, 6, 3))

    def report(self, values, cov):
        return {{"value": values[-1].tolist(), "summary": "nan bias"}}
'''


@pytest.mark.parametrize("name, text, match", [
    ("effects.txt", "x = 1\n", r"effect plugin {path} is not a Python file \(suffix '.txt'\); expected a .py file"),
    ("effects", "x = 1\n", r"effect plugin {path} is not a Python file \(suffix 'none'\)"),
    ("broken.py", "raise ValueError('bad constant')\n", r"cannot load effect plugin {path}: ValueError: bad constant"),
    ("exits.py", "import sys\nsys.exit(3)\n", r"cannot load effect plugin {path}: SystemExit: 3"),
    ("syntax.py", "def f(:\n", r"cannot load effect plugin {path}: SyntaxError"),
    ("listed.py", "EFFECTS = [42]\n", r"effect plugin {path}: EFFECTS entry 42 does not implement the Effect protocol"),
    ("empty.py", "x = 1\n", r"effect plugin {path} defines no Effect"),
    ("clash.py", "from flexforce.factors.effects import GyroBias\n\nclass Mine(GyroBias):\n    pass\n\n"
                 "EFFECTS = [Mine]\n",
     r"effect plugin {path} defines effect 'gyro-bias', the name of a built-in effect; expected another name"),
])
def test_plugin_errors_name_the_file(name, text, match, tmp_path):
    from flexforce.compare.diagnostics.candidates import load_plugin

    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(ConfigError, match=match.format(path=re.escape(str(path)))):
        load_plugin(path)


def test_plugin_effect_returning_nan_fails_naming_file_and_effect(tmp_path):
    from flexforce.compare.diagnostics.candidates import effect_factory, load_plugin
    from flexforce.factors.effects import Effect

    good = tmp_path / "good.py"
    good.write_text(_NAN_PLUGIN.format(mean="0.0", scale="1.0"))
    (eff,) = load_plugin(good)
    assert isinstance(eff, Effect) and effect_factory(eff)[0] == "nan-bias" and eff.dim == 3
    mean, sigma = eff.prior(None)
    assert np.array_equal(mean, np.zeros(3))
    e = np.ones((2, 3))
    assert eff.residual_terms("imu", None, np.arange(2), None, None, None, e)[0][0, 0] == 1.0
    assert eff.residual_terms("contact", None, np.arange(2), None, None, None, e) is None

    bad = tmp_path / "nan.py"
    bad.write_text(_NAN_PLUGIN.format(mean="np.nan", scale="np.nan"))
    (eff,) = load_plugin(bad)
    with pytest.raises(ConfigError, match=rf"effect plugin {re.escape(str(bad))}: effect 'nan-bias' prior\(\) returned "
                                          r"mean with 3 of 3 value\(s\) NaN or inf; expected finite numbers"):
        eff.prior(None)
    with pytest.raises(ConfigError, match=r"effect 'nan-bias' residual_terms\('imu'\) returned dr with 6 of 12"):
        eff.residual_terms("imu", None, np.arange(2), None, None, None, e)


# ----------------------------------------------------------------------------------------------
# robot configurations and scenarios: every number within sane bounds, the file and key named
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("old, new, match", [
    ("k_fs = 28000.0", "k_fs = 1e30", r"stiffness.k_fs = 1e\+30 N/m; expected a stiffness of at most 1e\+09 N/m"),
    ("k_fs = 28000.0", "k_fs = 0.0", r"stiffness.k_fs = 0.0 N/m; expected a positive, finite stiffness"),
    ("k_fs = 28000.0", "k_fs = [1e4, 1e4, 1e12]",
     r"stiffness.k_fs = \[10000.0, 10000.0, 1000000000000.0\] N/m; expected a stiffness of at most"),
    ("k_fd = 420.0", "k_fd = -1.0", r"stiffness.k_fd = -1.0 N s/m; expected a positive, finite damping"),
    ("k_td = 8.0", "k_td = 1e9", r"stiffness.k_td = 1000000000.0 N m s/rad; expected a damping of at most"),
])
def test_robot_stiffness_bounds(old, new, match, tmp_path):
    text = ROMEO.read_text()
    assert old in text
    path = tmp_path / "robot.toml"
    path.write_text(text.replace(old, new, 1))
    with pytest.raises(ConfigError, match=match) as exc:
        RobotConfig.load(path)
    assert str(path) in str(exc.value)


@pytest.mark.parametrize("extra, match", [
    ('[ros]\nsavgol_window = "wide"', r"ros.savgol_window = 'wide' s; expected a duration, a finite number"),
    ("[ros]\nsavgol_order = 2.5", r"ros.savgol_order = 2.5; expected a whole number >= 2"),
    ("[ros]\nsavgol_order = 50", r"ros.savgol_order = 50 from 2 to 7 \(a polynomial .* ill-conditioned"),
    ('[ros]\nmax_gap = "long"', r"ros.max_gap = 'long' s; expected a duration"),
    ("[ros]\ncontact_on = true", r"ros.contact_on = True N; expected a normal force"),
    ("[ros]\nimu_topic = 3", r"ros.imu_topic = 3; expected a topic name"),
    ("[ros]\nft_topics = 3", r"ros.ft_topics = 3; expected a table of name = \"/topic\" entries"),
])
def test_robot_ros_numbers_are_checked(extra, match, tmp_path):
    path = _robot(tmp_path, extra)
    with pytest.raises(ConfigError, match=match) as exc:
        RobotConfig.load(path)
    assert str(path) in str(exc.value)


def _edited(tmp_path: Path, edit) -> Path:
    path = tmp_path / "robot.toml"
    path.write_text(edit(ROMEO.read_text()))
    return path


def _top(line: str):
    """Insert ``line`` among the top-level keys (before the first table)."""
    return lambda text: text.replace("\n[", f"\n{line}\n[", 1)


@pytest.mark.parametrize("edit, match", [
    (_top("ros = 3"), r"ros = 3 in robot configuration .*; expected a \[ros\] table"),
    (_top("footholds = 3"), r"footholds = 3 in robot configuration .*; expected a \[footholds\] table"),
    (lambda t: re.sub(r"(?s)contacts = \[.*?\n\]", 'contacts = "feet"', t, count=1),
     r"contacts = 'feet' in robot configuration .*; expected a list of contact tables"),
    (lambda t: t.replace('name = "right_foot"', 'name = "left_foot"'),
     r"contacts\[1\] repeats the contact name 'left_foot' in robot configuration .*; expected distinct names"),
    (lambda t: t.replace('name = "right_foot"', 'name = 3'), r"contacts\[1\] = \{.*\} in robot configuration .*; "
                                                             r"expected a table with a name and a frame "
                                                             r"\(non-empty strings\) and optionally a sole"),
])
def test_robot_structure_is_checked(edit, match, tmp_path):
    path = _edited(tmp_path, edit)
    with pytest.raises(ConfigError, match=match):
        RobotConfig.load(path)


def test_builtin_robots_are_within_the_bounds():
    for name in ("romeo", "talos", "icub", "icub-identified"):
        RobotConfig.load(name)


@pytest.mark.parametrize("line, match", [
    ("sim_rate = 1e6", r"scenario s: sim_rate = 1000000.0 Hz: expected the integration rate in Hz, at most 50000 Hz"),
    ("rate = 1e5", r"scenario s: rate = 100000.0 Hz: expected the recording's sampling rate in Hz, at most 10000 Hz"),
])
def test_scenario_rates_have_an_upper_bound(line, match, tmp_path):
    path = tmp_path / "s.toml"
    path.write_text(f'name = "s"\nduration = 1.0\n{line}\n')
    with pytest.raises(ConfigError, match=match):
        Scenario.load(path)


def test_the_recordings_description_carries_its_sensor_faults():
    """describe(rec) -- the 'recording' of summary.json and diagnosis.json -- lists the faults the
    data showed, and nothing when there are none."""
    from flexforce.compare.runner import describe
    from flexforce.datasets.sensorcheck import check_recording

    rec = _live()
    assert "sensor_faults" not in describe(rec)
    rec.accel[:, 0] = np.clip(rec.accel[:, 0], -1.5, 1.5)
    rec.meta["sensor_faults"] = [f.to_dict() for f in check_recording(rec)]
    faults = describe(rec)["sensor_faults"]
    assert faults and {f["kind"] for f in faults} == {"clipped"} and all("effect" in f for f in faults)
