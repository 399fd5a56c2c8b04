"""Importing raw robot bags (ROS 1, ROS 2 sqlite3 and MCAP) into a Recording.

The bags are written here, into ``tmp_path``, with rosbags' writers, from a synthetic motion of
Romeo whose local-frame quantities are known exactly (RobotModel.kinematics of the true motion);
the broken ones each give one clear error.  The real iCub recordings close the file.
"""

from __future__ import annotations

import copy
import dataclasses
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
import rosbags.rosbag1
import rosbags.rosbag2
from conftest import ICUB_DIR as ICUB  # noqa: E402
from scipy.signal import savgol_filter

from flexforce.datasets.contacts import fixed_contacts, phases, schmitt_trigger
from flexforce.datasets.io.bagio import load_recording, save_recording
from flexforce.datasets.io.rosimport import import_bag, imu_smoothed, is_flexforce_bag, window_holds
from flexforce.datasets.robot import RobotConfig, RobotModel, RosConfig
from flexforce.errors import BagError, ConfigError, DataError

T0 = 1_700_000_000_000_000_000  # an epoch time: stamps use both sec and nanosec
ROS = RosConfig(ft_topics={"left_foot": "/lf/wrench", "right_foot": "/rf/wrench"},
                mocap_topics={"torso": "/mocap/torso"}, contact_on=150.0, contact_off=100.0,
                joint_velocity="message", savgol_window=0.08)
UPPER = ("LShoulderPitch", "RElbowRoll", "NeckYaw", "TrunkYaw")
LEGS = ("LHipPitch", "LKneePitch", "LAnklePitch", "RHipPitch", "RKneePitch", "RAnklePitch")


@pytest.fixture(scope="module")
def romeo():
    config = dataclasses.replace(RobotConfig.load("romeo"), ros=ROS)
    return RobotModel(config)


# ------------------------------------------------------------------------------------------------
# a synthetic motion and its bag
# ------------------------------------------------------------------------------------------------
@dataclasses.dataclass
class Motion:
    """Joint trajectories q_j(t) = q_ref + A sin(2 pi f t + phi) on the named joints."""

    model: RobotModel
    joints: tuple
    amp: float = 0.3
    freq: float = 0.8

    def __post_init__(self):
        self.idx = [self.model.joint_index(j) for j in self.joints]
        self.phase = np.linspace(0.0, 1.0, len(self.joints))
        self.sign = np.ones(len(self.joints))

    def at(self, t: np.ndarray):
        """(q, v, a) joint parts, each (len(t), nj)."""
        w = 2 * np.pi * self.freq
        q = np.tile(self.model.q_reference[7:], (len(t), 1))
        v = np.zeros_like(q)
        a = np.zeros_like(q)
        for c, i in enumerate(self.idx):
            arg = w * t + self.phase[c]
            q[:, i] += self.sign[c] * self.amp * np.sin(arg)
            v[:, i] = self.sign[c] * self.amp * w * np.cos(arg)
            a[:, i] = -self.sign[c] * self.amp * w * w * np.sin(arg)
        return q, v, a


def stamps(n=240, period=10e-3, jitter=2e-3, seed=0):
    """Irregular stamps (ns) around ``period`` s."""
    rng = np.random.default_rng(seed)
    dt = period + rng.uniform(-jitter, jitter, n - 1)
    return T0 + np.concatenate([[0], np.cumsum(np.round(dt * 1e9))]).astype(np.int64)


def signals(t):
    """Smooth IMU readings and F/T forces (arbitrary but known)."""
    s = (t - T0) * 1e-9
    gyro = np.stack([0.1 * np.sin(3 * s), 0.05 * np.cos(2 * s), 0.02 * s], axis=1)
    accel = np.stack([0.3 * np.sin(2 * s), 0.1 * np.cos(s), 9.81 + 0.2 * np.sin(5 * s)], axis=1)
    return gyro, accel


def write_bag(path: Path, kind: str, topics: dict):
    """Write ``topics`` (topic -> (msgtype, [(t_ns, fields dict)])) as ``kind`` (mcap, sqlite3, ros1).

    ``t_ns`` is the header stamp and, unless ``fields["log"]`` says otherwise, the log time.
    """
    from rosbags.typesys import Stores, get_typestore

    ros1 = kind == "ros1"
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    T = ts.types
    writer: rosbags.rosbag1.Writer | rosbags.rosbag2.Writer
    if ros1:
        writer = rosbags.rosbag1.Writer(path)
    else:
        from rosbags.rosbag2 import StoragePlugin

        plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
        writer = rosbags.rosbag2.Writer(path, version=8, storage_plugin=plugin)

    def header(t, frame, seq):
        sec, nsec = divmod(int(t), 1_000_000_000)
        stamp = T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)
        if ros1:
            return T["std_msgs/msg/Header"](seq=seq, stamp=stamp, frame_id=frame)
        return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)

    def vec(v):
        return T["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))

    def build(msgtype, t, f, seq):
        h = header(t, f.get("frame", ""), seq)
        if msgtype == "sensor_msgs/msg/Imu":
            z9, o9 = np.zeros(9), np.zeros(9)
            o9[0] = -1
            return T[msgtype](header=h, orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
                              orientation_covariance=o9, angular_velocity=vec(f["gyro"]),
                              angular_velocity_covariance=z9, linear_acceleration=vec(f["accel"]),
                              linear_acceleration_covariance=z9)
        if msgtype == "sensor_msgs/msg/JointState":
            return T[msgtype](header=h, name=list(f["name"]), position=np.asarray(f["position"], float),
                              velocity=np.asarray(f.get("velocity", []), float), effort=np.zeros(0))
        if msgtype == "geometry_msgs/msg/WrenchStamped":
            return T[msgtype](header=h,
                              wrench=T["geometry_msgs/msg/Wrench"](force=vec(f["w"][:3]), torque=vec(f["w"][3:])))
        if msgtype == "geometry_msgs/msg/PoseStamped":
            p = f["p"]
            return T[msgtype](header=h, pose=T["geometry_msgs/msg/Pose"](
                position=T["geometry_msgs/msg/Point"](x=p[0], y=p[1], z=p[2]),
                orientation=T["geometry_msgs/msg/Quaternion"](x=p[3], y=p[4], z=p[5], w=p[6])))
        raise AssertionError(msgtype)

    with writer:
        events = []
        for topic, (msgtype, items) in topics.items():
            conn = writer.add_connection(topic, msgtype, typestore=ts)
            events += [(f.get("log", t), t, i, conn, msgtype, f) for i, (t, f) in enumerate(items)]
        events.sort(key=lambda e: e[0])
        for log, t, seq, conn, msgtype, f in events:
            msg = build(msgtype, t, f, seq)
            data = ts.serialize_ros1(msg, msgtype) if ros1 else ts.serialize_cdr(msg, msgtype)
            writer.write(conn, int(log), data)
    return path


def robot_topics(model, motion, t_imu, t_js=None, forces=None, shuffle=True, mocap=True):
    """Topics of a standing robot: /imu, /joint_states (velocity included), F/T, mocap."""
    t_js = t_imu if t_js is None else t_js
    gyro, accel = signals(t_imu)
    q, v, _ = motion.at((t_js - T0) * 1e-9)
    names = list(model.joint_names)
    order = np.random.default_rng(1).permutation(len(names)) if shuffle else np.arange(len(names))
    topics = {
        "/imu": ("sensor_msgs/msg/Imu", [(t, {"gyro": g, "accel": a, "frame": "ImuTorsoAccelerometer_frame"})
                                         for t, g, a in zip(t_imu, gyro, accel)]),
        "/joint_states": ("sensor_msgs/msg/JointState", [
            (t, {"name": [names[i] for i in order], "position": qq[order], "velocity": vv[order]})
            for t, qq, vv in zip(t_js, q, v)]),
    }
    if forces is None:
        forces = np.full((len(t_imu), 2), 200.0)
    for i, (cname, frame) in enumerate((("left_foot", "l_sole"), ("right_foot", "r_sole"))):
        w = np.zeros((len(t_imu), 6))
        w[:, 2] = forces[:, i]
        w[:, 3:] = np.nan  # force-only sensor, like iCub's
        topics[ROS.ft_topics[cname]] = ("geometry_msgs/msg/WrenchStamped",
                                        [(t, {"w": ww, "frame": frame}) for t, ww in zip(t_imu, w)])
    if mocap:
        s = (t_imu - T0) * 1e-9
        pose = np.stack([0.01 * s, 0 * s, 0.8 + 0 * s, 0 * s, 0 * s, np.sin(0.1 * s), np.cos(0.1 * s)], axis=1)
        topics["/mocap/torso"] = ("geometry_msgs/msg/PoseStamped", [(t, {"p": p, "frame": "world"})
                                                                    for t, p in zip(t_imu, pose)])
    return topics


def expected_kinematics(model, rec, motion):
    """The local-frame quantities of the true motion: base fixed where the import put it."""
    q, v, a = motion.at(rec.time + (rec.t_ns[0] - T0) * 1e-9)
    base = np.array(rec.base_pose[0])
    out = []
    for k in range(rec.n):
        qf = np.concatenate([base, q[k]])
        out.append(model.kinematics(qf, np.concatenate([np.zeros(6), v[k]]), np.concatenate([np.zeros(6), a[k]])))
    return out


# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["mcap", "sqlite3", "ros1"])
def test_import_recovers_the_synthetic_motion(romeo, tmp_path, kind):
    """Every storage: the grid, the resampled readings and the local-frame inputs are the truth's."""
    motion = Motion(romeo, UPPER)
    t = stamps()
    path = write_bag(tmp_path / ("b.bag" if kind == "ros1" else "b"), kind, robot_topics(romeo, motion, t))
    rec = import_bag(path, romeo)

    period = round(1e9 / (1e9 / np.median(np.diff(t))))
    assert rec.t_ns[0] == t[0] and rec.n == (t[-1] - t[0]) // period + 1
    assert rec.meta["source"]["format"] == ("ROS 1" if kind == "ros1" else "ROS 2")
    gyro, accel = signals(rec.t_ns)
    np.testing.assert_allclose(rec.gyro, gyro, atol=2e-5)  # linear interpolation of smooth signals
    np.testing.assert_allclose(rec.accel, accel, atol=2e-4)
    q, v, _ = motion.at((rec.t_ns - T0) * 1e-9)
    # linear interpolation error <= |f''| h^2 / 8: A w^2 h^2 / 8 = 1.4e-4 rad for q (h <= 12 ms),
    # A w^3 h^2 / 8 = 7e-4 rad/s for v
    np.testing.assert_allclose(rec.joint_q, q, atol=2e-4)
    np.testing.assert_allclose(rec.joint_v, v, atol=1e-3)
    assert rec.contact_active.all() and rec.meta["anchor"]["first"] == "left_foot"
    # the anchor (left sole) is the local origin, flat; the base does not move (legs are still)
    np.testing.assert_allclose(rec.contact_p[:, 0], 0.0, atol=1e-12)
    np.testing.assert_allclose(rec.contact_R[:, 0], np.broadcast_to(np.eye(3), (rec.n, 3, 3)), atol=1e-12)
    base = np.array(rec.base_pose)
    np.testing.assert_allclose(base - base[0], 0.0, atol=1e-9)
    exp = expected_kinematics(romeo, rec, motion)
    inner = slice(5, -5)  # Savitzky-Golay edges use a one-sided fit
    for name, get, tol in (("com", lambda e: e.inputs.c, 1e-5), ("com_vel", lambda e: e.inputs.dc, 1e-4),
                           ("com_acc", lambda e: e.inputs.ddc, 3e-3), ("sigma", lambda e: e.inputs.sigma, 1e-3),
                           ("sigma_dot", lambda e: e.inputs.dsigma, 2e-2), ("inertia", lambda e: e.inputs.I, 1e-4),
                           ("imu_p", lambda e: e.imu.p, 1e-5), ("imu_w", lambda e: e.imu.w, 1e-3),
                           ("imu_a", lambda e: e.imu.a, 5e-3)):
        np.testing.assert_allclose(getattr(rec, name)[inner], np.array([get(e) for e in exp])[inner], atol=tol,
                                   err_msg=name)
    # F/T: force.z kept, unmeasured torques stay NaN; mocap resampled
    np.testing.assert_allclose(rec.ft[:, :, 2], 200.0)
    assert np.isnan(rec.ft[:, :, 3:]).all()
    s = (rec.t_ns - T0) * 1e-9
    np.testing.assert_allclose(rec.mocap["torso"][:, 0], 0.01 * s, atol=1e-9)
    np.testing.assert_allclose(rec.mocap["torso"][:, 5], np.sin(0.1 * s), atol=1e-6)


def test_leg_odometry_keeps_the_stance_foot_still(romeo, tmp_path):
    """A squat: the base moves; the anchor sole stays at its rest placement, the other sole too,
    and the analytic base velocity/acceleration agree with derivatives of the IMU position."""
    motion = Motion(romeo, LEGS, amp=0.15)
    motion.phase[:] = 0.0
    motion.sign[:] = [-1, 2, -1, -1, 2, -1]  # hip, knee, ankle: the feet stay parallel to the pelvis
    t = T0 + np.arange(300, dtype=np.int64) * 5_000_000
    path = write_bag(tmp_path / "squat.mcap", "mcap", robot_topics(romeo, motion, t))
    rec = import_bag(path, romeo, contacts="fixed")
    model = romeo.model
    data = model.createData()
    lf = romeo.contact_frame_ids[0]
    for k in range(0, rec.n, 37):  # the anchor's kinematic placement is its rest placement
        q = np.concatenate([rec.base_pose[k], rec.joint_q[k]])
        pin.framesForwardKinematics(model, data, q)
        np.testing.assert_allclose(data.oMf[lf].translation, 0.0, atol=1e-9)
    base = np.array(rec.base_pose)
    assert np.ptp(base[:, 2]) > 0.01  # the pelvis goes down and up
    assert rec.meta["anchor"]["drift_m"] < 1e-3  # the right sole's rest placement is consistent
    inner = slice(10, -10)
    dt = rec.dt
    np.testing.assert_allclose(np.gradient(rec.imu_p, dt, axis=0)[inner], rec.imu_v[inner], atol=2e-3)
    np.testing.assert_allclose(np.gradient(rec.imu_v, dt, axis=0)[inner], rec.imu_a[inner], atol=2e-2)
    np.testing.assert_allclose(np.gradient(rec.com, dt, axis=0)[inner], rec.com_vel[inner], atol=2e-3)


def test_schmitt_trigger_has_hysteresis():
    f = np.array([130, 160, 140, 110, 95, 130, 149, 151, np.nan, 99, 100])
    assert schmitt_trigger(f, on=150, off=100).tolist() == [
        True, True, True, True, False, False, False, True, True, False, False]
    assert schmitt_trigger([50.0, 200.0], on=150, off=100).tolist() == [False, True]
    with pytest.raises(ConfigError, match="off < on"):
        schmitt_trigger(f, on=100, off=150)
    assert fixed_contacts(3, ("a", "b"), ("b",)).tolist() == [[False, True]] * 3
    with pytest.raises(ConfigError, match="not contacts"):
        fixed_contacts(3, ("a", "b"), ("c",))
    assert phases(np.arange(5.0), np.array([[1, 1, 0, 1, 1]]).T.astype(bool), ["a"])[0].intervals == ((0, 1), (3, 4))


def test_walking_contacts_switch_the_anchor(romeo, tmp_path):
    """Alternating single supports from the F/T: the anchor follows the stance foot and each
    contact's rest placement stays fixed while it is in contact."""
    motion = Motion(romeo, UPPER)
    t = T0 + np.arange(400, dtype=np.int64) * 10_000_000
    s = (t - T0) * 1e-9
    forces = np.full((len(t), 2), 200.0)
    forces[(s > 0.8) & (s < 1.5), 0] = 5.0    # left swing
    forces[(s > 2.0) & (s < 2.8), 1] = 5.0    # right swing
    forces[(s > 3.2) & (s < 3.6), 0] = 120.0  # between the thresholds: stays as it was (in contact)
    forces[(s > 3.2) & (s < 3.6), 1] = 400.0
    rec = import_bag(write_bag(tmp_path / "walk", "mcap", robot_topics(romeo, motion, t, forces=forces)), romeo)
    ph = rec.meta["contacts"]["phases"]
    assert len(ph["left_foot"]) == 2 and len(ph["right_foot"]) == 2
    # the anchor follows the swings, then passes to the right foot when it carries more than
    # 3 times the left one's load (400 N against 120 N) while both are down
    switches = rec.meta["anchor"]["switches"]
    assert [(sw["from"], sw["to"]) for sw in switches] == [
        ("left_foot", "right_foot"), ("right_foot", "left_foot"), ("left_foot", "right_foot")]
    assert 3.2 <= switches[2]["t"] - rec.time[0] <= 3.25
    for i in range(2):
        col = rec.contact_active[:, i]
        edges = np.flatnonzero(np.diff(col.astype(int))) + 1
        for seg in np.split(np.arange(rec.n), edges):
            if col[seg[0]]:
                np.testing.assert_allclose(rec.contact_p[seg, i] - rec.contact_p[seg[0], i], 0.0, atol=1e-12)


def test_irregular_stamps_and_gaps(romeo, tmp_path):
    """Gaps above gap_factor periods are reported; beyond max_gap they are an error."""
    motion = Motion(romeo, UPPER)
    t = stamps(300, seed=3)
    keep = np.ones(len(t), dtype=bool)
    keep[100:104] = False  # a 50 ms gap on the IMU only
    topics = robot_topics(romeo, motion, t)
    topics["/imu"] = ("sensor_msgs/msg/Imu", [m for m, ok in zip(topics["/imu"][1], keep) if ok])
    rec = import_bag(write_bag(tmp_path / "gap", "mcap", topics), romeo)
    gaps = rec.meta["gaps"]
    assert len(gaps) == 1 and gaps[0]["topics"] == ["/imu"] and 0.04 < gaps[0]["duration"] < 0.06
    strict = dataclasses.replace(romeo.config, ros=dataclasses.replace(ROS, max_gap=0.03))
    with pytest.raises(DataError, match=r"topic /imu has a gap of 0\.0\d+ s .* ros.max_gap = 0.03 s"):
        import_bag(tmp_path / "gap", strict)


def test_velocities_differentiated_when_absent(romeo, tmp_path):
    motion = Motion(romeo, UPPER)
    t = T0 + np.arange(300, dtype=np.int64) * 10_000_000
    topics = robot_topics(romeo, motion, t)
    for _, f in topics["/joint_states"][1]:
        f.pop("velocity")
    rec = import_bag(write_bag(tmp_path / "nov", "mcap", topics), romeo)
    assert rec.meta["joint_velocity"] == "savgol"
    _, v, _ = motion.at((rec.t_ns - T0) * 1e-9)
    np.testing.assert_allclose(rec.joint_v[5:-5], v[5:-5], atol=1e-3)


def test_imported_recording_round_trips_and_is_told_apart(romeo, tmp_path):
    """The import saves as a flexforce recording; is_flexforce_bag tells the two kinds apart."""
    motion = Motion(romeo, UPPER)
    raw = write_bag(tmp_path / "raw", "mcap", robot_topics(romeo, motion, stamps(120)))
    rec = import_bag(raw, romeo)
    out = save_recording(rec, tmp_path / "rec")
    back = load_recording(out)
    np.testing.assert_array_equal(back.com, rec.com)
    np.testing.assert_array_equal(back.base_pose, rec.base_pose)
    assert is_flexforce_bag(out) and not is_flexforce_bag(raw)


# ------------------------------------------------------------------------------------------------
# broken bags: one clear error each
# ------------------------------------------------------------------------------------------------
@pytest.fixture()
def good_topics(romeo):
    return robot_topics(romeo, Motion(romeo, UPPER), stamps(100), shuffle=False)


def test_random_bytes(romeo, tmp_path):
    bad = tmp_path / "noise.bag"
    bad.write_bytes(np.random.default_rng(0).bytes(4096))
    with pytest.raises(BagError, match="cannot read bag .*noise.bag: corrupt, truncated or not a bag"):
        import_bag(bad, romeo)
    with pytest.raises(BagError, match="corrupt, truncated or not a bag"):
        is_flexforce_bag(bad)
    with pytest.raises(BagError, match="does not exist"):
        import_bag(tmp_path / "nothing.mcap", romeo)


@pytest.mark.parametrize("kind", ["mcap", "ros1"])
def test_truncated_bag(romeo, tmp_path, good_topics, kind):
    path = write_bag(tmp_path / ("t.bag" if kind == "ros1" else "t"), kind, good_topics)
    file = path if kind == "ros1" else next(path.glob("*.mcap"))
    data = file.read_bytes()
    file.write_bytes(data[: len(data) // 2])
    with pytest.raises(BagError, match="corrupt, truncated or not a bag"):
        import_bag(path, romeo)


def test_missing_topic(romeo, tmp_path, good_topics):
    del good_topics["/rf/wrench"]
    path = write_bag(tmp_path / "m", "mcap", good_topics)
    with pytest.raises(BagError,
                       match=r"lacks topic /rf/wrench \(geometry_msgs/msg/WrenchStamped\).*the bag has: /imu"):
        import_bag(path, romeo)
    rec = import_bag(path, romeo, contacts="fixed")  # without the F/T contact detection it is optional
    assert rec.contact_active.all() and np.isnan(rec.ft[:, 1]).all()


def test_topics_without_messages(romeo, tmp_path, good_topics):
    """Declared topics with no message: the error says the topic is empty, not that it is missing."""
    empty = {topic: (msgtype, []) for topic, (msgtype, _) in good_topics.items()}
    path = write_bag(tmp_path / "e", "mcap", empty)
    with pytest.raises(BagError, match=r"topic /imu \(sensor_msgs/msg/Imu\) of bag .*e has no messages; expected the "
                                       "messages robot config 'romeo' reads from it"):
        import_bag(path, romeo)


def test_unknown_joint(romeo, tmp_path, good_topics):
    """A joint the robot does not have is refused, unless ignored (``ros.ignore_joints``): then the
    URDF joint it stood for is not measured, which is allowed away from the contacts and the IMU
    (a wrist stays at its reference) and refused where it carries a foot (a knee)."""
    names = list(good_topics["/joint_states"][1][0][1]["name"])
    wrist, knee = names.index("LWristYaw"), names.index("LKneePitch")
    lenient = dataclasses.replace(romeo.config, ros=dataclasses.replace(ROS, ignore_joints="Twist$"))
    for i, (which, stem) in enumerate(((wrist, "LWristTwist"), (knee, "LKneeTwist"))):
        topics = copy.deepcopy(good_topics)
        for _, f in topics["/joint_states"][1]:
            f["name"] = list(f["name"])
            f["name"][which] = stem
        path = write_bag(tmp_path / f"j{i}", "mcap", topics)
        with pytest.raises(BagError, match=f"names joint '{stem}', which robot 'romeo' .* does not have"):
            import_bag(path, romeo)
        if stem == "LWristTwist":
            rec = import_bag(path, lenient)
            assert rec.meta["joints_not_measured"] == ["LWristYaw"]
        else:
            with pytest.raises(BagError, match="never names joint 'LKneePitch', which moves contact 'left_foot'"):
                import_bag(path, lenient)


def test_joints_in_degrees_are_refused(romeo, tmp_path, good_topics):
    """Joint positions beyond a turn (a humanoid's revolute joints stay within +-pi): degrees,
    refused offline and streamed, naming the joint, its reading and its URDF range."""
    for _, f in good_topics["/joint_states"][1]:
        f["position"] = np.degrees(np.asarray(f["position"], dtype=float))
    path = write_bag(tmp_path / "deg", "mcap", good_topics)
    pattern = r"joint '\w+' reads [0-9.]+, more than a turn \(2 pi rad\); its URDF range is .* look like degrees"
    with pytest.raises(DataError, match=pattern):
        import_bag(path, romeo)
    from flexforce.datasets.io.stream import stream_bag

    with pytest.raises(DataError, match=pattern):
        list(stream_bag(path, romeo))


def test_unknown_frame(romeo, tmp_path, good_topics):
    for _, f in good_topics["/lf/wrench"][1]:
        f["frame"] = "l_ankle_ft_sensor"
    with pytest.raises(BagError, match="topic /lf/wrench is in frame 'l_ankle_ft_sensor', which is not in the URDF"):
        import_bag(write_bag(tmp_path / "f", "mcap", good_topics), romeo)


def test_a_force_only_sensor_in_another_frame_is_refused(romeo, tmp_path, good_topics):
    """An F/T topic in a URDF frame turned from the contact's, carrying F_z only (the others NaN):
    its normal force cannot be moved to the sole; refused naming both frames (the normal force
    came out NaN and the foot "never came into force")."""
    import pinocchio as pin

    from flexforce.datasets.io.stream import stream_bag

    pm = romeo.model
    data = pm.createData()
    pin.framesForwardKinematics(pm, data, pin.neutral(pm))
    sole = data.oMf[pm.getFrameId("l_sole")]
    turned = next(f.name for i, f in enumerate(pm.frames)
                  if np.linalg.norm(pin.log3(sole.rotation.T @ data.oMf[i].rotation)) > 0.3)
    for _, f in good_topics["/lf/wrench"][1]:
        f["frame"] = turned
        f["w"] = np.array([np.nan, np.nan, f["w"][2], np.nan, np.nan, np.nan])
    path = write_bag(tmp_path / "turned", "mcap", good_topics)
    pattern = (rf"topic /lf/wrench is in frame '{turned}', not the contact frame 'l_sole', and its wrench cannot be "
               r"moved there: F_x, F_y, T_x, T_y, T_z are not measured")
    with pytest.raises(BagError, match=pattern):
        import_bag(path, romeo)
    with pytest.raises(BagError, match=pattern):
        list(stream_bag(path, romeo))


def test_imu_in_another_frame(romeo, tmp_path, good_topics):
    for _, f in good_topics["/imu"][1]:
        f["frame"] = "imu_link"
    with pytest.raises(BagError, match="topic /imu is in frame 'imu_link' .*expected the IMU frame"):
        import_bag(write_bag(tmp_path / "i", "mcap", good_topics), romeo)


def test_nan_imu_reading_is_missing_not_refused(romeo, tmp_path, good_topics):
    """A NaN IMU component is a missing reading: NaN on that axis at the grid points its message
    brackets (at most two), the other axes and samples untouched; too many is refused."""
    clean = import_bag(write_bag(tmp_path / "c", "mcap", good_topics), romeo)
    good_topics["/imu"][1][42][1]["accel"] = np.array([0.0, np.nan, 9.8])
    rec = import_bag(write_bag(tmp_path / "n", "mcap", good_topics), romeo)
    assert rec.meta["imu_missing_messages"] == 1
    bad = np.isnan(rec.accel)
    assert 1 <= bad[:, 1].sum() <= 2 and not bad[:, [0, 2]].any() and not np.isnan(rec.gyro).any()
    ok = ~bad[:, 1]
    assert np.array_equal(rec.accel[ok], clean.accel[ok])
    for k in range(10, 60):
        good_topics["/imu"][1][k][1]["gyro"] = np.array([np.inf, 0.0, 0.0])
    with pytest.raises(DataError, match="missing"):
        import_bag(write_bag(tmp_path / "m", "mcap", good_topics), romeo)


def test_imu_filter_is_the_joints_savgol_smoother(romeo, tmp_path, good_topics):
    """``ros.imu_filter = "savgol"``: the IMU readings on the grid through scipy's savgol_filter with
    the joints' window and order (zero-phase, ``mode="interp"``); a 20 Hz vibration on top of the
    smooth readings is what it takes out, as the joints' derivatives lose it."""
    for t, f in good_topics["/imu"][1]:  # a 20 Hz vibration of the pelvis on the accelerometer
        f["accel"] = f["accel"] + np.array([0.0, 0.0, 0.5 * np.sin(2 * np.pi * 20 * (t - T0) * 1e-9)])
    path = write_bag(tmp_path / "v", "mcap", good_topics)
    raw = import_bag(path, romeo)
    band = dataclasses.replace(romeo.config, ros=dataclasses.replace(ROS, imu_filter="savgol"))
    rec = import_bag(path, band)
    assert raw.meta["imu_filter"] == "none" and rec.meta["imu_filter"] == "savgol"
    win = int(round(ROS.savgol_window / rec.dt)) | 1
    for name in ("gyro", "accel"):
        expected = savgol_filter(getattr(raw, name), win, ROS.savgol_order, axis=0, mode="interp")
        np.testing.assert_allclose(getattr(rec, name), expected, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(rec.joint_v, raw.joint_v)  # the joints are untouched

    # a vibration: the smoother's response at 20 Hz is its own, |H(20 Hz)| < 0.2 for 9 samples at 100 Hz
    t = np.arange(400) * 0.01
    x = np.stack([np.sin(2 * np.pi * 20 * t), np.sin(2 * np.pi * 0.5 * t), np.ones_like(t)], axis=1)
    y = imu_smoothed(x, np.inf, win, lambda z: savgol_filter(z, win, ROS.savgol_order, axis=0, mode="interp"))
    inner = slice(win, -win)
    assert np.abs(y[inner, 0]).max() < 0.2 * np.abs(x[inner, 0]).max()
    np.testing.assert_allclose(y[inner, 1:], x[inner, 1:], atol=1e-4)  # slow motion and gravity kept


def test_imu_filter_leaves_missing_what_it_cannot_use():
    """A missing (NaN) or clipped reading makes missing, on its axis, every output whose window
    holds it (the centred window inside, the first or last at the ends); the others are scipy's."""
    win, order, n = 9, 3, 60
    rng = np.random.default_rng(4)
    x = rng.normal(size=(n, 3))
    x[30, 0] = np.nan
    x[2, 1] = 16.0  # at the full scale
    x[n - 1, 2] = -16.0

    def smooth(z):
        return savgol_filter(z, win, order, axis=0, mode="interp")

    y = imu_smoothed(x, 16.0, win, smooth)
    bad = np.zeros((n, 3), dtype=bool)
    bad[26:35, 0] = True  # 30 +- 4
    bad[:7, 1] = True  # rows 0..6: the first window (rows 0..8) or, for 5 and 6, the centred one
    bad[n - 5:, 2] = True  # the last window's rows and the centred ones reaching n - 1
    assert np.array_equal(np.isnan(y), bad)
    clean = smooth(np.where(np.isfinite(x) & (np.abs(x) < 15.9), x, 0.0))
    np.testing.assert_array_equal(y[~bad], clean[~bad])
    assert np.array_equal(window_holds(np.isnan(x), win), bad & (np.arange(3) == 0))


def test_nan_joint_position(romeo, tmp_path, good_topics):
    pos = good_topics["/joint_states"][1][7][1]["position"]
    pos[2] = np.nan
    with pytest.raises(DataError, match=r"message 7 .* NaN or inf position for joint 'LHipPitch'"):
        import_bag(write_bag(tmp_path / "nj", "mcap", good_topics), romeo)


def test_time_going_backwards(romeo, tmp_path, good_topics):
    items = good_topics["/joint_states"][1]
    t, f = items[30]
    items[30] = (t - 50_000_000, {**f, "log": t})  # stamped 50 ms early, logged in order
    with pytest.raises(DataError, match="time goes backwards on topic /joint_states: message 30 is stamped"):
        import_bag(write_bag(tmp_path / "back", "mcap", good_topics), romeo)


def test_bad_config(romeo, tmp_path, good_topics):
    path = write_bag(tmp_path / "c", "mcap", good_topics)
    with pytest.raises(ConfigError, match="contacts = 'maybe'"):
        import_bag(path, romeo, contacts="maybe")
    with pytest.raises(ConfigError, match="contact_off = 160.0 N must be below"):
        RosConfig(contact_on=150.0, contact_off=160.0)
    with pytest.raises(ConfigError, match=r"unknown key\(s\) \['imu_topc'\] in \[ros\]"):
        RobotConfig.from_dict({"name": "x", "urdf": "x", "imu_frame": "x", "contacts": [],
                               "stiffness": {"k_fs": 1e4, "k_fd": 1e2, "k_ts": 3e2, "k_td": 5.0},
                               "ros": {"imu_topc": "/imu"}})


# ------------------------------------------------------------------------------------------------
# the real iCub recordings
# ------------------------------------------------------------------------------------------------
@pytest.mark.skipif(not ICUB.exists(), reason="shared iCub recordings not available")
def test_icub_recordings():
    """Both bags import: counts, grids, contact phases, and the local frame is the Vicon world at t0."""
    walk = import_bag(ICUB / "icub-walk-12s", "icub")
    sway = import_bag(ICUB / "icub-com-sinusoid-20s.bag", "icub")
    for rec, messages, span in ((walk, 1188, 11.9936), (sway, 2004, 20.1356)):
        assert rec.meta["source"]["messages"]["/imu"] == messages
        assert abs(rec.time[-1] - span) < rec.dt and rec.n == int(span / rec.dt) + 1
        assert 99.0 < 1.0 / rec.dt < 101.0
        assert rec.joint_q.shape == (rec.n, 32) and rec.gyro.shape == (rec.n, 3)  # one grid for all
        assert len(rec.meta["joints_not_measured"]) == 6  # the wrists
        # at rest the accelerometer reads gravity through the kinematic IMU orientation
        np.testing.assert_allclose(rec.accel[0], rec.imu_R[0].T @ [0, 0, 9.81], atol=0.3)
        # local frame = Vicon world at the start (world = right sole at t0); 1.2 cm of sole height
        np.testing.assert_allclose(rec.base_pose[0][:3], rec.mocap["root_link"][0, :3], atol=0.015)
    assert max(g["duration"] for g in walk.meta["gaps"]) < 0.03
    assert 0.16 < max(g["duration"] for g in sway.meta["gaps"]) < 0.18
    assert sway.contact_active.all() and not sway.meta["anchor"]["switches"]
    left, right = walk.meta["contacts"]["phases"]["left_foot"], walk.meta["contacts"]["phases"]["right_foot"]
    assert len(left) >= 4 and len(right) >= 4  # alternating single supports after 5.5 s
    single = walk.contact_active.sum(axis=1) == 1
    # 40 % of the samples in single support (feet in force down to 20 % of the weight; 39 % with
    # the authors' 150/120 N trigger); margin 0.05 for a sample more or less at each switch
    assert single[: int(5.4 / walk.dt)].sum() == 0 and single.mean() > 0.35
    # loaded feet stay in the model: a foot called unloaded carries at most the on threshold,
    # 0.25 m g = 81 N, measured 80 N (the 150/120 N trigger left out feet carrying up to 147 N)
    weight = walk.mass * 9.81
    inactive_load = np.where(~walk.contact_active, walk.ft[:, :, 2], -np.inf)
    assert np.nanmax(inactive_load) <= 0.25 * weight
    # the anchor passes between feet while both are down: 6 switches, jumps 4.4-6.2 mm measured,
    # bound 8 mm
    # (when a foot was anchor until it left contact at 5 % of the weight, rolling off its toes,
    # the jumps were 36-51 mm)
    switches = walk.meta["anchor"]["switches"]
    assert len(switches) >= 6 and max(s["jump_m"] for s in switches) < 0.008
    assert walk.meta["anchor"]["drift_m"] < 0.01
    assert set(walk.mocap) == {"root_link", "l_sole", "r_sole"} and set(sway.mocap) == {"root_link"}


def test_a_foot_that_never_touches_is_named(romeo, tmp_path):
    """One foot's F/T never reaches the on threshold (a dead sensor, a wrong topic): one line
    naming the foot, its largest force, the threshold and the topic; none at all: another."""
    motion = Motion(romeo, UPPER)
    t = T0 + np.arange(120, dtype=np.int64) * 10_000_000
    forces = np.full((len(t), 2), 300.0)
    forces[:, 1] = 3.0
    bag = write_bag(tmp_path / "dead", "mcap", robot_topics(romeo, motion, t, forces=forces))
    with pytest.raises(DataError, match=r"contact\(s\) \['right_foot'\] never come into force \(largest F/T "
                                        r"normal force right_foot: 3.0 N, on threshold 150.0 N\).*/rf/wrench"):
        import_bag(bag, romeo)
    forces[:, 0] = 3.0
    bag = write_bag(tmp_path / "none", "mcap", robot_topics(romeo, motion, t, forces=forces))
    with pytest.raises(DataError, match="no contact is ever in force"):
        import_bag(bag, romeo)
    # the forces read, and a hint when they look like a flipped sign
    forces[:] = -300.0
    bag = write_bag(tmp_path / "flipped", "mcap", robot_topics(romeo, motion, t, forces=forces))
    with pytest.raises(DataError, match=r"no contact is ever in force .*\(F/T Schmitt trigger: in force above "
                                        r"150 N.*the F/T normal forces read -300 to -300 N; mostly negative"):
        import_bag(bag, romeo)


def test_a_landing_far_off_the_floor_contradicts_the_ground_prior(romeo, tmp_path):
    """A foot landing further off the floor plane than the ground prior allows (6 kinematic
    sigmas) is refused with the time, the contact, the offsets and the way out; terrain 'none'
    takes the same log."""
    import dataclasses

    from flexforce.datasets.robot import FootholdConfig

    motion = Motion(romeo, LEGS, amp=0.01)
    t = T0 + np.arange(300, dtype=np.int64) * 10_000_000
    s = (t - T0) * 1e-9
    forces = np.full((len(t), 2), 200.0)
    forces[(s > 0.8) & (s < 1.5), 0] = 5.0
    topics = robot_topics(romeo, motion, t, forces=forces)
    bag = write_bag(tmp_path / "stair", "mcap", topics)
    flat = import_bag(bag, romeo)  # the legs move a little: the feet land near the floor
    worst = max(abs(d["height_m"]) for d in flat.meta["footholds"]["touch_downs"])
    assert worst > 1e-4
    tight = dataclasses.replace(romeo.config, footholds=FootholdConfig(kinematics_sigma_height=worst / 7.0))
    with pytest.raises(DataError, match=r"contact '\w+_foot' lands .* mm above it by the leg kinematics; "
                                        r"the ground prior .* allows 6 sigma"):
        import_bag(bag, tight)
    loose = dataclasses.replace(romeo.config, footholds=FootholdConfig(terrain="none"))
    assert import_bag(bag, loose).meta["footholds"]["touch_downs"]
