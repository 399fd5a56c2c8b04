"""Streaming: messages in time order to parts of a recording, parts to fixed-lag estimates.

The streamed path must give the offline one's answer: the parts joined are the offline import,
and the streamed estimates are the offline fixed-lag smoother's, whatever the part sizes (the
same window, factors and update order; only the memory differs).  The bounded memory is
asserted on the stream's own buffers; the peak RSS of an hour-long log is a benchmark
(benchmarks/stream_memory.py).
"""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import ICUB_DIR

from flexforce.datasets.io.rosimport import import_bag
from flexforce.datasets.io.stream import StreamImporter, stream_bag
from flexforce.datasets.recording import Recording, concat_recordings
from flexforce.datasets.robot import RobotConfig
from flexforce.datasets.sim.scenario import Scenario
from flexforce.datasets.sim.simulator import Simulator
from flexforce.errors import ConfigError, DataError
from flexforce.factors.effects import AccelBias
from flexforce.factors.model import ModelConfig
from flexforce.smoother import FixedLagConfig, run_fixed_lag
from flexforce.smoother.stream import FixedLagStream, run_stream

WALK = ICUB_DIR / "icub-walk-12s"
ROBOT = "icub-identified"
needs_icub = pytest.mark.skipif(not WALK.exists(), reason="iCub recordings not beside the checkout")

EXACT = 1e-9
"""Streamed against offline: the same floating-point operations in the same order (measured
difference 0.0); 1e-9 leaves room for a BLAS that splits a product differently by size."""


@pytest.fixture(scope="module")
def pitch():
    sc = Scenario.load("push-pitch")
    sc.duration = 3.0
    return Simulator(sc).run()


def _random_parts(rec: Recording, seed: int, largest: int = 80):
    rng = np.random.default_rng(seed)
    a = 0
    while a < rec.n:
        b = min(rec.n, a + int(rng.integers(1, largest)))
        yield rec.slice(a, b)
        a = b


def _joined(estimates):
    return {name: np.concatenate([getattr(e, name) for e in estimates]) for name in ("R", "t", "v", "wrench", "cov")}


@pytest.mark.parametrize("seed", [0, 1])
def test_stream_equals_offline_fixed_lag(pitch, seed):
    model = ModelConfig.from_recording(pitch)
    offline = run_fixed_lag(pitch, model)
    stream = FixedLagStream(model)
    ests = [e for e in (stream.push(p) for p in _random_parts(pitch, seed)) if e is not None]
    ests.append(stream.finish())
    got = _joined(ests)
    assert got["R"].shape == offline.R.shape
    for name, ref in (("R", offline.R), ("t", offline.t), ("v", offline.v), ("wrench", offline.wrench),
                      ("cov", offline.cov)):
        assert np.max(np.abs(got[name] - ref)) <= EXACT, name
    # steps leave in order, each once; times are absolute
    t_ns = np.concatenate([e.t_ns for e in ests])
    assert np.array_equal(t_ns, pitch.t_ns)
    # residuals of each part equal the offline ones (but the last integration factor of a part)
    a = 0
    for e in ests:
        ref = offline.residuals["imu"][a:a + e.n]
        assert np.nanmax(np.abs(e.residuals["imu"] - ref)) <= 1e-6
        a += e.n


@pytest.mark.parametrize("lag", [1.0, 0.13])
def test_blocked_marginals_equal_the_step_by_step_recursion(pitch, monkeypatch, lag):
    """The read-outs' covariances by block maps across the final steps equal the marginal
    recursion through every step of the window (the former computation) to rounding."""
    from flexforce.smoother import solvers
    from flexforce.smoother.fixed_lag import FixedLagSmoother

    model = ModelConfig.from_recording(pitch)
    fast = run_fixed_lag(pitch, model, lag=lag, report_every=7)

    def step_by_step(self, k, j0, j1):
        solvers.window_marginals(self.Ld, self.C, np.arange(k, j0 - 1, -1) % self.cap, self.Pw)
        self.last_cov_time = 0.0

    monkeypatch.setattr(FixedLagSmoother, "_covariances", step_by_step)
    ref = run_fixed_lag(pitch, model, lag=lag, report_every=7)
    assert np.array_equal(fast.wrench, ref.wrench)
    scale = np.abs(ref.cov).max(axis=(1, 2), keepdims=True)
    assert np.max(np.abs(fast.cov - ref.cov) / scale) <= 1e-11


@pytest.mark.parametrize("block", [4, 13])
def test_stream_in_blocks_equals_offline_in_blocks(pitch, block):
    """Several samples per update: the stream equals the offline smoother run the same way (the
    part boundaries fall anywhere in a block), and stays close to one update per sample."""
    model = ModelConfig.from_recording(pitch)
    config = FixedLagConfig(block=block)
    offline = run_fixed_lag(pitch, model, config)
    stream = FixedLagStream(model, config)
    ests = [e for e in (stream.push(p) for p in _random_parts(pitch, 5)) if e is not None]
    ests.append(stream.finish())
    got = _joined(ests)
    for name, ref in (("R", offline.R), ("t", offline.t), ("v", offline.v), ("wrench", offline.wrench),
                      ("cov", offline.cov)):
        assert np.max(np.abs(got[name] - ref)) <= EXACT, name
    stats = stream.update_stats
    assert stats["updates"] == -(-pitch.n // block) and stats["samples_per_update"] == block
    assert stream.samples_updated == pitch.n and len(stream.update_time) == 0  # reported: handed out
    assert sum(len(e.time_per_step) for e in ests) == pitch.n
    single = run_fixed_lag(pitch, model)
    assert np.max(np.abs(offline.wrench - single.wrench)) < 0.05 * np.max(np.abs(single.wrench))


def test_stream_with_an_effect_and_without_covariance(pitch):
    model = dataclasses.replace(ModelConfig.from_recording(pitch), effects=(AccelBias(),))
    offline = run_fixed_lag(pitch, model)
    stream = FixedLagStream(model, covariance=False)
    ests = [e for e in (stream.push(p) for p in _random_parts(pitch, 3)) if e is not None]
    ests.append(stream.finish())
    assert all(e.cov is None for e in ests)
    got = np.concatenate([e.wrench for e in ests])
    assert np.max(np.abs(got - offline.wrench)) <= EXACT
    assert all("accel-bias" in e.effects for e in ests)


def test_stream_memory_is_bounded(pitch):
    """The stream keeps the window and the steps not yet reported, however long it runs."""
    model = ModelConfig.from_recording(pitch)
    stream = FixedLagStream(model, FixedLagConfig(lag=0.5), covariance=False)
    size = 25
    kept = []
    for _ in range(6):  # the recording six times over (time shifted): 18 s
        for a in range(0, pitch.n, size):
            part = pitch.slice(a, min(a + size, pitch.n))
            shift = (stream.n - a) * 5_000_000 if stream.n else 0
            part.t_ns = part.t_ns + shift
            stream.push(part)
            kept.append(stream.segment.n)
    fls = stream.fls
    bound = fls.lag_steps + fls.M + fls.report_every + size + 2
    assert max(kept[len(kept) // 2:]) <= bound
    assert stream.n == 6 * pitch.n


def test_stream_refuses_what_it_cannot_stream(pitch):
    model = ModelConfig.from_recording(pitch)
    with pytest.raises(ConfigError, match="footholds"):
        FixedLagStream(model, FixedLagConfig(footholds=True))
    with pytest.raises(ConfigError, match="window"):
        FixedLagStream(model, FixedLagConfig(backend="gtsam"))
    stream = FixedLagStream(model)
    stream.push(pitch.slice(0, 40))
    with pytest.raises(DataError, match="not after the previous step"):
        stream.push(pitch.slice(30, 50))
    with pytest.raises(DataError, match="one period"):
        stream.push(pitch.slice(45, 60))


# ------------------------------------------------------------------------------------------------
# real bags
# ------------------------------------------------------------------------------------------------
def config_default_velocity() -> str:
    ros = RobotConfig.load(ROBOT).ros
    assert ros is not None
    return ros.joint_velocity


@pytest.fixture(scope="module")
def walk_offline():
    return import_bag(WALK, ROBOT)


@needs_icub
@pytest.mark.parametrize("velocity", ["message", "differentiate"])
def test_stream_import_equals_offline_import(walk_offline, velocity):
    config = RobotConfig.load(ROBOT)
    assert config.ros is not None
    config = dataclasses.replace(config, ros=dataclasses.replace(config.ros, joint_velocity=velocity))
    offline = walk_offline if velocity == config_default_velocity() else import_bag(WALK, config)
    rate = offline.meta["grid"]["rate_hz"]
    parts = list(stream_bag(WALK, config, rate=rate, part_seconds=0.37))
    assert len(parts) > 20
    rec = parts[0]
    for p in parts[1:]:
        rec = concat_recordings(rec, p)
    assert np.array_equal(rec.t_ns, offline.t_ns)
    assert np.array_equal(rec.contact_active, offline.contact_active)
    for name in offline.per_step_fields():
        a, b = getattr(offline, name), getattr(rec, name)
        if a.dtype == bool:
            continue
        assert np.array_equal(np.isnan(a), np.isnan(b)), name
        assert np.nanmax(np.abs(a - b)) <= 1e-9, name


@needs_icub
def test_stream_import_filters_the_imu_as_offline():
    """``ros.imu_filter = "savgol"``: the streamed IMU readings are the offline import's (the same
    smoother over the same rows, with the joints' delay), and so is every input."""
    config = RobotConfig.load(ROBOT)
    assert config.ros is not None
    config = dataclasses.replace(config, ros=dataclasses.replace(config.ros, imu_filter="savgol"))
    offline = import_bag(WALK, config)
    parts = list(stream_bag(WALK, config, rate=offline.meta["grid"]["rate_hz"], part_seconds=0.37))
    assert all(p.meta["stream"]["imu_filter"] == "savgol" for p in parts)
    rec = parts[0]
    for p in parts[1:]:
        rec = concat_recordings(rec, p)
    assert np.array_equal(rec.t_ns, offline.t_ns)
    for name in offline.per_step_fields():
        a, b = getattr(offline, name), getattr(rec, name)
        if a.dtype == bool:
            continue
        assert np.array_equal(np.isnan(a), np.isnan(b)), name
        assert np.nanmax(np.abs(a - b)) <= EXACT, name


@needs_icub
def test_blocks_on_the_icub_walk(walk_offline):
    """Ten samples per update through the iCub walk (touch-downs, IMU outliers): the smoother
    holds, and its per-foot F_z error against the F/T stays within 1.5 times one update per
    sample's (measured 42.8 / 40.8 N against 34.2 / 34.7 N)."""
    from flexforce.compare.metrics import evaluate

    rec = walk_offline
    model = ModelConfig.from_recording(rec, robot=RobotConfig.load(ROBOT))
    errors = {}
    for block in (1, 10):
        with pytest.warns(RuntimeWarning):
            est = run_fixed_lag(rec, model, FixedLagConfig(block=block))
        assert np.all(np.isfinite(est.wrench))
        errors[block] = {c: d["vertical_force_N"] for c, d in evaluate(est, rec).per_contact.items()}
    for contact, err in errors[10].items():
        assert err < 1.5 * errors[1][contact], contact


@needs_icub
def test_cdr_decoder_equals_rosbags():
    """The fixed-layout decoder of the Imu, JointState and WrenchStamped messages gives rosbags'
    fields for every message of a raw bag; other types and big-endian data are left to rosbags."""
    from rosbags.highlevel import AnyReader

    from flexforce.datasets.io.rosimport import T_IMU, T_JOINTS, T_WRENCH, _typestore
    from flexforce.datasets.io.stream import _CdrDecoder, _fields

    dec = _CdrDecoder()
    seen = set()
    with AnyReader([WALK], default_typestore=_typestore()) as reader:
        for conn, _, raw in reader.messages():
            got = dec.decode(conn.msgtype, raw)
            if conn.msgtype not in (T_IMU, T_JOINTS, T_WRENCH):
                assert got is None
                continue
            ref = _fields(reader.deserialize(raw, conn.msgtype), conn.msgtype)
            assert got is not None and got[:2] == ref[:2]
            if conn.msgtype == T_JOINTS:
                assert got[2][0] == tuple(ref[2][0])
                for a, b in zip(got[2][1:], ref[2][1:]):
                    assert np.array_equal(a, b, equal_nan=True) and a.dtype == float
            else:
                assert np.array_equal(np.ravel(got[2]), np.ravel(ref[2]), equal_nan=True)
            seen.add(conn.msgtype)
            big = bytes([0, 0]) + bytes(raw[2:])
            assert dec.decode(conn.msgtype, big) is None
            assert dec.decode(conn.msgtype, bytes(raw[:20])) is None
    assert seen == {T_IMU, T_JOINTS, T_WRENCH}


@needs_icub
def test_streamed_bag_estimate_equals_offline(walk_offline):
    rec = walk_offline
    model = ModelConfig.from_recording(rec, robot=RobotConfig.load(ROBOT))
    offline = run_fixed_lag(rec, model)
    parts = stream_bag(WALK, ROBOT, rate=rec.meta["grid"]["rate_hz"])
    stats: dict = {}
    ests = list(run_stream(parts, model, stats=stats))
    got = np.concatenate([e.wrench for e in ests])
    assert got.shape == offline.wrench.shape
    assert np.max(np.abs(got - offline.wrench)) <= EXACT
    assert stats["steps"] == rec.n and stats["update"]["updates"] == rec.n


def test_stream_importer_bad_messages():
    imp = StreamImporter("romeo", rate=100.0, contacts="fixed")
    imp.add_imu(1_000_000_000, (0, 0, 0), (0, 0, 9.8))
    with pytest.raises(DataError, match="time goes backwards on topic /imu"):
        imp.add_imu(900_000_000, (0, 0, 0), (0, 0, 9.8))
    imp.add_imu(1_100_000_000, (0, np.nan, 0), (0, 0, 9.8))  # a missing reading: skipped downstream
    assert np.isnan(imp.imu.v[-1][1]) and np.isfinite(imp.imu.v[-1][[0, 2, 3, 4, 5]]).all()
    with pytest.raises(DataError, match="3 \\+ 3"):
        imp.add_imu(1_200_000_000, (0, 0), (0, 0, 9.8))
    names = imp.joint_names[:3]
    with pytest.raises(DataError, match="NaN or inf position for joint"):
        imp.add_joints(1_000_000_000, names, (0.0, np.nan, 0.0))
    with pytest.raises(Exception, match="does not have"):
        imp.add_joints(1_000_000_000, ("no_such_joint",), (0.0,))
    with pytest.raises(DataError, match="no common time"):
        list(StreamImporter("romeo", rate=100.0, contacts="fixed").finish())
    with pytest.raises(ConfigError, match="F/T"):
        StreamImporter("romeo", rate=100.0, contacts="ft", ft_contacts=())


# ------------------------------------------------------------------------------------------------
# command line
# ------------------------------------------------------------------------------------------------
def _cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "flexforce.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd)


@needs_icub
def test_cli_streams_a_raw_bag(tmp_path: Path):
    out = tmp_path / "walk.csv"
    res = _cli("run", WALK, "--robot", ROBOT, "--estimator", "fixed-lag", "--end", "4", "-o", out, "-q")
    assert res.returncode == 0, res.stderr
    assert "streamed" in res.stdout
    table = np.loadtxt(out, delimiter=",", skiprows=1)
    header = out.read_text().splitlines()[0].split(",")
    assert "std_t_z" in header and table.shape[1] == len(header)
    assert 0.0 <= table[-1, 0] <= 4.0 + 1e-6 and table.shape[0] > 350
    # bag output: the estimate beside the copied inputs, paced at the bag's clock
    bag = tmp_path / "walk.mcap"
    res = _cli("run", WALK, "--robot", ROBOT, "--estimator", "fixed-lag", "--end", "1.5", "--no-cov", "--realtime",
               "-o", bag, "-q")
    assert res.returncode == 0, res.stderr
    assert "missed deadline" in res.stdout
    from rosbags.highlevel import AnyReader

    with AnyReader([bag]) as reader:
        topics = {c.topic for c in reader.connections}
    assert "/estimate/fixed_lag/total_wrench" in topics and "/estimate/fixed_lag/flexibility_cov" not in topics
    assert any(t.startswith("/icub") or "imu" in t.lower() for t in topics - {t for t in topics
                                                                               if t.startswith("/estimate")})
    res = _cli("run", WALK, "--robot", ROBOT, "--estimator", "ekf", "--realtime", "-o", tmp_path / "e.csv", "-q")
    assert res.returncode == 1 and "--realtime" in res.stderr
    # an error of the import (which runs in a child process for a .csv): one line, no output
    bad = tmp_path / "bad.csv"
    res = _cli("run", WALK, "--robot", "romeo", "--contacts", "fixed", "--estimator", "fixed-lag", "-o", bad, "-q")
    assert res.returncode == 1 and "topic /imu is in frame" in res.stderr
    assert "Traceback" not in res.stderr and len(res.stderr.strip().splitlines()) == 1 and not bad.exists()


def test_cli_streams_a_flexforce_recording(tmp_path: Path, pitch):
    from flexforce.datasets.io.bagio import save_recording

    bag = save_recording(pitch, tmp_path / "pitch")
    res = _cli("run", bag, "--estimator", "fixed-lag", "-o", tmp_path / "a.csv", "-q")
    assert res.returncode == 0, res.stderr
    res = _cli("run", bag, "--estimator", "fixed-lag", "--offline", "-o", tmp_path / "b.csv", "-q")
    assert res.returncode == 0, res.stderr
    a = np.loadtxt(tmp_path / "a.csv", delimiter=",", skiprows=1)
    b = np.loadtxt(tmp_path / "b.csv", delimiter=",", skiprows=1)
    assert a.shape == b.shape
    assert np.max(np.abs(a - b)) <= 1e-9
    # into a bag: the estimate beside every topic of the input, ground truth included
    res = _cli("run", bag, "--estimator", "fixed-lag", "-o", tmp_path / "c.mcap", "-q")
    assert res.returncode == 0, res.stderr
    from rosbags.highlevel import AnyReader

    with AnyReader([tmp_path / "c.mcap"]) as reader:
        out_topics = {c.topic for c in reader.connections}
    with AnyReader([bag]) as reader:
        in_topics = {c.topic for c in reader.connections}
    assert in_topics <= out_topics and any(t.startswith("/truth") for t in in_topics)
    assert "/estimate/fixed_lag/total_wrench" in out_topics


def test_update_times_quantiles_in_constant_memory():
    """The update-time distribution keeps bins, not samples: its median and p99 are within 0.1 %
    of the samples' (lower quantiles), its size does not grow."""
    from flexforce.smoother.stream import UpdateTimes

    rng = np.random.default_rng(3)
    x = np.exp(rng.normal(np.log(2e-4), 0.6, size=20000))
    u = UpdateTimes()
    size = u.bins.nbytes
    for v in x:
        u.add(v)
    assert u.bins.nbytes == size and u.count == x.size and u.max == x.max()
    assert u.total == pytest.approx(x.sum(), rel=1e-12)
    for q in (0.5, 0.99):
        ref = np.sort(x)[int(np.ceil(q * x.size)) - 1]
        assert u.quantile(q) == pytest.approx(ref, rel=1e-3), q


def test_an_importer_keeps_a_bounded_number_of_raw_imu_parts():
    """With ``imu_filter = "savgol"`` each part's readings before the filter wait for the sensor
    screen (``raw_imu``); an importer driven without one keeps at most ``RAW_IMU_PARTS`` of them."""
    import dataclasses

    from test_rosimport import ROS, UPPER, Motion, robot_topics, stamps

    from flexforce.datasets.io.stream import RAW_IMU_PARTS
    from flexforce.datasets.robot import RobotModel

    ros = dataclasses.replace(ROS, imu_filter="savgol")
    model = RobotModel(dataclasses.replace(RobotConfig.load("romeo"), ros=ros))
    t = stamps(n=1500)
    forces = 200.0 + np.random.default_rng(10).normal(scale=2.0, size=(len(t), 2))
    topics = robot_topics(model, Motion(model, UPPER), t, forces=forces)
    imp = StreamImporter(model, rate=100.0, contacts="ft", part_seconds=0.3)
    events = sorted([(s, "imu", f) for s, f in topics["/imu"][1]]
                    + [(s, "joints", f) for s, f in topics["/joint_states"][1]]
                    + [(s, c, f) for c, tp in (("left_foot", "/lf/wrench"), ("right_foot", "/rf/wrench"))
                       for s, f in topics[tp][1]], key=lambda e: (e[0], e[1]))
    parts = []
    for s, kind, f in events:
        if kind == "imu":
            imp.add_imu(int(s), f["gyro"], f["accel"], f["frame"])
        elif kind == "joints":
            imp.add_joints(int(s), f["name"], f["position"], f["velocity"])
        else:
            imp.add_ft(kind, int(s), f["w"], f["frame"])
        parts += list(imp.parts())
    assert len(parts) > 2 * RAW_IMU_PARTS
    assert len(imp._raw_imu) <= RAW_IMU_PARTS
    last = imp.raw_imu(parts[-1])
    assert last is not None and last["gyro"].shape == (parts[-1].n, 3)
